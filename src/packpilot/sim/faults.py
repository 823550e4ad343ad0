"""Scheduled fault injection: what goes wrong, when, on which battery.

Faults act where they would act in reality:

* sensor faults (``sensor_nan``, ``sensor_stuck``, ``sensor_dropout``) corrupt the
  *measurements* between plant and BMS — the plant itself is unaffected;
* switch faults (``welded_relay``, ``shorted_fet``) change the plant's hardware: the switch
  conducts whatever the gate says, and its feedback shows it;
* ``charger_fault`` raises a status flag in the dock; ``can_silence`` drops every frame between
  BMS and charger (so the dock's heartbeat times out and the BMS sees the charger offline);
* ``cooling_failure`` cuts one battery's heat transfer to ambient.

The schedule is the scenario's; a campaign batch applies it to every pack of the batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Protocol

from packpilot.config import FaultConfig, ScenarioConfig
from packpilot.contract.arrays import MeasArrays
from packpilot.contract.charger import CHARGER_FLAGS, ChargerCommand, ChargerLink, ChargerStatus
from packpilot.model.pack import Pack

SENSOR_KINDS = frozenset({"sensor_nan", "sensor_stuck", "sensor_dropout"})


def _active(f: FaultConfig, t_s: float) -> bool:
    return t_s >= f.at_s - 1e-9 and (f.until_s is None or t_s < f.until_s - 1e-9)


class Silenceable(Protocol):
    """A charger link (or all of them, :class:`~packpilot.sim.elcon.ElconLinks`) that a
    ``can_silence`` fault can silence."""

    silenced: bool


@dataclass
class SilenceableLink:
    """Wraps a charger link; while silenced nothing crosses in either direction."""

    inner: ChargerLink
    silenced: bool = False

    def send(self, command: ChargerCommand, t_s: float) -> None:
        if not self.silenced:
            self.inner.send(command, t_s)

    def poll(self, t_s: float) -> ChargerStatus | None:
        status = self.inner.poll(t_s)
        return None if self.silenced else status

    def close(self) -> None:
        self.inner.close()


@dataclass
class FaultInjector:
    """Applies the scenario's ``[[faults]]`` to the plant, the sensors and the charger links."""

    cfg: ScenarioConfig
    pack: Pack
    links: list[Silenceable] = field(default_factory=list)
    stuck: dict[tuple[int, str], Any] = field(default_factory=dict)
    frozen: dict[int, dict[str, Any]] = field(default_factory=dict)
    applied: set[int] = field(default_factory=set)
    cooling: dict[int, bool] = field(default_factory=dict)

    def __post_init__(self) -> None:
        bats = self.cfg.pack.batteries
        self.index = {b.name: i for i, b in enumerate(bats)}
        self.traction = [i for i, b in enumerate(bats) if b.role == "traction"]
        self.has_sensor_faults = any(f.kind in SENSOR_KINDS for f in self.cfg.faults)

    # ------------------------------------------------------------------ plant side
    def before_step(self, t_s: float) -> None:
        pack = self.pack
        for k, f in enumerate(self.cfg.faults):
            on = _active(f, t_s)
            i = self.index.get(f.battery or "", -1)
            if f.kind == "welded_relay":
                pack.welded[i] = on or (k in self.applied and f.until_s is None)
            elif f.kind == "shorted_fet":
                pack.fet_shorted[:, i, 0 if f.fet == "chg" else 1] = on
            elif f.kind == "charger_fault":
                pack.charger.flags[:, CHARGER_FLAGS.index(f.flag)] = on
            elif f.kind == "can_silence":
                for link in self.links:
                    link.silenced = on
            elif f.kind == "cooling_failure":
                self._cooling(i, f, on)
            if on:
                self.applied.add(k)

    def _cooling(self, string: int, f: FaultConfig, on: bool) -> None:
        """Cut (or restore) one battery's heat transfer to ambient, on state changes only."""
        if self.cooling.get(string) == on:
            return
        self.cooling[string] = on
        self.pack.set_cooling(string, f.cooling_factor if on else 1.0)

    # ------------------------------------------------------------------ sensor side
    def filter(self, m: MeasArrays) -> None:
        """Corrupt the measurements of every pack as the active sensor faults dictate."""
        if not self.has_sensor_faults:
            return
        t = float(m.t_s[0])
        bat = m.bat
        for f in self.cfg.faults:
            if f.kind not in SENSOR_KINDS:
                continue
            i = self.index[f.battery or ""]
            if i not in self.traction:
                continue
            k = self.traction.index(i)
            if not _active(f, t):
                self.stuck.pop((k, f.quantity), None)
                self.frozen.pop(k, None)
                continue
            col = getattr(bat, f.quantity)
            if f.kind == "sensor_nan":
                col[:, k] = math.nan
            elif f.kind == "sensor_stuck":
                value = self.stuck.setdefault((k, f.quantity), col[:, k].copy())
                col[:, k] = value
            else:  # dropout: the battery's monitor stops reporting; the last frame repeats
                frame = self.frozen.setdefault(
                    k, {name: arr[:, k].copy() for name, arr in bat._asdict().items()}
                )
                for name, arr in bat._asdict().items():
                    arr[:, k] = frame[name]
                bat.sample_age_s[:, k] = max(t - f.at_s, 0.0)


__all__ = ["FaultInjector", "Silenceable", "SilenceableLink"]
