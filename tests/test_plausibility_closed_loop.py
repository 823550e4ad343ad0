"""On the real plant: a welded relay and a shorted FET are detected from the switch feedback,
and a hot-spot sensor NaN isolates the faulty battery while the other keeps the load supplied."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import reduce
from typing import Any

from packpilot.config import parse_config
from packpilot.contract.bms import Commands, ControlOutput, Measurements
from packpilot.contract.record import Result
from packpilot.contract.topology import PackInfo
from packpilot.control.limits import LimitsConfig, LimitsController
from packpilot.control.plausibility import PlausibilityConfig, PlausibilityMonitor
from packpilot.sim.runner import Runner
from tests.compose import merge_commands
from tests.conftest import dual_pack


class Supervisor:
    """The composition docs/safety.md describes, plus a scripted 'method' command."""

    def __init__(
        self, info: PackInfo, script: dict[float, Commands], corrupt: bool = False
    ) -> None:
        self.limits = LimitsController(LimitsConfig(), info)
        self.plaus = PlausibilityMonitor(PlausibilityConfig(), info)
        self.script = script
        self.method = Commands()
        self.corrupt = corrupt

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        if self.corrupt and meas.t_s >= 2.0:  # battery A's temperature sensor dies
            bad = replace(meas.batteries[0], temp_c=math.nan)
            meas = replace(meas, batteries=(bad, *meas.batteries[1:]))
        for t, cmd in self.script.items():
            if abs(meas.t_s - t) < 1e-6:
                self.method = cmd
        outs = [self.plaus.step(meas, dt_s), self.limits.step(meas, dt_s)]
        merged = reduce(merge_commands, [self.method, *(o.commands for o in outs)], Commands())
        self.plaus.note_commands(merged)
        events = tuple(e for o in outs for e in o.events)
        return ControlOutput(merged, events, {k: v for o in outs for k, v in o.status.items()})


def _run(
    cfg_dict: dict[str, Any],
    script: dict[float, Commands],
    corrupt: bool = False,
    hooks: Sequence[Callable[[Runner, float], None]] = (),
) -> tuple[Result, Supervisor]:
    cfg = parse_config(cfg_dict)
    runner = Runner(cfg, progress=False, hooks=hooks)
    sup = Supervisor(runner.info, script, corrupt)
    runner.controller = sup
    return runner.run(), sup


def test_welded_relay_is_detected_on_the_plant() -> None:
    d = dual_pack(switch={"kind": "relay", "on_ohm": 0.0}, v_a=23.0, v_b=23.0, duration_s=5.0)
    d["pack"]["batteries"][0]["switch"] = {"kind": "relay", "on_ohm": 0.0, "welded": True}
    d["load"] = {"kind": "current", "value": 10.0}
    result, sup = _run(
        d, {0.0: Commands((True, True), (True, True)), 1.0: Commands((False, True), (False, True))}
    )
    faults = [e for e in result.events if e.kind == "Fault"]
    assert [(e.battery, e.data["kind"]) for e in faults] == [(0, "relay_welded")]
    assert 1.5 <= faults[0].t_s <= 1.75  # commanded open at 1.0 s, feedback lags one period
    assert sup.plaus.welded == (True, False)


def test_shorted_charge_fet_is_detected_on_the_plant() -> None:
    d = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0001}, v_a=23.0, v_b=23.0, duration_s=4.0
    )

    def short(runner: Runner, t: float) -> None:
        runner.pack.fet_shorted[0, 1, 0] = t >= 1.0  # battery B's charge FET fails short

    result, _ = _run(d, {0.0: Commands((True, False), (True, True))}, hooks=[short])
    faults = [e for e in result.events if e.kind == "Fault"]
    assert [(e.battery, e.data["kind"]) for e in faults] == [(1, "chg_fet_shorted")]


def test_dead_sensor_isolates_the_battery_and_the_other_supplies() -> None:
    d = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0001}, v_a=23.0, v_b=23.0, duration_s=6.0
    )
    d["load"] = {"kind": "current", "value": 10.0}
    result, _ = _run(d, {0.0: Commands((True, True), (True, True))}, corrupt=True)
    faults = [e for e in result.events if e.kind == "Fault"]
    assert [(e.battery, e.data["kind"], e.data["field"]) for e in faults] == [
        (0, "nonfinite", "temp_c")
    ]
    current = result.trace.channel("current_a")
    assert abs(current[-1, 0]) < 1e-6  # A isolated
    assert current[-1, 1] > 9.0  # B carries the load
    assert result.metrics["load_unsupplied_s"] == 0.0
