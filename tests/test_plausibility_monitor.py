"""PlausibilityMonitor: each detection fires after its delay (not before), latches one Fault
event, commands its documented safe state, and clears by its documented condition."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import pytest

from packpilot.contract.bms import (
    CLOSED,
    OPEN,
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.charger import CHARGER_OFF
from packpilot.control.core import Core, Part
from packpilot.control.plausibility import PlausibilityConfig, PlausibilityMonitor
from packpilot.control.plausibility.controller import METHOD
from packpilot.errors import ConfigError
from tests.test_limits_helpers import CAP, pack

DT = 0.1


def live(k: int, current_a: float = 10.0, **kw: Any) -> BatteryMeasurement:
    """A plausible battery whose readings move a little every sample (as real ones do)."""
    v = 3.7 - 1e-5 * k
    base: dict[str, Any] = dict(
        voltage_v=6 * v,
        current_a=current_a,
        temp_c=25.0 + 1e-4 * k,
        min_temp_c=24.0 + 1e-4 * k,
        min_cell_v=v,
        max_cell_v=v,
        soc=0.5,
        full_capacity_ah=CAP,
        remaining_capacity_ah=2.5,
        group_voltages_v=(v,) * 6,
    )
    base.update(kw)
    return BatteryMeasurement(**base)


class PDriver:
    def __init__(
        self,
        n: int = 2,
        kind: SwitchKind = SwitchKind.MOSFET_PAIR,
        cfg: PlausibilityConfig | None = None,
    ) -> None:
        self.mon = PlausibilityMonitor(cfg or PlausibilityConfig(), pack(n, kind))
        self.n = n
        self.k = 0

    def step(
        self, *bms: BatteryMeasurement, docked: bool = False, dt: float = DT, **meas: Any
    ) -> ControlOutput:
        meas.setdefault("bus_v", 22.2)
        m = Measurements(t_s=self.k * dt, batteries=bms, docked=docked, **meas)
        self.k += 1
        return self.mon.step(m, dt)

    def run(self, make: Any, steps: int, **kw: Any) -> list[ControlOutput]:
        """``make(k)`` returns the batteries of step k."""
        return [self.step(*make(self.k), **kw) for _ in range(steps)]


def faults(outs: list[ControlOutput], kind: str = "Fault") -> list[Any]:
    return [e for o in outs for e in o.events if e.kind == kind]


def first_fault_step(outs: list[ControlOutput]) -> int | None:
    for s, o in enumerate(outs):
        if any(e.kind == "Fault" for e in o.events):
            return s + 1
    return None


def test_healthy_varying_data_raises_nothing() -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k), live(k, current_a=12.0)), 2000)
    assert not [e for o in outs for e in o.events]
    assert outs[-1].commands == Commands(chg_on=(None, None), dsg_on=(None, None))
    assert outs[-1].status["plaus_faults"] == ["", ""]


# -- sensor faults ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("bad", "kind", "field", "delay_s"),
    [
        ({"min_cell_v": math.nan}, "nonfinite", "min_cell_v", 0.5),
        ({"temp_c": math.inf}, "nonfinite", "temp_c", 0.5),
        ({"group_voltages_v": (3.7,) * 5 + (math.nan,)}, "nonfinite", "group_voltages_v[5]", 0.5),
        ({"min_cell_v": 0.2}, "out_of_range", "min_cell_v", 0.5),
        ({"temp_c": 150.0}, "out_of_range", "temp_c", 0.5),
        ({"current_a": 130.0 * CAP}, "out_of_range", "current_a", 0.5),
        ({"soc": 1.5}, "out_of_range", "soc", 0.5),
        ({"min_cell_v": 3.9, "max_cell_v": 3.8}, "out_of_range", "min_cell_v>max_cell_v", 0.5),
        ({"voltage_v": 6 * 3.7 + 0.5}, "voltage_sum", "voltage_v-sum(group_voltages_v)", 1.0),
        ({"group_voltages_v": (3.7,) * 5}, "group_count", "group_voltages_v", 0.0),
    ],
)
def test_sensor_fault_fires_after_its_delay(
    bad: dict[str, Any], kind: str, field: str, delay_s: float
) -> None:
    d = PDriver()
    d.run(lambda k: (live(k), live(k)), 10)
    outs = d.run(lambda k: (live(k, **bad), live(k)), 40)
    need = 1 + math.ceil(delay_s / DT - 1e-9)
    assert first_fault_step(outs) == need
    (ev,) = faults(outs)  # latched: one event per episode
    assert ev.battery == 0 and ev.data["kind"] == kind and ev.data["field"] == field
    assert kind in d.mon.faults(0) and not d.mon.faults(1)


def test_sum_within_tolerance_is_fine() -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k, voltage_v=6 * (3.7 - 1e-5 * k) + 0.25), live(k)), 100)
    assert not faults(outs)


def test_fault_clears_after_clear_after_s_of_good_data() -> None:
    d = PDriver()
    d.run(lambda k: (live(k, min_cell_v=math.nan), live(k)), 10)
    assert d.mon.faults(0) == {"nonfinite"}
    outs = d.run(lambda k: (live(k), live(k)), 60)
    cleared = [s for s, o in enumerate(outs) if any(e.kind == "FaultCleared" for e in o.events)]
    assert cleared == [1 + round(5.0 / DT) - 1]  # first good sample starts the 5 s clock
    assert not d.mon.faults(0)
    assert outs[-1].commands.chg_on == (None, None)


def test_stuck_voltage_under_current() -> None:
    frozen = live(0)
    d = PDriver(cfg=PlausibilityConfig(stuck_time_s=10.0))
    outs = d.run(lambda k: (frozen, live(k)), 200)
    assert first_fault_step(outs) == 1 + 100  # 10 s of unchanged samples after the first
    (ev,) = faults(outs)
    assert ev.data["kind"] == "stuck" and ev.data["field"] == "voltage_v"


def test_constant_voltage_at_rest_is_not_stuck_and_any_change_restarts_the_clock() -> None:
    d = PDriver(cfg=PlausibilityConfig(stuck_time_s=10.0))
    rest = live(0, current_a=0.0)
    assert not faults(d.run(lambda k: (rest, live(k)), 300))  # resting: may not move
    loaded = live(0, current_a=10.0)
    outs = d.run(lambda k: (loaded if k % 50 else live(k), live(k)), 300)
    assert not faults(outs)  # changes every 5 s: alive


def test_stuck_temperature_uses_its_own_longer_time() -> None:
    d = PDriver(cfg=PlausibilityConfig(stuck_temp_time_s=300.0))
    outs = d.run(lambda k: (live(k, temp_c=30.0), live(k)), 400, dt=1.0)
    (ev,) = faults(outs)
    assert ev.data["field"] == "temp_c" and first_fault_step(outs) == 301
    d2 = PDriver(cfg=PlausibilityConfig(stuck_temp_time_s=None))
    assert not faults(d2.run(lambda k: (live(k, temp_c=30.0), live(k)), 400, dt=1.0))


@dataclass(frozen=True, slots=True)
class AgedMeasurement(BatteryMeasurement):
    """What a CAN front end with per-battery timestamps could report."""

    sample_age_s: float = 0.0


def test_stale_by_sample_age_when_the_measurement_carries_one() -> None:
    def aged(k: int, age: float) -> AgedMeasurement:
        return AgedMeasurement(**{f: getattr(live(k), f) for f in _FIELDS}, sample_age_s=age)

    d = PDriver()
    assert not faults(d.run(lambda k: (aged(k, 0.5), live(k)), 20))
    assert not faults(d.run(lambda k: (aged(k, math.nan), live(k)), 20))  # NaN: not reported
    outs = d.run(lambda k: (aged(k, 3.0), live(k)), 5)
    assert first_fault_step(outs) == 1 and faults(outs)[0].data["kind"] == "stale"


_FIELDS = [
    "voltage_v",
    "current_a",
    "temp_c",
    "min_cell_v",
    "max_cell_v",
    "soc",
    "full_capacity_ah",
    "remaining_capacity_ah",
    "group_voltages_v",
    "switch",
    "min_temp_c",
    "present",
]


def test_pack_level_nan_stops_the_charger() -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k), live(k)), 10, bus_v=math.nan)
    (ev,) = faults(outs)
    assert ev.battery is None and ev.data["field"] == "bus_v"
    assert outs[-1].commands.charger == CHARGER_OFF
    assert d.mon.pack_fault


def test_absent_battery_is_not_judged() -> None:
    d = PDriver()
    gone = replace(live(0, min_cell_v=math.nan, voltage_v=0.0), present=False)
    assert not faults(d.run(lambda k: (gone, live(k)), 100))


# -- reactions to a sensor fault -------------------------------------------------------


def _nan(k: int, **kw: Any) -> BatteryMeasurement:
    return live(k, min_cell_v=math.nan, **kw)


@pytest.mark.parametrize("kind", list(SwitchKind))
def test_in_flight_isolate_the_faulty_battery_when_another_supplies(kind: SwitchKind) -> None:
    d = PDriver(kind=kind)
    outs = d.run(lambda k: (_nan(k), live(k)), 10)
    assert faults(outs)[0].data["reaction"].startswith("isolate")
    cmd = outs[-1].commands
    assert cmd.chg_on == (False, None) and cmd.dsg_on == (False, None)
    assert cmd.charger == CHARGER_OFF  # its charge path still conducts (feedback closed)
    outs = d.run(lambda k: (_nan(k, switch=OPEN), live(k)), 3)
    assert outs[-1].commands.charger is None  # confirmed open: the others may charge
    assert outs[-1].status["plaus_isolated"] == [True, False]


def test_in_flight_last_source_keeps_supplying() -> None:
    # MOSFET pair: open only the charge FET; discharge continues through its body diode.
    d = PDriver(n=1)
    outs = d.run(lambda k: (_nan(k),), 10)
    assert outs[-1].commands.chg_on == (False,) and outs[-1].commands.dsg_on == (None,)
    # Relay: opening either path drops the load, so no opinion.
    d = PDriver(n=1, kind=SwitchKind.RELAY)
    outs = d.run(lambda k: (_nan(k),), 10)
    assert outs[-1].commands.chg_on == (None,) and outs[-1].commands.dsg_on == (None,)
    assert "keep_supplying" in faults(outs)[0].data["reaction"]
    # A sibling that is switched off does not count as a source.
    d = PDriver(n=2, kind=SwitchKind.RELAY)
    outs = d.run(lambda k: (_nan(k), live(k, switch=OPEN, current_a=0.0)), 10)
    assert outs[-1].commands.dsg_on == (None, None)


def test_docked_isolate_and_stop_the_charger() -> None:
    d = PDriver(n=1, kind=SwitchKind.RELAY)
    outs = d.run(lambda k: (_nan(k, current_a=-5.0),), 10, docked=True)
    cmd = outs[-1].commands
    assert cmd.chg_on == (False,) and cmd.dsg_on == (False,) and cmd.charger == CHARGER_OFF


# -- switch feedback ---------------------------------------------------------------------


def _cmd(chg: tuple[bool | None, ...], dsg: tuple[bool | None, ...]) -> Commands:
    return Commands(chg_on=chg, dsg_on=dsg)


def test_welded_relay() -> None:
    d = PDriver(kind=SwitchKind.RELAY)
    d.mon.note_commands(_cmd((False, True), (True, True)))  # battery 0: relay commanded open
    outs = d.run(lambda k: (live(k, switch=CLOSED), live(k)), 20)
    need = 1 + round(0.5 / DT)
    assert first_fault_step(outs) == need
    (ev,) = faults(outs)
    assert ev.data["kind"] == "relay_welded"
    cmd = outs[-1].commands
    assert cmd.charger == CHARGER_OFF
    assert cmd.chg_on == (None, None) and cmd.dsg_on == (None, None)  # never used to isolate
    assert d.mon.welded == (True, False)
    # a sensor fault on the welded battery still does not try to isolate it
    outs = d.run(lambda k: (_nan(k, switch=CLOSED), live(k)), 10)
    assert outs[-1].commands.chg_on == (None, None)
    # switch faults do not clear by themselves, only by a service reset
    d.mon.note_commands(_cmd((True, True), (True, True)))
    cleared = faults(d.run(lambda k: (live(k), live(k)), 200), "FaultCleared")
    assert [e.data["kind"] for e in cleared] == ["nonfinite"]  # the sensor fault did clear
    assert "relay_welded" in d.mon.faults(0)
    assert d.mon.clear_faults(0, ["relay_welded"]) == 1
    outs = d.run(lambda k: (live(k), live(k)), 1)
    assert [e.data["kind"] for e in faults(outs, "FaultCleared")] == ["relay_welded"]
    assert not d.mon.welded[0]


def test_relay_stuck_open() -> None:
    d = PDriver(kind=SwitchKind.RELAY)
    d.mon.note_commands(_cmd((True, True), (True, True)))
    outs = d.run(lambda k: (live(k), live(k, switch=OPEN, current_a=0.0)), 20)
    (ev,) = faults(outs)
    assert ev.battery == 1 and ev.data["kind"] == "relay_stuck_open"
    assert outs[-1].commands.chg_on == (None, False) and outs[-1].commands.dsg_on == (None, False)
    assert outs[-1].commands.charger is None


def test_shorted_and_stuck_open_fets() -> None:
    d = PDriver()
    d.mon.note_commands(_cmd((False, True), (True, False)))
    fb0 = SwitchState(chg_on=True, dsg_on=True)  # charge FET shorted
    fb1 = SwitchState(chg_on=True, dsg_on=True)  # discharge FET shorted
    outs = d.run(lambda k: (live(k, switch=fb0), live(k, switch=fb1)), 20)
    kinds = {(e.battery, e.data["kind"]) for e in faults(outs)}
    assert kinds == {(0, "chg_fet_shorted"), (1, "dsg_fet_shorted")}
    assert outs[-1].commands.charger == CHARGER_OFF  # cannot block charge into battery 0
    assert outs[-1].commands.chg_on == (None, None) and outs[-1].commands.dsg_on == (None, None)

    d = PDriver()
    d.mon.note_commands(_cmd((True, True), (True, True)))
    fb = SwitchState(chg_on=True, dsg_on=False)  # discharge FET will not turn on
    outs = d.run(lambda k: (live(k, switch=fb), live(k)), 20)
    assert [e.data["kind"] for e in faults(outs)] == ["dsg_fet_stuck_open"]
    assert outs[-1].commands.dsg_on == (False, None) and outs[-1].commands.chg_on == (None, None)


def test_switch_lag_within_the_delay_and_unknown_commands_are_fine() -> None:
    d = PDriver(kind=SwitchKind.RELAY)
    assert not faults(d.run(lambda k: (live(k, switch=OPEN), live(k)), 50))  # nothing noted yet
    d.mon.note_commands(_cmd((True, None), (True, None)))
    outs = d.run(lambda k: (live(k, switch=OPEN), live(k)), 5)  # 0.4 s: relay still closing
    outs += d.run(lambda k: (live(k), live(k)), 50)
    assert not faults(outs)


def test_none_in_merged_commands_keeps_the_previous_state() -> None:
    d = PDriver(kind=SwitchKind.RELAY)
    d.mon.note_commands(_cmd((False, True), (False, True)))
    d.mon.note_commands(_cmd((None, None), (None, None)))  # no opinion: still open
    outs = d.run(lambda k: (live(k, switch=CLOSED), live(k)), 20)
    assert [e.data["kind"] for e in faults(outs)] == ["relay_welded"]


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match=r"plausibility: cell_v_range must be"):
        PlausibilityConfig.load({"cell_v_range": [5.0, 1.0]})
    with pytest.raises(ConfigError, match=r"stuck_time_s must be > 0 s"):
        PlausibilityConfig.load({"stuck_time_s": 0.0})
    with pytest.raises(ConfigError, match=r"switch_delay_s must be a finite value >= 0"):
        PlausibilityConfig.load({"switch_delay_s": -1})
    assert PlausibilityConfig.load({"stuck_temp_time_s": None}).stuck_temp_time_s is None


def test_a_stale_sample_is_not_judged_for_its_switches() -> None:
    """A stale sample's feedback is as old as the sample: a battery whose telemetry stopped
    and that the BMS then isolated must not latch a "FET shorted" fault (only a service action
    clears those); once fresh again, its switches are judged as before."""

    def aged(k: int, age: float, fb: SwitchState) -> AgedMeasurement:
        m = live(k, switch=fb)
        return AgedMeasurement(**{f: getattr(m, f) for f in _FIELDS}, sample_age_s=age)

    on = SwitchState(chg_on=True, dsg_on=True)
    d = PDriver()
    d.mon.note_commands(_cmd((False, True), (False, True)))  # battery 0 commanded open
    outs = d.run(lambda k: (aged(k, 3.0, on), live(k)), 20)  # stale, feedback still "on"
    assert [e.data["kind"] for e in faults(outs)] == ["stale"]
    outs = d.run(lambda k: (aged(k, 0.1, on), live(k)), 20)  # fresh: now it is judged
    assert "chg_fet_shorted" in {e.data["kind"] for e in faults(outs)}

# -- degraded mode: the reserve (#15 §5) ------------------------------------------------


@dataclass
class _OpensA:
    """A layer ahead of plausibility that opens battery A's path from step ``at`` on, by one
    command (the charge command opens a relay as surely as the discharge command)."""

    at: int
    path: str
    k: int = 0

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        self.k += 1
        off = (False, None) if self.k > self.at else (None, None)
        cmd = Commands(chg_on=off) if self.path == "chg" else Commands(dsg_on=off)
        return ControlOutput(commands=cmd)


@pytest.mark.parametrize(
    ("kind", "path"),
    [(SwitchKind.RELAY, "chg"), (SwitchKind.RELAY, "dsg"), (SwitchKind.MOSFET_PAIR, "dsg")],
)
def test_the_reserve_is_released_in_the_step_its_last_trusted_source_is_opened(
    kind: SwitchKind, path: str
) -> None:
    """B (failed sensor) is held back while A carries the load; in the step a layer ahead of
    plausibility opens A, B's isolation is lifted (make-before-break) and ``ReserveEngaged``
    tells the platform. A's switch feedback still shows it closed in that step."""
    info = pack(2, kind)
    core = Core([info], [_OpensA(10, path), Part.build(METHOD, PlausibilityConfig(), [info])])
    outs = []
    for k in range(12):
        m = Measurements(t_s=k * DT, batteries=(live(k), _nan(k)), bus_v=22.2)
        outs.append(core.step(m, DT))
    assert outs[9].commands.dsg_on[1] is False  # held back while A carries the load
    assert outs[9].status["plaus_isolated"] == [False, True]
    engaged = outs[10]
    assert engaged.commands.dsg_on[1] is None  # released in the step A is opened
    assert [e.battery for e in engaged.events if e.kind == "ReserveEngaged"] == [1]
    assert engaged.status["plaus_isolated"] == [False, False]
