"""LimitsController: every row of the DEFAULT table trips after its debounce + delay (not
before) and clears per its hysteresis and latch; commands and events per tier."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from packpilot.contract.bms import ControlOutput, SwitchKind
from packpilot.contract.charger import CHARGER_OFF
from packpilot.control.limits import DEFAULT_ROWS, TIER_EVENT, LimitRow, LimitsConfig
from tests.test_limits_helpers import CAP, DELTA, DT, Driver, healthy, with_value


def beyond(row: LimitRow) -> float:
    return row.threshold + DELTA if row.direction == "above" else row.threshold - DELTA


def between(row: LimitRow) -> float:
    return 0.5 * (row.threshold + row.reset)


def safe(row: LimitRow) -> float:
    return row.reset - DELTA if row.direction == "above" else row.reset + DELTA


def samples_to_fire(row: LimitRow, dt: float = DT) -> int:
    return row.debounce + math.ceil(row.delay_s / dt - 1e-9)


ROWS = list(enumerate(DEFAULT_ROWS))
IDS = [f"{r.limit}-{r.tier}" for r in DEFAULT_ROWS]


def _fire(d: Driver, k: int, row: LimitRow) -> tuple[ControlOutput, bool]:
    docked = row.when == "charging"
    need = samples_to_fire(row)
    out = None
    for s in range(need):
        out = d.step(with_value(row, beyond(row)), docked=docked)
        if s < need - 1:
            assert not d.ctl.is_active(0, k), f"active after {s + 1} < {need} samples"
    assert out is not None
    return out, docked


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_row_fires_after_debounce_and_delay_not_before(k: int, row: LimitRow) -> None:
    d = Driver()
    out, docked = _fire(d, k, row)
    assert d.ctl.is_active(0, k)
    mine = [e for e in out.events if e.data.get("row") == k]
    assert [e.kind for e in mine] == [TIER_EVENT[row.tier]]
    assert mine[0].data["threshold"] == row.threshold
    assert mine[0].data["value"] == pytest.approx(beyond(row))
    cmd = out.commands
    if row.tier == "trip":
        opened = cmd.chg_on[0] if row.path == "charge" else cmd.dsg_on[0]
        assert opened is False
        assert (cmd.charger == CHARGER_OFF) == (row.path == "charge" and docked)
        assert out.status[f"lim_{row.limit}"][0] == "trip"
    else:
        assert cmd.chg_on == (None,) and cmd.dsg_on == (None,) and cmd.charger is None
        assert out.status[f"lim_{row.limit}"][0] == row.tier


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_interrupted_violation_restarts_the_debounce(k: int, row: LimitRow) -> None:
    d = Driver()
    docked = row.when == "charging"
    need = samples_to_fire(row)
    for _ in range(need - 1):
        d.step(with_value(row, beyond(row)), docked=docked)
    d.step(with_value(row, between(row)), docked=docked)  # not violating: count restarts
    for _ in range(need - 1):
        d.step(with_value(row, beyond(row)), docked=docked)
    assert not d.ctl.is_active(0, k)
    d.step(with_value(row, beyond(row)), docked=docked)
    assert d.ctl.is_active(0, k)


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_row_holds_inside_the_hysteresis_band(k: int, row: LimitRow) -> None:
    d = Driver()
    _, docked = _fire(d, k, row)
    hold_s = (row.latch_s or 0.0) + 5.0
    for _ in range(round(hold_s / DT)):
        d.step(with_value(row, between(row)), docked=docked)
    assert d.ctl.is_active(0, k), "cleared before the quantity passed the reset value"
    out = d.step(with_value(row, safe(row)), docked=docked)
    if row.latch_s is None:
        assert d.ctl.is_active(0, k), "a manual-reset row cleared by itself"
    else:
        assert not d.ctl.is_active(0, k)
        resets = [e for e in out.events if e.kind == "LimitReset" and e.data["row"] == k]
        assert len(resets) == 1 and resets[0].data["manual"] is False


@pytest.mark.parametrize(("k", "row"), ROWS, ids=IDS)
def test_row_latches_for_latch_s_or_until_explicit_reset(k: int, row: LimitRow) -> None:
    d = Driver()
    _, docked = _fire(d, k, row)
    if row.latch_s is None:
        for _ in range(round(600.0 / 1.0)):
            d.step(with_value(row, safe(row)), docked=docked, dt=1.0)
        assert d.ctl.is_active(0, k)
        assert d.ctl.reset_trips(0) >= 1
        assert not d.ctl.is_active(0, k)
        out = d.step(with_value(row, safe(row)), docked=docked)
        resets = [e for e in out.events if e.kind == "LimitReset" and e.data["row"] == k]
        assert len(resets) == 1 and resets[0].data["manual"] is True
        cmd = out.commands
        assert cmd.chg_on == (None,) and cmd.dsg_on == (None,)  # no opinion once cleared
        return
    steps = math.ceil(row.latch_s / DT - 1e-9)
    for s in range(max(steps, 1)):
        d.step(with_value(row, safe(row)), docked=docked)
        if s < steps - 1:
            assert d.ctl.is_active(0, k), f"cleared after {s + 1} of {steps} latch steps"
    assert not d.ctl.is_active(0, k)


def test_explicit_reset_refuses_while_still_beyond_reset_value() -> None:
    k, row = next((k, r) for k, r in ROWS if r.limit == "over_voltage" and r.tier == "trip")
    d = Driver()
    _fire(d, k, row)
    d.step(with_value(row, between(row)))
    assert d.ctl.reset_trips() == 0
    assert d.ctl.is_active(0, k)


def test_nan_value_holds_state_and_counters() -> None:
    k, row = next((k, r) for k, r in ROWS if r.limit == "under_voltage" and r.tier == "trip")
    d = Driver()
    need = samples_to_fire(row)
    for _ in range(need - 1):
        d.step(with_value(row, beyond(row)))
    d.step(healthy(min_cell_v=math.nan))  # unknown: neither counts nor resets
    d.step(with_value(row, beyond(row)))
    assert d.ctl.is_active(0, k)
    for _ in range(100):
        d.step(healthy(min_cell_v=math.nan))
    assert d.ctl.is_active(0, k)


def test_charge_context_rows_only_count_while_charging() -> None:
    k, row = next((k, r) for k, r in ROWS if r.limit == "over_temp_charge" and r.tier == "trip")
    d = Driver()
    for _ in range(200):  # 44-46 degC while flying: the charge limit does not apply
        d.step(healthy(temp_c=46.0, current_a=10.0))
    assert not d.ctl.is_active(0, k)
    for _ in range(samples_to_fire(row)):  # cross-charged by a sibling at 1C: it does
        out = d.step(healthy(temp_c=46.0, current_a=-CAP))
    assert d.ctl.is_active(0, k)
    assert out.commands.chg_on == (False,) and out.commands.charger is None  # not docked


def test_relay_battery_trip_opens_the_relay_and_stops_the_docked_charger() -> None:
    row = next(r for r in DEFAULT_ROWS if r.limit == "over_voltage" and r.tier == "trip")
    d = Driver(n=2, kind=SwitchKind.RELAY)
    for _ in range(samples_to_fire(row)):
        out = d.step(with_value(row, beyond(row)), healthy(), docked=True)
    assert out.commands.chg_on == (False, None)
    assert out.commands.dsg_on == (None, None)
    assert out.commands.charger == CHARGER_OFF


def test_delay_counts_time_not_samples() -> None:
    row = LimitRow(
        limit="uv",
        quantity="cell_v_min",
        direction="below",
        path="discharge",
        tier="trip",
        threshold=3.0,
        reset=3.2,
        debounce=2,
        delay_s=2.0,
    )
    for dt, need in ((0.1, 22), (0.5, 6), (1.0, 4), (3.0, 3)):
        d = Driver(LimitsConfig(rows=(row,)))
        fired_at = None
        for s in range(40):
            d.step(healthy(min_cell_v=2.9), dt=dt)
            if d.ctl.is_active(0, 0):
                fired_at = s + 1
                break
        assert fired_at == need, (dt, fired_at)


def test_absent_battery_opens_nothing_and_counts_nothing() -> None:
    d = Driver(n=2)
    for _ in range(100):
        out = d.step(healthy(), replace(healthy(min_cell_v=2.0), present=False))
    assert out.commands.dsg_on == (None, None)
    assert not out.events
    assert out.status["limit_dsg_a"][1] == 0.0
