"""Every injectable fault is detected within its delay, the pack reaches its safe state, the
run completes and the telemetry records the fault (docs/fault_injection.md lists the table)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.bms import Commands, ControlOutput, Measurements
from packpilot.contract.record import Result
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.sim.runner import Runner
from tests.conftest import dual_pack


def _flight(fault: dict[str, Any], duration_s: float = 40.0, **kw: Any) -> dict[str, Any]:
    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=24.0,
        v_b=23.9,
        duration_s=duration_s,
        load={"kind": "current", "value": 30.0},
        **kw,
    )
    d["controller"] = ["sequencing", "protection"]
    d["supervisor"] = {}
    d["limits"] = {}
    d["plausibility"] = {"stuck_time_s": 10.0}
    d["faults"] = [fault]
    return d


def _dock(fault: dict[str, Any], duration_s: float = 60.0) -> dict[str, Any]:
    d = dual_pack(switch={"kind": "relay"}, v_a=22.6, v_b=22.4, duration_s=duration_s, dt_s=0.5)
    for b in d["pack"]["batteries"]:  # 6 series groups of one cell: balancer-ready batteries
        b.update(series_groups=6, cells_per_group=1)
    d["charger"] = {"present": True, "rated_v": 60.0, "rated_a": 20.0}
    d["controller"] = ["charging"]
    d["charging"] = {"voltage_basis": "cell", "v_sat_v": 4.2, "charger_current_limit_a": 5.0}
    d["supervisor"] = {}
    d["limits"] = {}
    d["plausibility"] = {}
    d["faults"] = [fault]
    return d


def _run(d: dict[str, Any], tmp_path: Path, controller: Any = None) -> Result:
    db = tmp_path / "run.sqlite"
    with SQLiteRecorder(db) as rec:
        runner = Runner(parse_config(d), recorder=rec, progress=False)
        if controller is not None:
            runner.controller = controller(runner)
        result = runner.run()
    stored = load_run(db)
    assert stored.metrics["steps"] == result.metrics["steps"]  # the run completed
    assert [e.kind for e in stored.events] == [e.kind for e in result.events]
    return result


def _first(result: Result, event_kind: str, **data: Any) -> float:
    for e in result.events:
        if e.kind == event_kind and all(e.data.get(k) == v for k, v in data.items()):
            return e.t_s
    raise AssertionError(
        f"no {event_kind} event with {data}: {[(e.kind, dict(e.data)) for e in result.events]}"
    )


def _first_or_inf(result: Result, event_kind: str, **data: Any) -> float:
    try:
        return _first(result, event_kind, **data)
    except AssertionError:
        return float("inf")


def _at(result: Result, t_s: float) -> int:
    return int(np.searchsorted(result.trace.t_s, t_s))


def test_sensor_nan_isolates_the_battery_and_the_load_stays_supplied(tmp_path: Path) -> None:
    res = _run(_flight({"kind": "sensor_nan", "at_s": 10.0, "battery": "B"}), tmp_path)
    t = _first(res, "Fault", kind="nonfinite")
    assert 10.0 <= t <= 10.0 + 0.5 + 0.2  # nonfinite_delay_s + a period
    k = _at(res, t + 0.5)
    assert res.trace.channel("chg_on")[k:, 1].max() == 0.0  # B cannot be charged any more
    assert res.metrics["load_unsupplied_s"] == 0.0


@pytest.mark.parametrize("kind", ["sensor_stuck", "sensor_dropout"])
def test_frozen_sensor_is_detected_as_stuck(tmp_path: Path, kind: str) -> None:
    res = _run(_flight({"kind": kind, "at_s": 5.0, "battery": "A"}), tmp_path)
    # A frozen battery voltage also disagrees with its (live) group voltages: whichever check
    # sees it first, it must be seen within stuck_time_s.
    kinds = ("stuck", "voltage_sum", "stale")
    t = min(_first_or_inf(res, "Fault", kind=k, battery=0) for k in kinds)
    assert 5.0 < t <= 5.0 + 10.0 + 0.3  # stuck_time_s under current
    assert res.metrics["load_unsupplied_s"] == 0.0


def test_sensor_dropout_at_rest_is_detected_as_stale(tmp_path: Path) -> None:
    """No current, so nothing looks stuck: the repeated frame's age gives the dropout away."""
    d = _flight({"kind": "sensor_dropout", "at_s": 5.0, "battery": "A"})
    d["load"] = {"kind": "none"}
    res = _run(d, tmp_path)
    t = _first(res, "Fault", kind="stale", battery=0)
    assert 5.0 + 2.0 < t <= 5.0 + 2.0 + 0.3  # max_sample_age_s + a period


def test_shorted_charge_fet_is_detected_from_switch_feedback(tmp_path: Path) -> None:
    # B stands by (charge FET off) while A discharges; its charge FET fails short at 5 s.
    d = _flight({"kind": "shorted_fet", "at_s": 5.0, "battery": "B", "fet": "chg"})
    d["pack"]["batteries"][1]["ocv0_v"] = 22.5  # > v_th below A: B stands by
    res = _run(d, tmp_path)
    t = _first(res, "Fault", kind="chg_fet_shorted")
    assert 5.0 <= t <= 5.0 + 0.5 + 0.2  # switch_delay_s + a period


class _OpenAt:
    """A method that opens battery A's relay at 5 s (so a welded contact shows)."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        n = len(meas.batteries)
        if meas.t_s >= 5.0:
            return ControlOutput(
                Commands(chg_on=(False,) + (None,) * (n - 1), dsg_on=(False,) + (None,) * (n - 1))
            )
        return ControlOutput(Commands())


def test_welded_relay_is_detected_when_commanded_open(tmp_path: Path) -> None:
    from packpilot.control.plausibility import PlausibilityConfig, PlausibilityMonitor
    from packpilot.control.supervisor import Supervisor, SupervisorConfig

    d = dual_pack(
        switch={"kind": "relay"},
        v_a=23.0,
        v_b=23.0,
        duration_s=10.0,
        load={"kind": "current", "value": 10.0},
    )
    d["faults"] = [{"kind": "welded_relay", "at_s": 1.0, "battery": "A"}]
    d["plausibility"] = {}

    def build(runner: Runner) -> Supervisor:
        return Supervisor(
            SupervisorConfig(),
            runner.info,
            methods=[_OpenAt()],
            safety=[PlausibilityMonitor(PlausibilityConfig(), runner.info)],
        )

    res = _run(d, tmp_path, controller=build)
    t = _first(res, "Fault", kind="relay_welded")
    assert 5.0 <= t <= 5.0 + 0.5 + 0.2
    assert res.trace.channel("current_a")[-1, 0] > 0.0  # welded: it still conducts, flagged


class _DsgOffAt:
    """A method that turns battery B's discharge FET off at 5 s (so a shorted FET shows)."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        if meas.t_s >= 5.0:
            return ControlOutput(Commands(dsg_on=(None, False)))
        return ControlOutput(Commands())


def test_shorted_discharge_fet_is_flagged_and_the_run_goes_on(tmp_path: Path) -> None:
    from packpilot.control.plausibility import PlausibilityConfig, PlausibilityMonitor
    from packpilot.control.supervisor import Supervisor, SupervisorConfig

    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=23.0,
        v_b=23.0,
        duration_s=10.0,
        load={"kind": "current", "value": 10.0},
    )
    d["faults"] = [{"kind": "shorted_fet", "at_s": 1.0, "battery": "B", "fet": "dsg"}]
    d["plausibility"] = {}

    def build(runner: Runner) -> Supervisor:
        return Supervisor(
            SupervisorConfig(),
            runner.info,
            methods=[_DsgOffAt()],
            safety=[PlausibilityMonitor(PlausibilityConfig(), runner.info)],
        )

    res = _run(d, tmp_path, controller=build)
    t = _first(res, "Fault", kind="dsg_fet_shorted", battery=1)
    assert 5.0 <= t <= 5.0 + 0.5 + 0.2  # switch_delay_s + a period
    assert res.trace.channel("current_a")[-1, 1] > 0.0  # shorted: B still discharges, flagged
    assert res.metrics["load_unsupplied_s"] == 0.0


def test_charger_fault_flag_stops_charging_and_opens_relays(tmp_path: Path) -> None:
    res = _run(_dock({"kind": "charger_fault", "at_s": 20.0, "flag": "hardware_failure"}), tmp_path)
    k0 = _at(res, 19.0)
    assert res.trace.charger_a[k0] > 1.0  # it was charging
    t = _first(res, "Fault")
    assert 20.0 <= t <= 21.0
    k = _at(res, t + 1.0)
    assert np.all(res.trace.charger_a[k:] == 0.0)
    assert np.all(res.trace.channel("chg_on")[k:] == 0.0)  # relays open


def test_can_silence_times_out_the_charger_and_the_bms_notices(tmp_path: Path) -> None:
    res = _run(_dock({"kind": "can_silence", "at_s": 20.0}), tmp_path)
    # The dock stops its output within its 5 s heartbeat timeout ...
    k = _at(res, 20.0 + 5.0 + 0.5)
    assert res.trace.charger_a[_at(res, 19.0)] > 1.0
    assert np.all(res.trace.charger_a[k:] == 0.0)
    # ... and the BMS raises an event once the charger has been silent for its timeout.
    t = _first(res, "Fault")
    assert 20.0 < t <= 20.0 + 5.0 + 5.0 + 1.0


def test_cooling_failure_trips_over_temperature_on_that_battery(tmp_path: Path) -> None:
    d = _flight(
        {"kind": "cooling_failure", "at_s": 0.0, "battery": "A", "cooling_factor": 0.01},
        duration_s=700.0,
        dt_s=0.5,
    )
    d["pack"]["ambient_c"] = 40.0
    d["pack"]["batteries"][1]["ocv0_v"] = 24.0
    for bat in d["pack"]["batteries"]:  # the stated resistances hold at this hot ambient
        bat["resistance_temp_c"] = 40.0  # (#27: else they hold at 25 degC, less heat at 40)
    d["load"] = {"kind": "current", "value": 50.0}
    res = _run(d, tmp_path)
    trip = next(e for e in res.events if e.kind == "LimitTripped")
    assert trip.battery == 0 and "over_temp" in trip.message, trip
    t = trip.t_s
    k = _at(res, t + 1.0)
    assert res.trace.channel("dsg_on")[k, 0] == 0.0  # A isolated
    temp = res.trace.channel("temp_c")
    assert temp[:k, 0].max() > temp[:k, 1].max() + 5.0


# ------------------------------------------------------------------ degraded mode (#15 §5)


def _reserve_flight(switch: str) -> dict[str, Any]:
    """B's temperature sensor fails at 2 s while A is connected: B becomes the reserve, A
    carries the 30 A load alone until a trip opens it. MOSFET pairs: a nearly empty A and a
    full B (A connected in standby, its charge diode conducting); relays: both nearly empty
    and equal (a relay connects a battery only while it is admitted)."""
    d = _flight({"kind": "sensor_nan", "at_s": 2.0, "battery": "B", "quantity": "temp_c"},
                duration_s=60.0)  # fmt: skip
    d["pack"]["switch"] = {"kind": switch}
    socs = (0.04, 0.9) if switch == "mosfet_pair" else (0.06, 0.06)
    for bat, soc0 in zip(d["pack"]["batteries"], socs, strict=True):
        del bat["ocv0_v"]
        bat["soc0"] = soc0
    return d


def _first_trip(result: Result) -> float:
    """When A's path was opened by a trip (protection's or the safety limits', whichever first)."""
    return min(_first_or_inf(result, "ProtectionTripped"), _first_or_inf(result, "LimitTripped"))


@pytest.mark.parametrize("switch", ["mosfet_pair", "relay"])
def test_the_reserve_is_brought_in_by_the_step_that_opens_the_last_trusted_source(
    tmp_path: Path, switch: str
) -> None:
    """Make-before-break: the load never goes unsupplied while B still has energy, because
    plausibility lifts B's isolation in the very step protection opens A (it sees this step's
    commands, not only last step's feedback); the platform is told by ``ReserveEngaged``."""
    res = _run(_reserve_flight(switch), tmp_path)
    trip = _first_trip(res)
    assert trip < 50.0
    assert _first(res, "ReserveEngaged", battery=1) == pytest.approx(trip)
    k, kt = _at(res, 3.0), _at(res, trip)
    assert res.trace.channel("current_a")[k:kt, 1].max() == pytest.approx(0.0)  # held back
    assert res.trace.load_a[: kt + 50].min() > 29.9  # never unsupplied through the hand-over
    assert _first_or_inf(res, "LoadUnsupplied") > trip + 5.0


def test_a_tripped_battery_cannot_be_charged_by_the_reserve_that_replaces_it(
    tmp_path: Path,
) -> None:
    """Sequencing opens the charge FET of a battery whose discharge FET another layer opened,
    in the same step (embodiments 5 and 7): otherwise the full reserve, 2.5 V higher, pushes
    tens of amperes into the tripped battery through its discharge FET's body diode."""
    res = _run(_reserve_flight("mosfet_pair"), tmp_path)
    trip = _first_trip(res)
    assert trip < 50.0
    k = _at(res, trip)
    into_a = -res.trace.channel("current_a")[k:, 0]
    assert into_a.max() < 0.5  # A's charge limit is 2.5 A (0.5C); nothing may flow at all
    assert res.trace.channel("chg_on")[k + 1 :, 0].max() == 0.0
