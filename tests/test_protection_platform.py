"""Protection's platform interface (#15 §4): the warning before the trip, the predicted time
to trip and the time to empty, as status channels and events of the compiled controller."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from packpilot.control.protection import ProtectionConfig
from tests.test_protection_controller import Driver, _bm


def _warnings(d: Driver) -> list[object]:
    return d.events("ProtectionWarning")


def _ttt(d: Driver) -> float | None:
    return d.outputs[-1].status["protection_time_to_trip_s"][0]  # type: ignore[no-any-return]


def _tte(d: Driver) -> float | None:
    return d.outputs[-1].status["protection_time_to_empty_s"][0]  # type: ignore[no-any-return]


def test_warning_fires_exactly_at_half_the_allowance() -> None:
    d = Driver()
    d.run(2.0, 10.0, 25.0, 3.1, dt=0.5)  # P3: 5 s allowance, 2 s used = 0.4
    assert _warnings(d) == []
    d.run(0.5, 10.0, 25.0, 3.1, dt=0.5)  # 2.5 s = 0.5 exactly
    (w,) = _warnings(d)
    data = w.data  # type: ignore[attr-defined]
    assert data["param"] == "P3"
    assert data["fraction"] == 0.5
    assert data["share"] == 0.5
    assert data["time_to_trip_s"] == pytest.approx(2.5)
    assert data["current_a"] == 10.0
    assert d.trip_end_s is None


def test_warning_once_per_episode_then_the_trip() -> None:
    d = Driver()
    d.run(4.5, 10.0, 25.0, 3.1, dt=0.5)
    assert len(_warnings(d)) == 1
    d.run(0.5, 10.0, 25.0, 3.1, dt=0.5)
    assert d.trip_end_s == 5.0
    d.run(3.0, 10.0, 25.0, 3.1, dt=0.5)
    assert len(_warnings(d)) == 1


def test_warning_re_armed_after_a_new_cycle() -> None:
    d = Driver()
    d.run(3.0, 10.0, 25.0, 3.1)  # warned at 3 s (0.6)
    assert len(_warnings(d)) == 1
    d.run(10.0, -2.0, 25.0, 3.6)  # sustained charge: new cycle, sum 0
    assert d.ctl.fraction(0) == 0.0
    d.run(2.0, 10.0, 25.0, 3.1)  # 0.4: not yet
    assert len(_warnings(d)) == 1
    d.run(1.0, 10.0, 25.0, 3.1)  # 0.6: again
    assert len(_warnings(d)) == 2


def test_warning_re_armed_when_the_share_falls_back_on_recovery() -> None:
    d = Driver(ProtectionConfig(reset_on_recovery=True))
    d.run(3.0, 10.0, 25.0, 3.1)
    assert len(_warnings(d)) == 1
    d.run(1.0, 10.0, 25.0, 3.5)  # recovered: sum reset
    d.run(3.0, 10.0, 25.0, 3.1)
    assert len(_warnings(d)) == 2


@pytest.mark.parametrize(("share", "at_s"), [(0.8, 12.0), (0.2, 3.0)])
def test_warning_share_is_configurable(share: float, at_s: float) -> None:
    d = Driver(ProtectionConfig(warning_share=share))
    d.run(at_s - 1.0, 30.0, 25.0, 2.7)  # P1: 15 s allowance
    assert _warnings(d) == []
    d.run(1.0, 30.0, 25.0, 2.7)
    assert len(_warnings(d)) == 1


def test_a_tick_that_trips_reports_the_trip_alone() -> None:
    d = Driver(ProtectionConfig(warning_share=1.0))
    d.run(5.0, 10.0, 25.0, 3.1)
    assert d.trip_end_s == 5.0
    assert _warnings(d) == []


def test_share_one_with_strict_trip_warns_at_the_allowance() -> None:
    d = Driver(ProtectionConfig(warning_share=1.0, trip_comparison=">"))
    d.run(5.0, 10.0, 25.0, 3.1)
    assert len(_warnings(d)) == 1
    assert d.trip_end_s is None


def test_no_warning_above_the_cut_off() -> None:
    d = Driver()
    d.run(30.0, 10.0, 25.0, 3.3)
    assert _warnings(d) == []


def test_warning_share_validated() -> None:
    for bad in (0.0, -0.1, 1.5, math.nan):
        with pytest.raises(ValueError):
            ProtectionConfig(warning_share=bad)
    with pytest.raises(ValueError):
        ProtectionConfig(predict_tau_s=0.0)


# ---- predicted time to trip ------------------------------------------------------------------


def test_time_to_trip_below_the_cut_off_is_the_allowance_left() -> None:
    d = Driver()
    d.run(2.0, 10.0, 25.0, 3.1)  # P3, 2 of 5 s
    assert _ttt(d) == pytest.approx(3.0)
    d.run(1.0, 30.0, 25.0, 2.7)  # P1: 2/5 + 1/15 used; left (1 - 7/15) x 15 s = 8 s
    assert _ttt(d) == pytest.approx(8.0)
    d.run(8.0, 30.0, 25.0, 2.7)
    assert d.trip_end_s == 11.0
    assert _ttt(d) == 0.0


def test_time_to_trip_none_when_not_discharging() -> None:
    d = Driver()
    d.run(2.0, 10.0, 25.0, 3.1)
    d.run(1.0, 0.0, 25.0, 3.1)
    assert _ttt(d) is None
    d.run(1.0, 0.4, 25.0, 3.1)  # below the 0.5 A discharge threshold
    assert _ttt(d) is None


def test_time_to_trip_above_the_cut_off_follows_the_voltage_slope() -> None:
    d = Driver()
    v = 3.5
    for _ in range(10):
        d.step(_bm(10.0, 25.0, v), 1.0)
        v -= 0.01  # 10 mV/s towards the 3.2 V cut-off of P3
    # last sample 3.41 V: 21 s to 3.2 V at 10 mV/s, then 5 s at or below it
    assert _ttt(d) == pytest.approx(26.0, rel=1e-6)
    d.run(30.0, 10.0, 25.0, 3.45)  # flat: slope decays to 0 from below, large time
    t_flat = _ttt(d)
    assert t_flat is None or t_flat > 1000.0
    for k in range(5):
        v = 3.45 + 0.01 * (k + 1)
        d.step(_bm(10.0, 25.0, v), 1.0)
    assert _ttt(d) is None  # rising voltage: no trip predicted


def test_time_to_trip_at_the_cut_off_with_strict_comparison() -> None:
    d = Driver(ProtectionConfig(voltage_comparison="<"))
    d.run(3.0, 10.0, 25.0, 3.2)  # at, not below: nothing accumulates, flat slope
    assert d.ctl.fraction(0) == 0.0
    assert _ttt(d) is None
    d2 = Driver()
    d2.run(3.0, 10.0, 25.0, 3.2)  # "<=": counts
    assert _ttt(d2) == pytest.approx(2.0)


# ---- time to empty ---------------------------------------------------------------------------


def test_time_to_empty_from_remaining_capacity() -> None:
    d = Driver()
    d.run(1.0, 10.0, 25.0, 3.6)  # 0.5 Ah at 10 A = 180 s
    assert _tte(d) == pytest.approx(180.0)
    d.step(_bm(20.0, 25.0, 3.6), 1.0)
    assert _tte(d) == pytest.approx(90.0)
    d.step(replace(_bm(10.0, 25.0, 3.6), remaining_capacity_ah=math.nan), 1.0)
    assert _tte(d) == pytest.approx(180.0)  # soc 0.1 x 5 Ah
    d.step(replace(_bm(10.0, 25.0, 3.6), remaining_capacity_ah=0.0), 1.0)
    assert _tte(d) == 0.0
    d.step(replace(_bm(10.0, 25.0, 3.6), remaining_capacity_ah=math.nan, soc=math.nan), 1.0)
    assert _tte(d) is None


@pytest.mark.parametrize("current", [0.0, 0.4, 0.5, -3.0, math.nan])
def test_time_to_empty_none_when_not_discharging(current: float) -> None:
    d = Driver()
    d.step(_bm(current, 25.0, 3.6), 1.0)
    assert _tte(d) is None


def test_time_to_empty_just_above_the_discharge_threshold() -> None:
    d = Driver()
    d.step(_bm(0.6, 25.0, 3.6), 1.0)
    assert _tte(d) == pytest.approx(3000.0)


def test_time_to_trip_none_for_a_flat_voltage_above_the_cut_off() -> None:
    d = Driver()
    d.run(5.0, 10.0, 25.0, 3.5)  # slope exactly 0: no crossing predicted
    assert _ttt(d) is None


def test_time_to_empty_of_a_negative_remaining_capacity_is_zero() -> None:
    """A gauge that reads below empty (-0.5 Ah, as coulomb counters drift) means empty now:
    0 s, never a negative time (generated mutant 6a99f4f03e: the early 0 dropped, -180 s)."""
    d = Driver()
    d.step(replace(_bm(10.0, 25.0, 3.6), remaining_capacity_ah=-0.5), 1.0)
    assert _tte(d) == 0.0
