"""Baselines the benchmarks compare the control methods with (not production methods).

:class:`PassiveTopBalancer` is the classic passive top balancer that ``bench_equalization.py``
runs against the Newton-iterated equalizer (``packpilot.control.equalization``): a plain scalar
controller over the scalar contract.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
)
from packpilot.contract.topology import PackInfo


def _input_problem(bm: BatteryMeasurement, n_groups: int) -> str | None:
    """Why this battery's inputs cannot drive the balancer, or None (the equalizer's checks:
    group voltages and string current only)."""
    if len(bm.group_voltages_v) != n_groups:
        return f"expected {n_groups} group voltages, got {len(bm.group_voltages_v)}"
    for g, v in enumerate(bm.group_voltages_v):
        if not math.isfinite(v) or v <= 0.0:
            return f"group {g} voltage {v} is not a positive finite number"
    if not math.isfinite(bm.current_a):
        return f"string current {bm.current_a} is not finite"
    return None


class PassiveTopBalancerConfig(BaseModel):
    """A classic passive top balancer, the baseline the method is compared with: a bleed
    resistor across each group, switched on while the group is above a voltage threshold and
    above the lowest group of its string, only while the string charges or rests."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    threshold_cell_v: float = Field(
        3.40,
        description="Per-cell voltage above which a group may bleed (group threshold = "
        "cells_per_group × this). 3.40 V suits LFP; use ~4.15 V for NMC/LCO.",
    )
    delta_cell_v: float = Field(
        0.005,
        description="Per-cell margin: a group bleeds only if it is more than cells_per_group "
        "× this above the lowest group of its string.",
    )
    bleed_ohm: float = Field(10.0, description="Bleed resistance across one group (Ω).")
    max_discharge_a: float = Field(
        0.5,
        description="Bleeding is allowed only while the string current is below this (A, "
        "positive = discharge): charging or at rest, i.e. top balancing.",
    )

    @field_validator("threshold_cell_v", "bleed_ohm")
    @classmethod
    def _positive(cls, v: float, info: ValidationInfo) -> float:
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"{info.field_name} must be a positive number (got {v})")
        return v

    @field_validator("delta_cell_v", "max_discharge_a")
    @classmethod
    def _non_negative(cls, v: float, info: ValidationInfo) -> float:
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"{info.field_name} must be >= 0 (got {v})")
        return v


class PassiveTopBalancer:
    """Bleed-resistor baseline: commands ``balancer_a = −V_g/R`` for the groups it bleeds.

    A negative balancer current is "out of the group". On the plant this is a bidirectional
    balancer whose returned energy is wasted (``[balancer] bidirectional = true`` with a
    negligible ``efficiency``), which is what a resistor does. Invalid inputs stop bleeding
    and raise one ``Fault`` event, as the equalizer does.
    """

    def __init__(self, config: PassiveTopBalancerConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.faulted = [False] * pack.n_batteries
        self.bled_ah = [[0.0] * m for m in pack.groups_per_battery]
        """Charge bled from each group (Ah), for tests and benchmarks."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        cfg = self.config
        dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
        events: list[Event] = []
        currents: list[tuple[float, ...]] = []
        for b, m in enumerate(self.pack.groups_per_battery):
            bm = meas.batteries[b] if b < len(meas.batteries) else None
            zero = (0.0,) * m
            if bm is None or not bm.present:
                currents.append(zero)
                continue
            problem = _input_problem(bm, m)
            if problem is not None:
                if not self.faulted[b]:
                    events.append(
                        Event(
                            t_s=meas.t_s,
                            kind="Fault",
                            battery=b,
                            message=f"passive balancing stopped: {problem}",
                            data={"source": "passive_balancer"},
                        )
                    )
                self.faulted[b] = True
                currents.append(zero)
                continue
            self.faulted[b] = False
            if bm.current_a >= cfg.max_discharge_a or m < 2:
                currents.append(zero)
                continue
            cells = self.pack.cells_per_group[b] if b < len(self.pack.cells_per_group) else 1
            gv = bm.group_voltages_v
            floor = min(gv) + cells * cfg.delta_cell_v
            out = []
            for g, v in enumerate(gv):
                bleed = v > cells * cfg.threshold_cell_v and v > floor
                i = -v / cfg.bleed_ohm if bleed else 0.0
                self.bled_ah[b][g] += -i * dt / 3600.0
                out.append(i)
            currents.append(tuple(out))
        balancer = tuple(currents) if self.pack.has_balancers else None
        status: dict[str, list[float | int | str | bool | None]] = {
            "passive_bleeding": [sum(1 for x in c if x < 0.0) for c in currents]
        }
        return ControlOutput(
            commands=Commands(balancer_a=balancer), events=tuple(events), status=status
        )


__all__ = ["PassiveTopBalancer", "PassiveTopBalancerConfig"]
