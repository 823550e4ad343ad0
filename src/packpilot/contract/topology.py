"""The batteries of a pack and the one battery index.

A pack has *strings* (every battery behind its own switch, in config order: what the plant,
the trace and the telemetry index) of which the *traction* batteries are the ones the control
methods manage (their ``battery`` index in commands, status and events); an optional
auxiliary battery powers the BMS. :class:`Topology` is the one place that maps between the
string index, the traction index and the name shown to a user.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from packpilot.contract.bms import SwitchKind


@dataclass(frozen=True, slots=True)
class Topology:
    """Names and roles of a pack's batteries, in config order."""

    names: tuple[str, ...]
    roles: tuple[str, ...]
    """``"traction"`` or ``"aux"`` per string."""

    def __post_init__(self) -> None:
        if len(self.names) != len(self.roles):
            raise ValueError("names and roles must have one entry per battery")
        if sum(r == "aux" for r in self.roles) > 1:
            raise ValueError("at most one auxiliary battery")

    @property
    def n_strings(self) -> int:
        return len(self.names)

    @property
    def traction(self) -> tuple[int, ...]:
        """String index of each traction battery, in traction order."""
        return tuple(i for i, r in enumerate(self.roles) if r != "aux")

    @property
    def aux(self) -> int | None:
        """String index of the auxiliary battery, if any."""
        return next((i for i, r in enumerate(self.roles) if r == "aux"), None)

    @classmethod
    def of_config(cls, config: Mapping[str, Any] | None, names: Sequence[str]) -> Topology:
        """The topology of a recorded run: ``names`` (the trace's batteries) with the roles its
        saved config gives them (a battery the config does not name is traction)."""
        pack = (config or {}).get("pack")
        bats = pack.get("batteries") if isinstance(pack, Mapping) else None
        roles = {
            b.get("name"): b.get("role") or "traction"
            for b in (bats if isinstance(bats, Sequence) else ())
            if isinstance(b, Mapping)
        }
        return cls(tuple(names), tuple(str(roles.get(n, "traction")) for n in names))

    def battery_name(self, battery: int | None) -> str | None:
        """The name of a controller's ``battery`` index (commands, status, events: traction
        batteries only); None for a pack-wide value or an index out of range."""
        traction = self.traction
        if battery is None or not 0 <= battery < len(traction):
            return None
        return self.names[traction[battery]]

    def spread(self, per_traction: Sequence[object], fill: object = None) -> list[object]:
        """A per-traction-battery list laid out over all strings (``fill`` elsewhere)."""
        out = [fill] * self.n_strings
        for k, i in enumerate(self.traction):
            if k < len(per_traction):
                out[i] = per_traction[k]
        return out


@dataclass(frozen=True, slots=True)
class PackInfo:
    """Static facts a controller is built for: its traction batteries (from the pack config)."""

    n_batteries: int
    groups_per_battery: tuple[int, ...]
    cells_per_group: tuple[int, ...]
    switch_kind: tuple[SwitchKind, ...]
    has_aux: bool = False
    has_charger: bool = False
    has_balancers: bool = False
    capacity_ah: tuple[float, ...] = ()
    """Nominal capacity of each battery."""
    ocv_soc: tuple[float, ...] = ()
    ocv_v: tuple[float, ...] = ()
    """The traction cells' open-circuit voltage curve (SOC -> cell volts, at the reference
    temperature), as a BMS has it in its parameter memory; empty when unknown."""
    names: tuple[str, ...] = ()
    """The batteries' configured names (event messages use them); empty: indices."""
    ecm_temp_c: tuple[float, ...] = ()
    ecm_soc: tuple[float, ...] = ()
    """Axes of the traction cells' equivalent-circuit tables at zero current (the observer's
    model, issue #28); empty when unknown (the SOC estimator then runs its fallback only)."""
    ecm_r0_ohm: tuple[float, ...] = ()
    """Cell R0 over (temperature, SOC), temperature-major (len(ecm_temp_c) * len(ecm_soc))."""
    ecm_r1_ohm: tuple[float, ...] = ()
    """Cell R1, same layout."""
    ecm_tau_s: tuple[float, ...] = ()
    """Cell R1 * C1, same layout."""
    ocv_ref_temp_c: float = math.nan
    """The temperature at which ``ocv_v`` holds (degC); NaN: the OCV has no temperature term."""
    ocv_dudt_temp_c: tuple[float, ...] = ()
    """Temperature axis of the OCV's entropic coefficient ..."""
    ocv_dudt_v_per_k: tuple[float, ...] = ()
    """... dOCV/dT (V/K) at each temperature of that axis and each point of ``ocv_soc``,
    temperature-major: the cell's OCV at T is ``ocv_v + (T - ocv_ref_temp_c) * dudt`` (the
    plant's entropic term, issue #28); empty: none."""
    balancer_max_a: float = 0.0
    """The equalizers' current limit per group (A; 0: no equalizers) ..."""
    balancer_bidirectional: bool = False
    """... whether they can also take charge out of a group ..."""
    balancer_efficiency: float = 1.0
    """... and their efficiency: a group's equalizer current is drawn from its own string as
    power (the observer counts both, issue #28)."""
    cell_v_min_v: float = 2.5
    """The traction cells' lower voltage limit (the cell set's ``v_min_v``)."""
    cell_v_max_v: float = math.nan
    """Their upper voltage limit (the cell set's ``v_max_v``; NaN: unknown)."""
    r_scale: tuple[float, ...] = ()
    """Per battery, the stated resistance as a factor on the cell tables (1: the tables;
    empty: 1 for every battery)."""
    charge_path_ohm: tuple[float, ...] = ()
    """Per battery, the resistance between the charger's regulation point and the battery's
    cells while charging (ohm): its switch's charge path plus its share of the charger's
    output slope (the charger's stated load regulation, over the batteries it feeds). A CC/CV
    charger's constant voltage reaches the cells lowered by this times the current (the time
    to full, issue #28); empty: 0 for every battery."""


__all__ = ["PackInfo", "Topology"]
