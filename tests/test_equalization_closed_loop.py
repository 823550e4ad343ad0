"""Closed loop on the plant: the method never loses usable Ah against no balancing."""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

from packpilot.config import parse_config
from packpilot.contract.bms import Commands, Controller, ControlOutput, Measurements, NullController
from packpilot.contract.charger import ChargerCommand
from packpilot.control.equalization import EqualizationConfig, EqualizationController
from packpilot.model import loads
from packpilot.sim.runner import Runner
from tests.budget import budget
from tests.compose import ComposedController

CUTOFF_V = 3.0
LOAD_A = 20.0


class _Done(Exception):
    """Ends a run from a hook once the harness has its cycles."""


@dataclass
class Cycler:
    """Harness: discharge to the first group's cut-off, CC/CV recharge (limited by the first
    group reaching 4.2 V) to taper, repeat."""

    n_groups: int
    cycles: int
    phase: str = "discharge"
    ah: float = 0.0
    taper_s: float = 0.0
    done: bool = False

    def __post_init__(self) -> None:
        self.usable: list[float] = []

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        b = meas.batteries[0]
        if self.phase == "discharge":
            self.ah += b.current_a * dt_s / 3600.0
            if min(b.group_voltages_v) <= CUTOFF_V:
                self.usable.append(self.ah)
                self.done = len(self.usable) >= self.cycles
                self.phase, self.ah, self.taper_s = "charge", 0.0, 0.0
        else:
            self.taper_s = self.taper_s + dt_s if -b.current_a < 0.5 else 0.0
            if self.taper_s >= 30.0:
                self.phase = "discharge"
        on = self.phase == "charge"
        # CC/CV on the string, with the voltage lowered so that no group exceeds 4.2 V: the
        # cell-level limit any BMS enforces (without it an unbalanced string "wins" Ah by
        # overcharging its leading cell).
        v_set = min(4.2 * self.n_groups, b.voltage_v + (4.2 - max(b.group_voltages_v)))
        cmd = ChargerCommand(v_set, 10.0, enable=on)
        return ControlOutput(commands=Commands(charger=cmd))

    def hook(self, runner: Runner, t_s: float) -> None:
        if self.done:
            raise _Done
        runner.profile = loads.constant("current" if self.phase == "discharge" else "none", LOAD_A)


def usable_ah(
    caps: list[float], socs: list[float], eq: EqualizationConfig | None, cycles: int = 2
) -> list[float]:
    n = len(caps)
    data: dict[str, Any] = {
        "pack": {
            "cell": "uav_5ah",
            "switch": {"kind": "relay", "on_ohm": 0.0},
            "batteries": [
                {
                    "name": "s",
                    "series_groups": n,
                    "group_capacity_scale": caps,
                    "group_soc0": socs,
                }
            ],
        },
        "charger": {"present": True, "rated_v": 60.0, "rated_a": 10.0},
        "balancer": {"present": eq is not None, "max_current_a": 1.0, "efficiency": 0.9},
        "sim": {"dt_s": 5.0, "duration_s": 40000.0, "progress": False},
    }
    cfg = parse_config(data)
    cycler = Cycler(n, cycles)
    runner = Runner(cfg, controller=NullController(), hooks=[cycler.hook])
    method: Controller = NullController() if eq is None else EqualizationController(eq, runner.info)
    runner.controller = ComposedController([cycler, method])
    with contextlib.suppress(_Done):
        runner.run()
    return cycler.usable


EQ = EqualizationConfig(
    sample_period_s=5.0,
    time_mode="fixed_current",
    fixed_current_a=0.5,
    equalizer_max_a=1.0,
    balance_at_rest=True,
    n_ah=0.05,
)


def test_balancing_recovers_capacity_on_a_known_string() -> None:
    caps = [1.0, 0.95, 1.05]
    socs = [0.95, 0.85, 0.9]
    base = usable_ah(caps, socs, None)
    eq = usable_ah(caps, socs, EQ)
    # Without balancing the SOC offsets are conserved, so the weakest group (0.95 × 5 Ah) is
    # never used fully; the method recovers it by the second cycle.
    assert base[1] < 0.96 * 4.75
    assert eq[1] > base[1] + 0.15
    assert eq[1] > 0.98 * 4.75


# ci 24 (was a fixed 8): a closed loop, ~0.5 s per example on the loaded 2-core box, so 200
# would add ~100 s to `make test`; see docs/safety.md §5. Soak (nightly): 10,000.
@budget(24, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
@given(
    caps=st.lists(st.floats(0.9, 1.1), min_size=3, max_size=3),
    socs=st.lists(st.floats(0.6, 1.0), min_size=3, max_size=3),
    mode=st.sampled_from(["fixed_current", "string_current"]),
)
def test_usable_ah_never_below_no_balancing(
    caps: list[float], socs: list[float], mode: str
) -> None:
    eq = EQ.model_copy(update={"time_mode": mode, "balance_at_rest": mode == "fixed_current"})
    base = usable_ah(caps, socs, None)
    got = usable_ah(caps, socs, eq)
    # One control step of load current is the resolution of the cut-off detection.
    tol = LOAD_A * 5.0 / 3600.0
    assert np.all(np.array(got) >= np.array(base) - tol), (base, got)
