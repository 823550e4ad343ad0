"""Limits at their exact edges (#18 §1: rules that only mutation testing showed unguarded).

Violation is *strictly* beyond the threshold and clearing is *at or past* the reset value
(docs/safety.md "Semantics of a row"); a trip zeroes its path's published current limit even
where the derating tables would allow current; an unknown (NaN) reading never clears a row,
however long the row has been active.
"""

from __future__ import annotations

import dataclasses
import math

import pytest

from packpilot.contract.bms import CLOSED, Measurements, SwitchKind, SwitchState
from packpilot.control.limits import DEFAULT_ROWS, LimitRow, LimitsConfig, LimitsController
from tests.test_limits_helpers import CAP, Driver, healthy, pack, with_value

ROWS = list(enumerate(DEFAULT_ROWS))
IDS = [f"{r.limit}-{r.tier}" for r in DEFAULT_ROWS]
DELTA = 1e-3


def _docked(row: LimitRow) -> bool:
    return row.when == "charging"


def _fire(d: Driver, k: int, row: LimitRow) -> None:
    beyond = row.threshold + DELTA if row.direction == "above" else row.threshold - DELTA
    for _ in range(row.debounce + math.ceil(row.delay_s / 0.1) + 1):
        d.step(with_value(row, beyond), docked=_docked(row))
    assert d.ctl.is_active(0, k)


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_a_value_exactly_at_the_threshold_never_fires(k: int, row: LimitRow) -> None:
    """At the threshold is not a violation, however long it lasts."""
    d = Driver()
    for _ in range(row.debounce + math.ceil(row.delay_s / 0.1) + 50):
        d.step(with_value(row, row.threshold), docked=_docked(row))
    assert not d.ctl.is_active(0, k)


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_a_value_exactly_at_reset_clears(k: int, row: LimitRow) -> None:
    """At the reset value is past it: an auto row clears after its latch, a manual row accepts
    an explicit reset."""
    d = Driver()
    _fire(d, k, row)
    at_reset = with_value(row, row.reset)
    if row.latch_s is None:
        d.step(at_reset, docked=_docked(row))
        assert d.ctl.reset_trips(0) >= 1
        assert not d.ctl.is_active(0, k)
        return
    for _ in range(math.ceil(row.latch_s / 0.1) + 2):
        d.step(at_reset, docked=_docked(row))
    assert not d.ctl.is_active(0, k)


@pytest.mark.parametrize(
    ("limit", "current_a", "channel"),
    [
        ("over_current_discharge", 21.0 * CAP, "limit_dsg_a"),
        ("over_current_charge", -3.1 * CAP, "limit_chg_a"),
    ],
)
def test_a_trip_zeroes_its_published_limit_where_the_tables_allow_current(
    limit: str, current_a: float, channel: str
) -> None:
    """3.7 V, 25 degC, SOC 0.5: the tables allow 2C charge / 15C discharge; the trip says 0."""
    k = next(k for k, r in ROWS if r.limit == limit and r.tier == "trip")
    d = Driver()
    for _ in range(20):
        out = d.step(healthy(current_a=current_a))
    assert d.ctl.is_active(0, k)
    assert out.status[channel] == [0.0]
    rested = d.step(healthy(current_a=0.0))  # still latched (30 s): the table would give > 0
    assert d.ctl.is_active(0, k)
    assert rested.status[channel] == [0.0]


def test_nan_never_clears_an_auto_row_after_its_latch() -> None:
    """A NaN temperature for longer than latch_s (60 s) holds an over-temperature trip; a real
    safe reading then clears it."""
    k, row = next((k, r) for k, r in ROWS if r.limit == "over_temp_discharge" and r.tier == "trip")
    assert row.latch_s is not None
    d = Driver()
    _fire(d, k, row)
    for _ in range(round(row.latch_s) + 30):
        d.step(healthy(temp_c=math.nan, min_temp_c=math.nan), dt=1.0)
    assert d.ctl.is_active(0, k), "a NaN reading cleared the trip"
    d.step(healthy(temp_c=25.0))
    assert not d.ctl.is_active(0, k)


@pytest.mark.parametrize(
    ("limit", "current_a", "channel", "table_a"),
    [
        ("over_current_charge", -2.6 * CAP, "limit_chg_a", 2.0 * CAP),
        ("over_current_discharge", 19.0 * CAP, "limit_dsg_a", 15.0 * CAP),
    ],
)
def test_a_derate_row_scales_its_published_limit(
    limit: str, current_a: float, channel: str, table_a: float
) -> None:
    """While a derate row of a path is active its limit is the table's x derate_fraction."""
    k = next(k for k, r in ROWS if r.limit == limit and r.tier == "derate")
    d = Driver()
    for _ in range(20):
        out = d.step(healthy(current_a=current_a))
    assert d.ctl.is_active(0, k) and d.ctl.active_tier(0, limit) == "derate"
    assert out.status[channel] == [pytest.approx(0.5 * table_a)]


@pytest.mark.parametrize(
    ("nominal_ah", "limit_a"),
    [((CAP,), 15.0 * CAP), ((0.5,), 7.5), ((0.0,), 37.5), ((-1.0,), 37.5), ((math.nan,), 37.5)],
)
def test_the_c_rate_limit_uses_the_nominal_capacity_else_the_reported_one(
    nominal_ah: tuple[float, ...], limit_a: float
) -> None:
    """A C-rate becomes amperes with the pack's nominal capacity; only a nominal capacity that
    is not a positive number (absent, 0, negative) falls back to the battery's reported full
    capacity (control/battery.py; generated mutants d21b5f02f9, 6088d9ca6c, e8d489c81f,
    855fac0ef1, 0a77656af5). At
    3.7 V / 25 degC the discharge table allows 15 C."""
    info = dataclasses.replace(pack(1), capacity_ah=nominal_ah)
    ctl = LimitsController(LimitsConfig(), info)
    meas = Measurements(t_s=0.0, batteries=(healthy(full_capacity_ah=2.5),), bus_v=22.2)
    assert ctl.step(meas, 0.1).status["limit_dsg_a"] == [pytest.approx(limit_a)]


@pytest.mark.parametrize(
    ("full_ah", "limit_a"), [(0.5, 7.5), (0.0, math.nan), (-1.0, math.nan), (math.inf, math.nan)]
)
def test_an_unknown_capacity_publishes_an_unknown_limit(full_ah: float, limit_a: float) -> None:
    """No nominal capacity and a reported full capacity that is not a positive finite number:
    the limit is NaN (unknown), never 0 A, negative or infinite (generated mutants 942f3e18ae,
    34edf6e1e1, 04cc3e190d, 253073a3e2, 78a27d12a4, ebe7631e8f)."""
    info = dataclasses.replace(pack(1), capacity_ah=(math.nan,))
    ctl = LimitsController(LimitsConfig(), info)
    meas = Measurements(t_s=0.0, batteries=(healthy(full_capacity_ah=full_ah),), bus_v=22.2)
    assert ctl.step(meas, 0.1).status["limit_dsg_a"] == [pytest.approx(limit_a, nan_ok=True)]


def test_a_relay_conducts_only_with_both_feedbacks_closed() -> None:
    """The pack limit is N x the smallest limit of the N batteries that conduct: a relay whose
    feedback is half closed (charge on, discharge off, or the reverse) conducts neither way,
    unlike a MOSFET pair (control/battery.py ``conducts``; generated mutants a08e2ca1dc,
    85d534c192)."""
    for half in (SwitchState(chg_on=False, dsg_on=True), SwitchState(chg_on=True, dsg_on=False)):
        ctl = LimitsController(LimitsConfig(), pack(2, SwitchKind.RELAY))
        bms = (healthy(switch=CLOSED), healthy(switch=half))
        ctl.step(Measurements(t_s=0.0, batteries=bms, bus_v=22.2), 0.1)
        assert ctl.pack_limit_dsg_a == pytest.approx(15.0 * CAP)  # one battery, not two
        assert ctl.pack_limit_chg_a == pytest.approx(ctl.limit_chg_a[0])
    ctl = LimitsController(LimitsConfig(), pack(2))  # a MOSFET pair: its discharge FET decides
    bms = (healthy(switch=CLOSED), healthy(switch=SwitchState(chg_on=False, dsg_on=True)))
    ctl.step(Measurements(t_s=0.0, batteries=bms, bus_v=22.2), 0.1)
    assert ctl.pack_limit_dsg_a == pytest.approx(2 * 15.0 * CAP)


def test_an_explicit_reset_of_one_battery_leaves_the_others_latched() -> None:
    """``reset_trips(i)`` clears battery i's latched rows only; ``reset_trips()`` clears every
    battery's. Three batteries latched at the over-voltage trip (no latch time: held until an
    explicit reset), all back below the reset value."""
    k, row = next((k, r) for k, r in enumerate(DEFAULT_ROWS)
                  if r.limit == "over_voltage" and r.tier == "trip")  # fmt: skip
    assert row.latch_s is None
    d = Driver(n=3)
    hot = with_value(row, row.threshold + 0.05)
    for _ in range(400):
        d.step(hot, hot, hot)
    assert all(d.ctl.is_active(i, k) for i in range(3))
    ok = healthy()
    d.step(ok, ok, ok)
    assert d.ctl.reset_trips(1) >= 1
    assert [d.ctl.is_active(i, k) for i in range(3)] == [True, False, True]
    out = d.step(ok, ok, ok)  # the reset's events come with the next tick, naming battery 1
    resets = [(e.battery, e.data["row"]) for e in out.events if e.kind == "LimitReset"]
    assert (1, k) in resets and all(b == 1 for b, _ in resets)
    assert d.ctl.reset_trips(0) >= 1
    assert [d.ctl.is_active(i, k) for i in range(3)] == [False, False, True]
    assert d.ctl.reset_trips() >= 1
    assert not any(d.ctl.is_active(i, k) for i in range(3))


def _charge_trip() -> tuple[int, LimitRow]:
    """The over-temperature-while-charging trip (latched 60 s: the tests stay inside that)."""
    k, row = next((k, r) for k, r in enumerate(DEFAULT_ROWS)
                  if r.limit == "over_temp_charge" and r.tier == "trip")  # fmt: skip
    assert row.when == "charging" and row.direction == "above" and (row.latch_s or 0) >= 10
    return k, row


def test_a_charge_only_trip_can_be_reset_once_the_battery_no_longer_charges() -> None:
    """A row that applies only while charging is out of context once the pack is undocked and
    the battery not charged: an explicit reset clears it even with its quantity still beyond
    the reset value (generated mutant ae7f2d2c03: the out-of-context row kept refusing)."""
    k, row = _charge_trip()
    d = Driver()
    hot = with_value(row, row.threshold + 1.0)
    for _ in range(30):
        d.step(hot, docked=True)
    assert d.ctl.is_active(0, k)
    assert d.ctl.reset_trips() == 0  # still charging and beyond the reset value
    d.step(hot, docked=False)
    assert d.ctl.reset_trips() >= 1
    assert not d.ctl.is_active(0, k)


def test_an_absent_battery_takes_no_charging_context_from_its_neighbour() -> None:
    """An absent battery's rows are judged in its own context (charging only when docked), not
    in the one left by the battery before it: undocked, with battery 0 cross-charged at 1C,
    absent battery 1's latched charge-only trip is out of context and can be reset
    (generated mutant 0472b2b94f)."""
    k, row = _charge_trip()
    d = Driver(n=2)
    hot = with_value(row, row.threshold + 1.0)
    for _ in range(30):
        d.step(healthy(), hot, docked=True)
    assert d.ctl.is_active(1, k)
    charged = healthy(current_a=-CAP)  # 1C into battery 0: its charge context is on
    d.step(charged, None, docked=False)  # type: ignore[arg-type]
    assert d.ctl.reset_trips(1) >= 1
    assert not d.ctl.is_active(1, k)


def test_a_battery_not_charged_has_a_charge_c_rate_of_zero() -> None:
    """At rest or discharging the charge C-rate is 0, however small the battery: a 0.25 Ah
    battery at 0 A or at +1 A (discharge) never reaches the over-current-charge rows (2 / 2.5 /
    3 C) and keeps its table charge limit (generated mutant e604a6a3b4: ``fmax(1.0, -cur)``
    read 1 A / 0.25 Ah = 4 C at rest and tripped the charge path)."""
    info = dataclasses.replace(pack(1), capacity_ah=(0.25,))
    for cur in (0.0, 1.0):
        ctl = LimitsController(LimitsConfig(), info)
        for k in range(40):  # 4 s: beyond every over-current-charge row's debounce + delay
            bm = healthy(current_a=cur, full_capacity_ah=0.25)
            out = ctl.step(Measurements(t_s=0.1 * k, batteries=(bm,), bus_v=22.2), 0.1)
        assert ctl.active_tier(0, "over_current_charge") == "ok"
        assert out.status["limit_chg_a"] == [pytest.approx(2.0 * 0.25)]  # 2C at 3.7 V, 25 degC


def test_a_conducting_battery_with_an_unknown_limit_makes_the_pack_limit_unknown() -> None:
    """The pack limit is N x the smallest battery limit only if every conducting battery's
    limit is known: one with an unknown capacity (limit NaN) makes the pack's charge and
    discharge limits unknown, not 2 x the other's (generated mutant 0155fc093a: the charge
    side's "any unknown" turned into "all unknown")."""
    for order in ((CAP, math.nan), (math.nan, CAP)):
        info = dataclasses.replace(pack(2), capacity_ah=order)
        ctl = LimitsController(LimitsConfig(), info)
        bms = tuple(healthy(switch=CLOSED, full_capacity_ah=0.0 if math.isnan(c) else CAP)
                    for c in order)  # fmt: skip
        ctl.step(Measurements(t_s=0.0, batteries=bms, bus_v=22.2), 0.1)
        assert math.isnan(ctl.pack_limit_chg_a)
        assert math.isnan(ctl.pack_limit_dsg_a)


def test_with_an_unknown_capacity_any_charge_current_is_charging() -> None:
    """The charging context needs a charge current beyond context_current_c x capacity; with
    the capacity unknown the band is 0, so 0.5 A of charge undocked already counts and a
    charge-only over-temperature trips (generated mutant 73738ae471: a 1 A band hid it)."""
    k, row = _charge_trip()
    info = dataclasses.replace(pack(1), capacity_ah=(math.nan,))
    ctl = LimitsController(LimitsConfig(), info)
    for j in range(30):
        bm = healthy(current_a=-0.5, full_capacity_ah=0.0, temp_c=row.threshold + 1.0)
        ctl.step(Measurements(t_s=0.1 * j, batteries=(bm,), bus_v=22.2), 0.1)
    assert ctl.is_active(0, k)
