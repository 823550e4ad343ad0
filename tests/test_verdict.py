"""Issue #17 §1: every event kind has a severity; a run's verdict and alarms table come from the
events and from physics checks on the trace, the same for the CLI, the report and the dashboard.
"""

from __future__ import annotations

import math
import tomllib
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.contract.severity import EVENT_SEVERITY, Severity, row_of
from packpilot.contract.topology import Topology
from packpilot.control.method import Method
from packpilot.control.registry import REGISTRY
from packpilot.control.supervisor import controller as supervisor
from packpilot.io.can.plant import PORT_EVENT_KINDS
from packpilot.sim.loop import LOOP_EVENT_KINDS
from packpilot.sim.runner import Runner
from packpilot.sim.verdict import (
    EventAlarms,
    PhysicsLimits,
    PhysicsWatch,
    parse_fail_on,
    run_verdict,
)
from tests.conftest import EXAMPLES

# --------------------------------------------------------------------------- the table


def emitted_kinds() -> set[str]:
    """Every event kind the registry's methods, the supervisor, the loop and the CAN
    runtime's port can emit."""
    kinds = {r.kind for r in supervisor.REASONS} | set(LOOP_EVENT_KINDS) | set(PORT_EVENT_KINDS)
    for entry in REGISTRY.values():
        method = entry.resolve()
        assert isinstance(method, Method), entry.name
        kinds |= {r.kind for r in method.reasons}
    return kinds


def test_every_emitted_event_kind_has_a_severity_row() -> None:
    missing = emitted_kinds() - set(EVENT_SEVERITY)
    assert not missing, f"event kinds without a row in contract/severity.py: {sorted(missing)}"


def test_the_table_has_no_row_for_a_kind_nothing_emits() -> None:
    stale = set(EVENT_SEVERITY) - emitted_kinds()
    assert not stale, f"rows for kinds nothing emits: {sorted(stale)}"


def test_clearing_kinds_exist_and_unknown_kinds_are_visible() -> None:
    for kind, row in EVENT_SEVERITY.items():
        assert row.cleared_by is None or row.cleared_by in EVENT_SEVERITY, kind
        assert (row.severity > Severity.INFO) == bool(row.category), kind
    assert row_of("SomethingNew").severity == Severity.WARNING


# --------------------------------------------------------------------------- events


def topo() -> Topology:
    # the aux battery sits between A and B: event index 1 must still name B
    return Topology(("A", "aux", "B"), ("traction", "aux", "traction"))


def test_event_alarms_name_batteries_and_track_clearing() -> None:
    watch = EventAlarms(topo())
    watch.feed(
        [
            Event(1.0, "ProtectionTripped", 1, "tripped under P2"),
            Event(2.0, "StateChanged", 0, "routine"),
            Event(3.0, "Fault", 1, "nonfinite: temp_c", {"kind": "nonfinite", "field": "temp_c"}),
            Event(4.0, "Fault", 1, "nonfinite: temp_c", {"kind": "nonfinite", "field": "temp_c"}),
            Event(5.0, "ProtectionReset", 1, "new cycle"),
            Event(6.0, "FaultCleared", 1, "stale cleared", {"kind": "stale", "field": "temp_c"}),
        ]
    )
    rows = {a.kind: a for a in watch.alarms()}
    assert set(rows) == {"ProtectionTripped", "Fault"}  # the routine event is not an alarm
    trip, fault = rows["ProtectionTripped"], rows["Fault"]
    assert trip.battery == "B" and trip.cleared_t_s == 5.0 and trip.category == "trip"
    assert fault.battery == "B" and fault.count == 2 and fault.t_s == 3.0
    assert not fault.cleared  # a different kind of fault was cleared, not this one


# --------------------------------------------------------------------------- physics


def trace(n: int, soc: list[float], cell_v: list[float], current_a: list[float]) -> Any:
    col = {c: i for i, c in enumerate(BATTERY_CHANNELS)}
    bat = np.zeros((n, len(soc), len(BATTERY_CHANNELS)))
    bat[:, :, col["soc"]] = soc
    bat[:, :, col["min_cell_v"]] = cell_v
    bat[:, :, col["current_a"]] = current_a
    bat[:, :, col["full_ah"]] = 5.0
    return np.arange(n) * 0.5, bat


def limits() -> PhysicsLimits:
    return PhysicsLimits(("A", "B"), (True, True), (2.5, 2.5), charge_c=2.0)


def test_physics_checks_flag_each_condition_once_with_its_worst_value() -> None:
    t, bat = trace(10, [0.5, 0.5], [3.6, 3.6], [5.0, -5.0])
    bat[4:7, 1, BATTERY_CHANNELS.index("current_a")] = -39.5  # 7.9C into a 5 Ah battery
    bat[8:, 0, BATTERY_CHANNELS.index("soc")] = -0.018
    bat[9, 0, BATTERY_CHANNELS.index("min_cell_v")] = 2.41
    demand, load = np.full(10, 10.0), np.full(10, 10.0)
    load[2] = 0.0
    watch = PhysicsWatch(limits())
    watch.feed(t, bat, demand, load, np.zeros(10))
    rows = {(a.kind, a.battery, a.severity): a for a in watch.alarms()}
    cross = rows[("CrossCharge", "B", Severity.ALARM)]
    assert cross.t_s == 2.0 and cross.cleared_t_s == 3.5 and "39.5 A" in cross.cause
    assert "-1.8 %" in rows[("OverDischarge", "A", Severity.WARNING)].cause
    assert "2.410 V" in rows[("OverDischarge", "A", Severity.ALARM)].cause
    loss = rows[("LoadLoss", None, Severity.ALARM)]
    assert loss.t_s == 1.0 and loss.cleared_t_s == 1.5 and loss.category == "unsupplied"
    assert len(rows) == 4


def test_charging_from_a_charger_is_not_cross_charge() -> None:
    t, bat = trace(4, [0.5, 0.5], [3.6, 3.6], [-30.0, -30.0])
    watch = PhysicsWatch(limits())
    watch.feed(t, bat, np.zeros(4), np.zeros(4), np.full(4, 60.0))
    assert watch.alarms() == []


def test_chunked_feed_equals_one_feed() -> None:
    """The dashboard feeds a few samples at a time, the report the whole trace: same rows."""
    rng = np.random.default_rng(3)
    n = 400
    t, bat = trace(n, [0.5, 0.5], [3.6, 3.6], [0.0, 0.0])
    bat[:, :, BATTERY_CHANNELS.index("current_a")] = rng.normal(0, 12, (n, 2))
    bat[:, :, BATTERY_CHANNELS.index("soc")] = rng.normal(0.05, 0.05, (n, 2))
    demand, load = np.full(n, 10.0), 10.0 - np.clip(rng.normal(0, 1, n), 0, None)
    whole = PhysicsWatch(limits())
    whole.feed(t, bat, demand, load, np.zeros(n))
    parts = PhysicsWatch(limits())
    for lo in range(0, n, 37):
        sl = slice(lo, lo + 37)
        parts.feed(t[sl], bat[sl], demand[sl], load[sl], np.zeros(n)[sl])
    assert whole.alarms() == parts.alarms()
    assert len(whole.alarms()) > 3


def test_fail_on_categories_are_checked() -> None:
    assert parse_fail_on("trip, fault,unsupplied,overdischarge") == [
        "trip", "fault", "unsupplied", "overdischarge",
    ]  # fmt: skip
    with pytest.raises(Exception, match="unknown category tirp"):
        parse_fail_on("tirp")


# --------------------------------------------------------------------------- the runs


def run(data: dict[str, Any], duration_s: float | None = None) -> Any:
    if duration_s is not None:
        data["sim"]["duration_s"] = duration_s
    data["sim"]["progress"] = False
    cfg = parse_config(data)
    result = Runner(cfg, progress=False).run()
    return run_verdict(result, cfg.model_dump(mode="json"))


def example(name: str) -> dict[str, Any]:
    with (EXAMPLES / f"{name}.toml").open("rb") as fh:
        return tomllib.load(fh)


def test_smart_battery_below_empty_warns() -> None:
    """The issue: smart_battery ends at -1.8 % SOC and nothing said so."""
    v = run(example("smart_battery"))
    assert v.word != "OK"
    over = [a for a in v.alarms if a.category == "overdischarge"]
    assert over and over[0].battery == "main" and "SOC below 0 %" in over[0].cause


def test_uav_dual_parallel_cross_charge_alarms() -> None:
    """The issue: ~40 A into a 5 Ah battery and the report said "ok"."""
    v = run(example("uav_dual_parallel"), duration_s=10.0)
    assert v.word == "ALARM"
    cross = [a for a in v.alarms if a.category == "crosscharge"]
    assert cross and cross[0].battery in ("A", "B") and cross[0].source == "physics"
    worst = float(cross[0].cause.split("cross-charge ")[1].split(" A")[0])
    assert worst > 30.0


def test_uav_mission_with_sensor_nan_and_can_silence_is_a_fault() -> None:
    """The issue: NaN on B's temperature at 300 s and CAN silence at 2000-2100 s said "ok"."""
    data = example("uav_mission")
    data["faults"] = [
        {"kind": "sensor_nan", "at_s": 300.0, "battery": "B", "quantity": "temp_c"},
        {"kind": "can_silence", "at_s": 2000.0, "until_s": 2100.0},
    ]
    v = run(data, duration_s=2200.0)
    assert v.word == "FAULT"
    faults = [a for a in v.alarms if a.category == "fault"]
    assert any(a.battery == "B" and math.isclose(a.t_s, 300.0, abs_tol=2.0) for a in faults)
    assert any(a.t_s >= 2000.0 for a in faults)  # the charger link went silent
