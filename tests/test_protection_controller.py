"""ProtectionController: the spec's worked examples, latch, new-cycle reset, fail-safes."""

from __future__ import annotations

import math
from collections.abc import Sequence

import pytest

from packpilot.contract.bms import BatteryMeasurement, ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.protection import (
    ProtectionConfig,
    ProtectionController,
    ProtectionParameter,
    TableRow,
)

PACK1 = PackInfo(
    n_batteries=1,
    groups_per_battery=(6,),
    cells_per_group=(1,),
    switch_kind=(SwitchKind.MOSFET_PAIR,),
    capacity_ah=(5.0,),
)


def _bm(
    current_a: float,
    temp_c: float,
    min_cell_v: float,
    *,
    voltage_v: float | None = None,
    groups: tuple[float, ...] = (),
    present: bool = True,
) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=6 * min_cell_v if voltage_v is None else voltage_v,
        current_a=current_a,
        temp_c=temp_c,
        min_cell_v=min_cell_v,
        max_cell_v=min_cell_v,
        soc=0.1,
        full_capacity_ah=5.0,
        remaining_capacity_ah=0.5,
        group_voltages_v=groups,
        present=present,
    )


class Driver:
    """Feeds segments of constant (I, T, V) to a controller and records the trip time."""

    def __init__(self, config: ProtectionConfig | None = None, pack: PackInfo = PACK1) -> None:
        self.ctl = ProtectionController(config or ProtectionConfig(), pack)
        self.t = 0.0
        self.trip_end_s: float | None = None
        self.outputs: list[ControlOutput] = []

    def run(
        self, seconds: float, current_a: float, temp_c: float, v: float, dt: float = 1.0
    ) -> ControlOutput:
        n = round(seconds / dt)
        out = None
        for _ in range(n):
            out = self.step(_bm(current_a, temp_c, v), dt)
        assert out is not None
        return out

    def step(
        self, bm: BatteryMeasurement | Sequence[BatteryMeasurement], dt: float
    ) -> ControlOutput:
        batteries = (bm,) if isinstance(bm, BatteryMeasurement) else tuple(bm)
        out = self.ctl.step(Measurements(t_s=self.t, batteries=batteries, bus_v=20.0), dt)
        self.outputs.append(out)
        if self.trip_end_s is None and any(e.kind == "ProtectionTripped" for e in out.events):
            self.trip_end_s = self.t + dt
        self.t += dt
        return out

    def events(self, kind: str) -> list[object]:
        return [e for o in self.outputs for e in o.events if e.kind == kind]


# ---- worked examples (spec §8) -------------------------------------------------------------


@pytest.mark.parametrize("dt", [1.0, 0.1, 0.01, 0.02, 0.25])
def test_p3_only_trips_at_exactly_5_s(dt: float) -> None:
    d = Driver()
    d.run(5.0 - dt, 10.0, 25.0, 3.1, dt)
    assert d.trip_end_s is None
    out = d.run(dt, 10.0, 25.0, 3.1, dt)
    assert d.trip_end_s == pytest.approx(5.0, abs=1e-9)
    assert out.commands.dsg_on == (False,)
    assert out.status["protection_param"] == ["P3"]
    assert out.status["protection_fraction"] == [1.0]


@pytest.mark.parametrize("temp_c", [-20.0, 0.0, 10.0, 25.0, 45.0])
def test_p1_only_trips_at_exactly_15_s(temp_c: float) -> None:
    d = Driver()
    d.run(14.0, 30.0, temp_c, 2.7)
    assert d.trip_end_s is None
    d.run(1.0, 30.0, temp_c, 2.7)
    assert d.trip_end_s == 15.0
    (ev,) = d.events("ProtectionTripped")
    assert ev.data["param"] == "P1"  # type: ignore[attr-defined]


def test_mixed_6s_p1_2s_p2_2s_p3_trips_at_10_s() -> None:
    d = Driver()
    d.run(6.0, 30.0, 25.0, 2.7)  # 6 x 2 = 12
    assert d.ctl.fraction(0) == pytest.approx(6 / 15)
    d.run(2.0, 20.0, 25.0, 2.9)  # 2 x 3 = 6
    assert d.ctl.fraction(0) == pytest.approx(6 / 15 + 2 / 10)
    d.run(1.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s is None
    d.run(1.0, 10.0, 25.0, 3.1)  # 2 x 6 = 12 -> 30
    assert d.trip_end_s == 10.0
    (ev,) = d.events("ProtectionTripped")
    data = ev.data  # type: ignore[attr-defined]
    assert data["param"] == "P3" and data["cutoff_v"] == 3.2 and data["t_max_s"] == 5.0
    assert data["accumulated_s"] == 30.0 and data["m_s"] == 30.0 and data["fraction"] == 1.0
    assert data["min_cell_v"] == 3.1 and data["current_a"] == 10.0 and data["temp_c"] == 25.0
    assert data["soc"] == 0.1 and data["remaining_capacity_ah"] == 0.5


def test_heavy_load_between_cutoffs_does_not_accumulate_until_load_drops() -> None:
    d = Driver()
    out = d.run(120.0, 30.0, 25.0, 3.0)
    assert d.ctl.fraction(0) == 0.0 and d.trip_end_s is None
    assert out.status["protection_cutoff_v"] == [2.8]
    out = d.run(1.0, 10.0, 25.0, 3.0)
    assert out.status["protection_param"] == ["P3"]
    assert d.ctl.fraction(0) == pytest.approx(6 / 30)  # weight 6
    d.run(4.0, 10.0, 25.0, 3.0)
    assert d.trip_end_s == 125.0


# ---- commands, latch, reset --------------------------------------------------------------


def test_no_opinion_before_trip() -> None:
    d = Driver()
    out = d.run(3.0, 10.0, 25.0, 3.1)
    assert out.commands.dsg_on == (None,)
    assert all(x is None for x in out.commands.chg_on)  # no opinion on the charge path


def test_voltage_exactly_at_cutoff_accumulates_and_strict_mode_does_not() -> None:
    d = Driver()
    d.run(1.0, 10.0, 25.0, 3.2)
    assert d.ctl.fraction(0) == pytest.approx(0.2)
    d2 = Driver(ProtectionConfig(voltage_comparison="<"))
    d2.run(1.0, 10.0, 25.0, 3.2)
    assert d2.ctl.fraction(0) == 0.0


def test_strict_trip_comparison_needs_more_than_m() -> None:
    d = Driver(ProtectionConfig(trip_comparison=">"))
    d.run(5.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s is None
    d.run(1.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 6.0


def test_not_discharging_does_not_accumulate() -> None:
    d = Driver()
    d.run(60.0, 0.3, 25.0, 3.0)  # below the 0.5 A discharge threshold
    d.run(60.0, -0.3, 25.0, 3.0)
    assert d.ctl.fraction(0) == 0.0


def test_no_reset_on_voltage_recovery_by_default() -> None:
    d = Driver()
    d.run(3.0, 10.0, 25.0, 3.1)
    d.run(100.0, 10.0, 25.0, 3.6)
    d.run(100.0, 0.0, 25.0, 3.7)
    assert d.ctl.fraction(0) == pytest.approx(0.6)
    d.run(2.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 205.0


def test_reset_on_recovery_option() -> None:
    d = Driver(ProtectionConfig(reset_on_recovery=True))
    d.run(3.0, 10.0, 25.0, 3.1)
    d.run(1.0, 10.0, 25.0, 3.6)
    assert d.ctl.fraction(0) == 0.0
    d.run(4.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s is None
    d.run(1.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 9.0


def test_trip_latches_until_sustained_charge() -> None:
    d = Driver()
    d.run(5.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 5.0
    # Recovery, rest, brief and weak charging: still latched.
    for seg in [(30.0, 0.0, 3.6), (9.0, -2.0, 3.7), (1.0, 0.0, 3.7), (100.0, -0.4, 3.7)]:
        out = d.run(seg[0], seg[1], 25.0, seg[2])
        assert out.commands.dsg_on == (False,)
        assert out.status["protection_tripped"] == [True]
    assert d.ctl.fraction(0) == 1.0  # frozen after the trip
    assert len(d.events("ProtectionTripped")) == 1
    # 10 s of charging below -0.5 A starts a new cycle.
    out = d.run(9.0, -2.0, 25.0, 3.8)
    assert out.commands.dsg_on == (False,)
    out = d.run(1.0, -2.0, 25.0, 3.8)
    assert out.commands.dsg_on == (None,)
    assert out.status["protection_tripped"] == [False]
    assert out.status["protection_fraction"] == [0.0]
    (reset,) = d.events("ProtectionReset")
    assert reset.data["reason"] == "charge" and reset.data["was_tripped"] is True  # type: ignore[attr-defined]
    # Long charging does not emit more resets; the next discharge starts from zero.
    d.run(100.0, -2.0, 25.0, 3.9)
    assert len(d.events("ProtectionReset")) == 1
    trip_before = d.trip_end_s
    d.run(4.0, 10.0, 25.0, 3.1)
    assert d.ctl.fraction(0) == pytest.approx(0.8)
    assert d.trip_end_s == trip_before


def test_charge_also_resets_partial_sum_and_thresholds_are_configurable() -> None:
    d = Driver(ProtectionConfig(charge_threshold_a=1.0, charge_detect_s=3.0))
    d.run(2.0, 10.0, 25.0, 3.1)
    d.run(3.0, -0.8, 25.0, 3.7)
    assert d.ctl.fraction(0) == pytest.approx(0.4)
    d.run(3.0, -1.5, 25.0, 3.7)
    assert d.ctl.fraction(0) == 0.0


def test_reinsertion_starts_new_cycle() -> None:
    d = Driver()
    d.run(5.0, 10.0, 25.0, 3.1)
    out = d.step(_bm(0.0, 25.0, 3.1, present=False), 1.0)
    assert out.commands.dsg_on == (False,)
    out = d.step(_bm(0.0, 25.0, 3.9), 1.0)
    assert out.commands.dsg_on == (None,)
    assert d.events("ProtectionReset")[0].data["reason"] == "reinserted"  # type: ignore[attr-defined]

    d2 = Driver(ProtectionConfig(reset_on_reinsert=False))
    d2.run(5.0, 10.0, 25.0, 3.1)
    d2.step(_bm(0.0, 25.0, 3.1, present=False), 1.0)
    assert d2.step(_bm(0.0, 25.0, 3.9), 1.0).commands.dsg_on == (False,)


def test_host_can_start_new_cycle() -> None:
    d = Driver()
    d.run(5.0, 10.0, 25.0, 3.1)
    d.ctl.start_new_cycle(0)
    assert d.run(1.0, 0.0, 25.0, 3.9).commands.dsg_on == (None,)


def test_each_battery_has_its_own_state() -> None:
    pack = PackInfo(
        n_batteries=3,
        groups_per_battery=(6, 6, 6),
        cells_per_group=(1, 1, 1),
        switch_kind=(SwitchKind.RELAY,) * 3,
    )
    d = Driver(pack=pack)
    sample = (_bm(10.0, 25.0, 3.5), _bm(30.0, 25.0, 2.7), _bm(10.0, 25.0, 3.1))
    dsg = [d.step(sample, 1.0).commands.dsg_on for _ in range(15)]
    assert dsg[3] == (None, None, None)
    assert dsg[4] == (None, None, False)
    assert dsg[13] == (None, None, False)
    out = d.outputs[-1]
    assert out.commands.dsg_on == (None, False, False)
    assert out.status["protection_param"] == ["P3", "P1", "P3"]
    trips = d.events("ProtectionTripped")
    assert [(e.battery, e.t_s) for e in trips] == [(2, 4.0), (1, 14.0)]  # type: ignore[attr-defined]
    assert {len(v) for v in out.status.values()} == {3}


# ---- hysteresis and filtering --------------------------------------------------------------


def test_hysteresis_keeps_the_row_inside_the_band() -> None:
    d = Driver(ProtectionConfig(hysteresis={"current_a": 0.5, "temp_c": 0.5}))
    assert d.run(1.0, 14.0, 25.0, 3.9).status["protection_param"] == ["P3"]
    assert d.run(1.0, 15.4, 25.0, 3.9).status["protection_param"] == ["P3"]
    assert d.run(1.0, 15.6, 25.0, 3.9).status["protection_param"] == ["P2"]
    assert d.run(1.0, 14.7, 25.0, 3.9).status["protection_param"] == ["P2"]
    assert d.run(1.0, 14.4, 25.0, 3.9).status["protection_param"] == ["P3"]
    assert d.run(1.0, 10.0, 14.6, 3.9).status["protection_param"] == ["P3"]
    assert d.run(1.0, 10.0, 14.4, 3.9).status["protection_param"] == ["P2"]
    plain = Driver()
    assert plain.run(1.0, 15.4, 25.0, 3.9).status["protection_param"] == ["P2"]


def test_first_order_filter_delays_parameter_change() -> None:
    d = Driver(ProtectionConfig(filter_tau_s={"current_a": 2.0}))
    d.run(10.0, 10.0, 25.0, 3.9, dt=0.1)
    params = [d.run(0.1, 30.0, 25.0, 3.9, dt=0.1).status["protection_param"][0] for _ in range(30)]
    # Filtered I = 10 + 20 (1 - exp(-t/2)) crosses 15 A at t = 0.575 s, 25 A at t = 2.77 s.
    assert params[:5] == ["P3"] * 5
    assert params[5:27] == ["P2"] * 22
    assert params[27:] == ["P1"] * 3


# ---- fail-safes for non-finite measurements ------------------------------------------------


def test_nan_min_cell_falls_back_to_group_voltages_then_mean_cell() -> None:
    d = Driver()
    bm = _bm(10.0, 25.0, math.nan, groups=(3.4, 3.1, 3.5, 3.4, 3.4, 3.4), voltage_v=20.2)
    d.step(bm, 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.2)  # min group 3.1 <= 3.2
    bm = _bm(10.0, 25.0, math.nan, voltage_v=6 * 3.15)
    d.step(bm, 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.4)  # mean cell 3.15 <= 3.2
    faults = d.events("Fault")
    assert len(faults) == 1 and faults[0].data["field"] == "min_cell_v"  # type: ignore[attr-defined]


def test_fallback_divides_groups_into_series_cells() -> None:
    """3 groups of 2 series cells: group voltages are module voltages."""
    pack = PackInfo(
        n_batteries=1,
        groups_per_battery=(3,),
        cells_per_group=(2,),
        switch_kind=(SwitchKind.MOSFET_PAIR,),
    )
    d = Driver(pack=pack)
    d.step(_bm(10.0, 25.0, math.nan, groups=(7.0, 6.3, 7.0), voltage_v=20.3), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.2)  # weakest group: 3.15 V per cell
    d.step(_bm(10.0, 25.0, math.nan, groups=(7.0, 6.5, 7.0), voltage_v=20.5), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.2)  # 3.25 V per cell: above 3.2
    d.step(_bm(10.0, 25.0, math.nan, voltage_v=6 * 3.19), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.4)  # mean cell 3.19 V


def test_unknown_voltage_does_not_accumulate_and_faults_once_per_episode() -> None:
    d = Driver()
    d.run(2.0, 10.0, 25.0, 3.1)
    for _ in range(50):
        d.step(_bm(10.0, 25.0, math.nan, voltage_v=math.nan), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.4)
    assert len(d.events("Fault")) == 1
    d.run(1.0, 10.0, 25.0, 3.1)
    d.step(_bm(10.0, 25.0, math.nan, voltage_v=math.nan), 1.0)
    assert len(d.events("Fault")) == 2
    d.run(1.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s is None
    d.run(1.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 56.0


@pytest.mark.parametrize(
    ("current_a", "temp_c", "expected"),
    [
        (10.0, math.nan, "P3"),  # I low: P1/P2/P3 possible -> highest cut-off
        (20.0, math.nan, "P2"),  # I mid: P1/P2
        (30.0, math.nan, "P1"),  # I high: only P1
        (math.nan, 25.0, "P3"),
        (math.nan, 0.0, "P1"),  # cold: P1 whatever the current
        (math.nan, math.inf, "P3"),
        (math.nan, math.nan, "P3"),
    ],
)
def test_unknown_status_uses_most_conservative_consistent_parameter(
    current_a: float, temp_c: float, expected: str
) -> None:
    d = Driver()
    out = d.step(_bm(current_a, temp_c, 3.9), 1.0)
    assert out.status["protection_param"] == [expected]
    assert any(e.kind == "Fault" for e in out.events)


def test_nan_current_holds_the_discharge_state() -> None:
    d = Driver()
    d.run(1.0, 10.0, 25.0, 3.1)
    d.step(_bm(math.nan, 25.0, 3.1), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.4)
    d.run(1.0, 0.0, 25.0, 3.1)
    d.step(_bm(math.nan, 25.0, 3.1), 1.0)
    assert d.ctl.fraction(0) == pytest.approx(0.4)


def test_garbage_never_raises() -> None:
    d = Driver()
    for dt in (math.nan, -1.0, math.inf, 0.0):
        out = d.step(_bm(math.nan, math.nan, math.nan, voltage_v=math.nan), dt)
        assert out.commands.dsg_on == (None,)
    d.step((), 1.0)  # battery missing from the sample: treated as absent
    assert d.ctl.fraction(0) == 0.0


def test_one_row_baseline_ignores_status() -> None:
    cfg = ProtectionConfig(
        parameters=(ProtectionParameter(name="fixed", cutoff_v=3.2, t_max_s=5.0),),
        table=(TableRow(param="fixed"),),
    )
    d = Driver(cfg)
    d.run(4.0, 30.0, -10.0, 3.1)
    assert d.trip_end_s is None
    d.run(1.0, 30.0, -10.0, 3.1)
    assert d.trip_end_s == 5.0


def test_a_sustained_charge_starts_one_cycle_and_stays_started() -> None:
    """A sustained charge starts one new discharge cycle, once: the battery's view says the
    cycle started from charge_detect_s on and keeps saying so for the rest of the charge, with
    one reset event; only the end of the charge re-arms it (generated mutant fbf8ba0c6a: the
    flag never set, a new cycle restarted on every tick of the charge)."""
    d = Driver()
    d.run(2.0, 10.0, 25.0, 3.1)  # something to reset: 2 of P3's 5 s
    d.run(9.0, -2.0, 25.0, 3.8)
    assert not d.ctl.battery(0).charge_cycle_started
    for _ in range(30):
        d.run(1.0, -2.0, 25.0, 3.8)
        assert d.ctl.battery(0).charge_cycle_started
    assert len(d.events("ProtectionReset")) == 1
    d.run(1.0, 0.0, 25.0, 3.8)
    assert not d.ctl.battery(0).charge_cycle_started


def test_no_group_fallback_without_a_cell_count() -> None:
    """A pack that does not say how many cells a group holds (cells_per_group 0) gives the
    group voltages no meaning as cell voltages: without a min cell voltage the check voltage
    is unknown (nothing accumulates, one voltage fault), never a group voltage divided by 0
    (generated mutant bc3bb9e592: ``per_group > 0`` -> ``>= 0``)."""
    pack = PackInfo(
        n_batteries=1,
        groups_per_battery=(6,),
        cells_per_group=(0,),
        switch_kind=(SwitchKind.MOSFET_PAIR,),
    )
    d = Driver(pack=pack)
    out = d.step(_bm(10.0, 25.0, math.nan, groups=(3.1,) * 6, voltage_v=18.6), 1.0)
    assert d.ctl.fraction(0) == 0.0
    assert out.status["protection_time_to_trip_s"] == [None]
    (fault,) = d.events("Fault")
    assert fault.data["field"] == "min_cell_v"  # type: ignore[attr-defined]
    assert "no accumulation until a voltage is available" in fault.message  # type: ignore[attr-defined]


def test_an_absent_battery_leaves_the_status_of_the_layer_before_it_alone() -> None:
    """In a composed core protection writes only its own status columns: for a battery absent
    from the start (no table row yet) it shows no parameter and no cut-off, and the limits
    layer before it keeps every status value it published for that battery (generated mutant
    3bdfb0ba7e: ``s0 + ST_CUTOFF`` -> ``s0 - ST_CUTOFF`` wrote NaN into the limits layer's last
    column)."""
    from packpilot.control.core import Core, Part
    from packpilot.control.limits import LimitsConfig
    from packpilot.control.limits.controller import METHOD as LIMITS
    from packpilot.control.protection.controller import METHOD as PROTECTION

    pack = PackInfo(n_batteries=2, groups_per_battery=(6, 6), cells_per_group=(1, 1),
                    switch_kind=(SwitchKind.MOSFET_PAIR,) * 2, capacity_ah=(5.0, 5.0))  # fmt: skip
    alone = Core([pack], [Part.build(LIMITS, LimitsConfig(), [pack])])
    both = Core([pack], [Part.build(LIMITS, LimitsConfig(), [pack]),
                         Part.build(PROTECTION, ProtectionConfig(), [pack])])  # fmt: skip
    meas = Measurements(t_s=0.0, batteries=(_bm(5.0, 25.0, 3.7), _bm(0.0, 25.0, 3.7,
                        present=False)), bus_v=22.2)  # fmt: skip
    a = alone.step(meas, 1.0).status
    b = both.step(meas, 1.0).status
    assert {k: b[k] for k in a} == a
    assert b["protection_param"][1] in (None, "") and b["protection_cutoff_v"][1] is None


def test_among_equal_cut_offs_the_shorter_allowance_is_more_conservative() -> None:
    """Temperature unknown: of the parameters its known status allows, the most conservative
    is the highest cut-off and, at an equal cut-off, the shorter t_max, wherever its row is in
    the table (SHORT first or last; generated mutant 6fb64a0187: ``cut > best`` -> ``>=`` took
    the last row of an equal cut-off, the longer allowance)."""
    params = [{"name": "SHORT", "cutoff_v": 3.2, "t_max_s": 5},
              {"name": "LONG", "cutoff_v": 3.2, "t_max_s": 10}]  # fmt: skip
    for cold, warm in (("SHORT", "LONG"), ("LONG", "SHORT")):
        cfg = ProtectionConfig.model_validate({"parameters": params, "table": [
            {"param": cold, "ranges": {"temp_c": "(-inf, 20)"}},
            {"param": warm, "ranges": {"temp_c": "[20, inf)"}},
        ]})  # fmt: skip
        out = Driver(cfg).step(_bm(10.0, math.nan, 3.9), 1.0)
        assert out.status["protection_param"] == ["SHORT"], (cold, warm)
