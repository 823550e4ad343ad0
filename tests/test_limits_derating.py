"""Current derating: min of three C-rate tables x capacity, derate/trip tiers, pack = N x min."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from packpilot.contract.bms import OPEN, Measurements, SwitchKind, SwitchState
from packpilot.contract.topology import PackInfo
from packpilot.control.limits import (
    DEFAULT_ROWS,
    CurveTable,
    DeratingConfig,
    LimitsConfig,
    LimitsController,
)
from tests.test_limits_helpers import CAP, Driver, healthy, pack

DER = DeratingConfig()


def test_default_limits_at_room_temperature_mid_soc() -> None:
    d = Driver()
    out = d.step(healthy())
    assert out.status["limit_chg_a"] == [pytest.approx(2.0 * CAP)]
    assert out.status["limit_dsg_a"] == [pytest.approx(15.0 * CAP)]


@pytest.mark.parametrize(
    ("kw", "chg_c", "dsg_c"),
    [
        ({"max_cell_v": 4.185}, 2.0 - (0.035 / 0.07) * 1.8, 15.0),  # voltage taper on charge
        ({"min_cell_v": 3.15}, 2.0, 10.0),  # voltage taper on discharge
        ({"temp_c": 42.5, "min_temp_c": 30.0}, 1.0, 15.0),  # hot: charge 2C -> 0 at 45
        (
            {"temp_c": 20.0, "min_temp_c": 6.0},
            0.2 + 0.8 * 0.5,
            8.0 + 7.0 * 0.6,
        ),  # the coldest cell limits
        ({"soc": 0.05}, 2.0, 6.5),
        ({"soc": 0.925}, 1.25, 15.0),
    ],
)
def test_limit_is_the_minimum_of_the_three_tables(
    kw: dict[str, float], chg_c: float, dsg_c: float
) -> None:
    d = Driver()
    out = d.step(healthy(**kw))
    assert out.status["limit_chg_a"][0] == pytest.approx(chg_c * CAP)
    assert out.status["limit_dsg_a"][0] == pytest.approx(dsg_c * CAP)


def test_temperature_table_reads_both_hottest_and_coldest() -> None:
    bm = healthy(temp_c=45.0, min_temp_c=-20.0)
    assert DER.charge_c(bm) == 0.0
    assert DER.discharge_c(replace(bm, temp_c=30.0)) == 0.0
    assert DER.discharge_c(replace(bm, min_temp_c=math.nan, temp_c=30.0)) == 15.0


def test_unknown_input_takes_the_table_minimum() -> None:
    bm = healthy(soc=math.nan)
    assert DER.discharge_c(bm) == pytest.approx(min(DER.discharge_vs_soc.c_rate))
    bm = healthy(temp_c=math.nan, min_temp_c=math.nan)
    assert DER.charge_c(bm) == 0.0


def test_derate_tier_scales_and_trip_zeroes_the_path_limit() -> None:
    cfg = LimitsConfig(derate_fraction=0.25)
    d = Driver(cfg)
    k_derate = next(
        k for k, r in enumerate(cfg.rows) if r.limit == "over_temp_discharge" and r.tier == "derate"
    )
    for _ in range(20):  # 56 degC: derate active (discharge table 15C -> 6C at 56 degC)
        out = d.step(healthy(temp_c=56.0))
    assert d.ctl.is_active(0, k_derate)
    assert out.status["limit_dsg_a"][0] == pytest.approx(0.25 * 6.0 * CAP)
    assert out.status["limit_chg_a"][0] == pytest.approx(0.0)  # charge table is 0 above 45
    for _ in range(20):
        out = d.step(healthy(temp_c=61.0))
    assert out.status["limit_dsg_a"][0] == 0.0
    assert out.commands.dsg_on == (False,)


def test_several_derate_rows_on_one_path_apply_the_fraction_once() -> None:
    d = Driver()
    for _ in range(30):  # under-voltage derate (2.8 V) and over-current derate (18C) at once
        out = d.step(healthy(min_cell_v=2.79, current_a=18.5 * CAP))
    tiers = (out.status["lim_under_voltage"][0], out.status["lim_over_current_discharge"][0])
    assert tiers == ("derate", "derate")
    assert out.status["limit_dsg_a"][0] == pytest.approx(
        0.5 * DER.discharge_c(healthy(min_cell_v=2.79)) * CAP
    )


def _mixed_pack() -> PackInfo:
    return PackInfo(
        n_batteries=4,
        groups_per_battery=(6,) * 4,
        cells_per_group=(1,) * 4,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * 3 + (SwitchKind.RELAY,),
        capacity_ah=(5.0, 4.0, 5.0, 5.0),
    )


def test_pack_limit_is_n_times_the_smallest_conducting_battery() -> None:
    ctl = LimitsController(LimitsConfig(), _mixed_pack())
    bms = (
        healthy(),  # 10 A chg, 75 A dsg
        healthy(full_capacity_ah=4.0),  # 4 Ah: 8 A chg, 60 A dsg
        healthy(soc=0.05),  # 10 A chg, 32.5 A dsg
        healthy(max_cell_v=4.185),  # 0.2C..: 5.5 A chg, 75 A dsg
    )
    out = ctl.step(Measurements(t_s=0.0, batteries=bms, bus_v=22.2), 0.1)
    assert ctl.limit_chg_a == pytest.approx((10.0, 8.0, 10.0, 1.1 * 5.0))
    assert ctl.pack_limit_chg_a == pytest.approx(4 * 5.5)
    assert ctl.pack_limit_dsg_a == pytest.approx(4 * 32.5)
    assert out.status["pack_limit_dsg_a"] == [pytest.approx(4 * 32.5)] * 4

    # Battery 2 cannot discharge (discharge FET off) -> excluded from the discharge pack limit
    # but still counts for charge (its charge FET is on); the relay battery 3 is open -> out of
    # both. Battery 0 is absent -> out of both.
    bms2 = (
        replace(bms[0], present=False),
        bms[1],
        replace(bms[2], switch=SwitchState(chg_on=True, dsg_on=False)),
        replace(bms[3], switch=SwitchState(chg_on=True, dsg_on=False)),
    )
    ctl.step(Measurements(t_s=0.1, batteries=bms2, bus_v=22.2), 0.1)
    assert ctl.pack_limit_dsg_a == pytest.approx(1 * 60.0)
    assert ctl.pack_limit_chg_a == pytest.approx(2 * 8.0)
    assert ctl.limit_chg_a[0] == 0.0

    all_open = tuple(replace(b, switch=OPEN) for b in bms)
    ctl.step(Measurements(t_s=0.2, batteries=all_open, bus_v=0.0), 0.1)
    assert ctl.pack_limit_chg_a == 0.0 and ctl.pack_limit_dsg_a == 0.0


def test_tripped_battery_leaves_the_pack_charge_limit() -> None:
    d = Driver(n=2)
    for _ in range(10):
        d.step(healthy(max_cell_v=4.26), healthy(), docked=True)
    assert d.ctl.tripped(0, "charge")
    assert d.ctl.pack_limit_chg_a == pytest.approx(1 * 2.0 * CAP)


def test_trip_event_reports_the_pack_limits_after_the_trip() -> None:
    d = Driver(n=2)
    events = []
    for _ in range(10):
        events += d.step(healthy(max_cell_v=4.26), healthy(), docked=True).events
    trip = next(e for e in events if e.kind == "LimitTripped")
    assert trip.battery == 0 and trip.data["limit"] == "over_voltage"
    assert trip.data["pack_limit_chg_a"] == pytest.approx(1 * 2.0 * CAP)
    assert trip.data["pack_limit_dsg_a"] == pytest.approx(2 * 15.0 * CAP)


def test_unknown_capacity_publishes_nan_not_a_number_from_nowhere() -> None:
    info = PackInfo(
        n_batteries=1,
        groups_per_battery=(6,),
        cells_per_group=(1,),
        switch_kind=(SwitchKind.RELAY,),
    )
    ctl = LimitsController(LimitsConfig(), info)
    ctl.step(Measurements(0.0, (healthy(full_capacity_ah=math.nan),), 22.2), 0.1)
    assert math.isnan(ctl.limit_dsg_a[0]) and math.isnan(ctl.pack_limit_dsg_a)
    ctl.step(Measurements(0.1, (healthy(full_capacity_ah=3.0),), 22.2), 0.1)
    assert ctl.limit_dsg_a[0] == pytest.approx(45.0)  # falls back to the reported capacity


def test_custom_tables_are_used() -> None:
    der = DeratingConfig(discharge_vs_soc=CurveTable(x=(0.0, 1.0), c_rate=(0.0, 10.0)))
    ctl = LimitsController(LimitsConfig(derating=der, rows=DEFAULT_ROWS[:3]), pack())
    ctl.step(Measurements(0.0, (healthy(soc=0.3),), 22.2), 0.1)
    assert ctl.limit_dsg_a[0] == pytest.approx(3.0 * CAP)
