"""Plausibility at its exact edges (#18 §1: rules only mutation testing showed unguarded).

The plausible ranges are closed (a reading exactly at an edge is plausible), a sample exactly
``max_sample_age_s`` old is fresh (stale means *older*), and every pack or battery reading the
docs list under ``nonfinite`` is checked, the load current and the battery current included.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import pytest

from packpilot.contract.bms import CLOSED, OPEN, Commands, Measurements, SwitchKind, SwitchState
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo
from packpilot.control.plausibility import PlausibilityConfig, PlausibilityMonitor
from tests.test_limits_helpers import CAP
from tests.test_plausibility_monitor import _FIELDS, AgedMeasurement, PDriver, faults, live

CFG = PlausibilityConfig()


@pytest.mark.parametrize(
    "edge",
    [
        {"max_cell_v": CFG.cell_v_range[1]},
        {"min_cell_v": CFG.cell_v_range[0]},
        {"temp_c": CFG.temp_range_c[1]},
        {"min_temp_c": CFG.temp_range_c[0]},
        {"soc": CFG.soc_range[1]},
        {"soc": CFG.soc_range[0]},
        {"current_a": CFG.current_range_c[1] * CAP},
        {"current_a": CFG.current_range_c[0] * CAP},
    ],
    ids=lambda e: "-".join(f"{k}={v}" for k, v in e.items()),
)
def test_a_reading_exactly_at_a_range_edge_is_plausible(edge: dict[str, Any]) -> None:
    """Held 5 s (ten times the range delay): no fault."""
    d = PDriver()
    outs = d.run(lambda k: (live(k, **edge), live(k)), 50)
    assert not faults(outs), [e.data for e in faults(outs)]


def test_a_reading_just_outside_a_range_edge_is_not() -> None:
    """The companion of the edge test: one ulp-ish step past the edge is a fault."""
    d = PDriver()
    outs = d.run(lambda k: (live(k, max_cell_v=CFG.cell_v_range[1] + 1e-6), live(k)), 50)
    assert [e.data["kind"] for e in faults(outs)] == ["out_of_range"]


def test_a_sample_exactly_max_sample_age_old_is_fresh() -> None:
    def aged(k: int, age: float) -> AgedMeasurement:
        return AgedMeasurement(**{f: getattr(live(k), f) for f in _FIELDS}, sample_age_s=age)

    d = PDriver()
    assert not faults(d.run(lambda k: (aged(k, CFG.max_sample_age_s), live(k)), 20))


def test_a_nan_load_current_is_a_pack_fault_that_stops_the_charger() -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k), live(k)), 10, load_current_a=math.nan)
    (ev,) = faults(outs)
    assert ev.battery is None and ev.data["field"] == "load_current_a"
    assert outs[-1].commands.charger == CHARGER_OFF
    assert d.mon.pack_fault


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_nonfinite_battery_current_is_a_fault(bad: float) -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k, current_a=bad), live(k)), 10)
    (ev,) = faults(outs)
    assert ev.battery == 0 and ev.data["kind"] == "nonfinite"
    assert ev.data["field"] == "current_a"


def test_a_fault_shows_a_finite_value_as_a_number_and_a_nonfinite_one_as_text() -> None:
    """The Fault event carries the offending reading: 0.2 V (out of range) as the number, for
    battery 0 as for any other, and NaN as the text "nan" (generated mutants efe8ad165f:
    battery 0 coded as a pack fault, its value turned into text; c119faf5f0: the number /
    text choice inverted)."""
    d = PDriver()
    outs = d.run(lambda k: (live(k, min_cell_v=0.2), live(k, min_cell_v=math.nan)), 10)
    got = {e.battery: (e.data["kind"], e.data["field"], e.data["value"]) for e in faults(outs)}
    assert got == {0: ("out_of_range", "min_cell_v", 0.2), 1: ("nonfinite", "min_cell_v", "nan")}


def _reaction(outs: list[Any], battery: int) -> str:
    (ev,) = [e for e in faults(outs) if e.battery == battery]
    return str(ev.data["reaction"])


def test_each_fault_names_its_reaction_exactly() -> None:
    """The reaction a Fault event names is the one its commands carry out (REACTIONS): the
    last source in flight keeps supplying (a relay), or opens its charge path and keeps
    supplying (a MOSFET pair); a stuck-open relay is commanded open, a shorted charge FET stops
    the charger, a shorted discharge FET is only flagged, a stuck-open discharge FET is
    commanded off (generated mutants e28dd220ec: a relay named the MOSFET reaction;
    b0238ebf3a: every switch fault named "command_open")."""
    outs = PDriver(n=1, kind=SwitchKind.RELAY).run(lambda k: (live(k, min_cell_v=math.nan),), 10)
    assert _reaction(outs, 0) == "keep_supplying (last source in flight)"
    outs = PDriver(n=1).run(lambda k: (live(k, min_cell_v=math.nan),), 10)
    assert _reaction(outs, 0) == "open_charge_path, keep_supplying (last source in flight)"

    d = PDriver(kind=SwitchKind.RELAY)
    d.mon.note_commands(Commands(chg_on=(True, True), dsg_on=(True, True)))
    outs = d.run(lambda k: (live(k), live(k, switch=OPEN, current_a=0.0)), 20)
    assert _reaction(outs, 1) == "command_open"

    d = PDriver()
    d.mon.note_commands(Commands(chg_on=(False, True), dsg_on=(True, False)))
    shorted = SwitchState(chg_on=True, dsg_on=True)
    outs = d.run(lambda k: (live(k, switch=shorted), live(k, switch=shorted)), 20)
    assert _reaction(outs, 0) == "charger_off"
    assert _reaction(outs, 1) == "flag_only (discharge cannot be interrupted)"

    d = PDriver()
    d.mon.note_commands(Commands(chg_on=(True, True), dsg_on=(True, True)))
    stuck = SwitchState(chg_on=True, dsg_on=False)
    outs = d.run(lambda k: (live(k, switch=stuck), live(k)), 20)
    assert _reaction(outs, 0) == "command_dsg_off"


def test_an_absent_battery_is_no_source_for_a_faulty_one() -> None:
    """A battery that is not present is no other source, whatever its last switch feedback
    and current say: a relay battery with a failed sensor beside an absent one is the last
    source and keeps supplying, it is not isolated (generated mutant a9e5af8a11: the absent
    battery counted, the load would lose its only supply)."""
    d = PDriver(kind=SwitchKind.RELAY)
    gone = replace(live(0, switch=CLOSED), present=False)
    outs = d.run(lambda k: (live(k, min_cell_v=math.nan, switch=CLOSED), gone), 10)
    assert _reaction(outs, 0) == "keep_supplying (last source in flight)"
    assert outs[-1].commands.dsg_on == (None, None)
    assert outs[-1].commands.chg_on == (None, None)


def test_a_one_group_battery_has_its_voltage_range_checked() -> None:
    """A battery of one series group (6 cells in it) is range-checked like any other: a
    battery voltage above 6 x the cell maximum is out of range (generated mutant 3b1fb18aac:
    ``groups != 0`` -> ``!= 1`` skipped the check for one-group batteries)."""
    info = PackInfo(n_batteries=1, groups_per_battery=(1,), cells_per_group=(6,),
                    switch_kind=(SwitchKind.MOSFET_PAIR,), capacity_ah=(CAP,))  # fmt: skip
    mon = PlausibilityMonitor(PlausibilityConfig(), info)
    v = 6 * (CFG.cell_v_range[1] + 0.1)
    outs = []
    for k in range(10):
        bm = live(k, voltage_v=v, group_voltages_v=(v,))
        outs.append(mon.step(Measurements(t_s=k * 0.1, batteries=(bm,), bus_v=v), 0.1))
    got = [(e.data["kind"], e.data["field"]) for e in faults(outs)]
    assert got == [("out_of_range", "voltage_v")]


def test_more_group_voltages_than_groups_is_a_count_fault_not_a_sum_fault() -> None:
    """Seven group voltages from a six-group battery: the count is wrong (group_count, at
    once), and the sum check, which needs the right count, says nothing: no voltage_sum fault
    from comparing seven groups' voltage with six groups' sum (generated mutant 888dd71c9e)."""
    d = PDriver()
    odd = {"group_voltages_v": (3.5,) * 7, "voltage_v": 7 * 3.5, "min_cell_v": 3.5,
           "max_cell_v": 3.5}  # fmt: skip
    outs = d.run(lambda k: (live(k, **odd), live(k)), 40)
    assert [(e.battery, e.data["kind"]) for e in faults(outs)] == [(0, "group_count")]


def test_a_pack_fault_clears_by_itself_and_counts_in_a_service_reset() -> None:
    """A non-finite bus voltage latches a pack fault; 5 s (clear_after_s) of finite readings
    clear it with a FaultCleared naming no battery (generated mutant 49c9155b91: never
    cleared); a service reset of every battery counts it among the faults it cleared
    (04a515ce5e: not counted)."""
    d = PDriver()
    d.run(lambda k: (live(k), live(k)), 10, bus_v=math.nan)
    assert d.mon.pack_fault
    outs = d.run(lambda k: (live(k), live(k)), 60)
    cleared = faults(outs, "FaultCleared")
    assert [(e.battery, e.data["kind"]) for e in cleared] == [(None, "nonfinite")]
    assert not d.mon.pack_fault
    d.run(lambda k: (live(k), live(k)), 10, bus_v=math.nan)
    assert d.mon.pack_fault
    assert d.mon.clear_faults() == 1
    assert not d.mon.pack_fault
