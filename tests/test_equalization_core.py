"""Pure rules of the Newton-iterated equalizer: formulas, timers, subtract-min, time, config."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from packpilot.control.equalization import (
    AhUpdate,
    EqualizationConfig,
    SampleResult,
    balancing_time_s,
    equalizer_current_a,
    formula1,
    formula2,
    lower_median,
    sample_groups,
)

CFG = EqualizationConfig()


def run_samples(
    voltages: list[float],
    n: int,
    cfg: EqualizationConfig = CFG,
    ah: list[float] | None = None,
    ts: float = 1.0,
) -> tuple[SampleResult, list[AhUpdate]]:
    """Feed the same group voltages ``n`` times; return the last result and all updates."""
    m = len(voltages)
    ah = list(ah) if ah is not None else [0.0] * m
    hi = [0.0] * m
    lo = [0.0] * m
    updates: list[AhUpdate] = []
    res = None
    for _ in range(n):
        res = sample_groups(voltages, ah, hi, lo, ts, cfg)
        ah, hi, lo = list(res.ah), list(res.hi_timer_s), list(res.lo_timer_s)
        updates.extend(res.updates)
    assert res is not None
    return res, updates


def test_formula1_sequence_from_zero() -> None:
    seq = []
    ah = 0.0
    for _ in range(4):
        ah = formula1(ah, 0.5)
        seq.append(ah)
    assert seq == [0.25, 0.375, 0.4375, 0.46875]


def test_formula2_halves() -> None:
    assert formula2(0.4375) == 0.21875
    assert formula2(0.0) == 0.0


def test_lagging_group_follows_formula1_every_t1() -> None:
    # Group 0 is 30 mV low: ΔV0 = +22.5 mV > 5 mV; the others are below dv_set.
    v = [12.97, 13.0, 13.0, 13.0]
    res, ups = run_samples(v, 360)
    f1 = [u for u in ups if u.formula == "formula1"]
    assert [u.group for u in f1] == [0, 0, 0]
    assert [u.new_ah for u in f1] == [0.25, 0.375, 0.4375]
    assert res.ah[0] == 0.4375
    assert res.ah[1:] == (0.0, 0.0, 0.0)
    assert math.isclose(res.dv_v[0], 0.0225, abs_tol=1e-12)


def test_formula1_fires_exactly_at_t1() -> None:
    v = [12.97, 13.0, 13.0, 13.0]
    res, ups = run_samples(v, 119)
    assert not [u for u in ups if u.formula == "formula1"]
    assert res.hi_timer_s[0] == pytest.approx(119.0)
    res2 = sample_groups(v, res.ah, res.hi_timer_s, res.lo_timer_s, 1.0, CFG)
    assert [u.formula for u in res2.updates if u.group == 0] == ["formula1"]
    assert res2.hi_timer_s[0] == pytest.approx(0.0)


def test_timer_resets_when_condition_breaks() -> None:
    low = [12.97, 13.0, 13.0, 13.0]
    even = [13.0, 13.0, 13.0, 13.0]
    res, _ = run_samples(low, 100)
    assert res.hi_timer_s[0] == pytest.approx(100.0)
    # One sample with group 0 no longer lagging: hi timer resets, lo timer starts.
    res = sample_groups(even, res.ah, res.hi_timer_s, res.lo_timer_s, 1.0, CFG)
    assert res.hi_timer_s[0] == 0.0
    assert res.lo_timer_s[0] == 1.0
    # Another 100 s lagging: still no formula 1 (would need 120 s uninterrupted).
    ah, hi, lo = res.ah, res.hi_timer_s, res.lo_timer_s
    fired = []
    for _ in range(100):
        r = sample_groups(low, ah, hi, lo, 1.0, CFG)
        ah, hi, lo = r.ah, r.hi_timer_s, r.lo_timer_s
        fired += [u for u in r.updates if u.formula == "formula1"]
    assert fired == []
    assert lo[0] == 0.0


def test_formula2_every_t2_while_leading() -> None:
    v = [13.01, 13.0, 13.0, 13.0]  # group 0 leads; the others stay below dv_set
    res, ups = run_samples(v, 180, ah=[0.4, 0.0, 0.0, 0.0])
    g0 = [u for u in ups if u.group == 0]
    assert [u.formula for u in g0] == ["formula2"] * 3
    assert res.ah[0] == pytest.approx(0.05)


def test_equal_condition_updates_nothing_and_resets_timers() -> None:
    # Two groups 1 V apart: ΔV = ±0.5 V exactly; with dv_set = 0.5 group 0 is "equal".
    cfg = EqualizationConfig(dv_set_v=0.5)
    res = sample_groups([12.0, 13.0], [0.3, 0.0], [50.0, 0.0], [20.0, 0.0], 1.0, cfg)
    assert res.dv_v[0] == 0.5
    assert res.hi_timer_s[0] == 0.0 and res.lo_timer_s[0] == 0.0
    res, ups = run_samples([12.0, 13.0], 1000, cfg, ah=[0.3, 0.0])
    assert res.ah[0] == 0.3
    assert all(u.group == 1 for u in ups)


def test_subtract_min_when_all_positive() -> None:
    res = sample_groups(
        [13.0, 13.0, 13.0], [0.3, 0.2, 0.1], [0.0] * 3, [0.0] * 3, 1.0, CFG
    )  # no timer fires in one sample
    assert res.subtracted_min
    assert res.ah == pytest.approx((0.2, 0.1, 0.0))
    assert [u.formula for u in res.updates] == ["subtract_min"] * 3


def test_no_subtract_when_one_is_zero() -> None:
    res = sample_groups([13.0, 13.0], [0.3, 0.0], [0.0, 0.0], [0.0, 0.0], 1.0, CFG)
    assert not res.subtracted_min
    assert res.ah == (0.3, 0.0)


def test_subtract_min_after_halving() -> None:
    # Group 1 lags, group 0 leads; both start positive: the halving of group 0 keeps it > 0,
    # so after each sample the minimum is removed and the leader ends at exactly 0.
    res, ups = run_samples([13.02, 12.98], 60, ah=[0.2, 0.1])
    assert any(u.formula == "subtract_min" for u in ups)
    assert min(res.ah) == 0.0


def test_long_sample_applies_formula_repeatedly() -> None:
    res = sample_groups([12.97, 13.0, 13.0, 13.0], [0.0] * 4, [0.0] * 4, [0.0] * 4, 360.0, CFG)
    assert [u.new_ah for u in res.updates if u.formula == "formula1"] == [0.25, 0.375, 0.4375]


def test_balancing_time_string_current() -> None:
    cfg = EqualizationConfig(equalizer_max_a=5.0)
    assert balancing_time_s(0.25, 2.0, cfg) == pytest.approx(450.0)  # 3600·0.25/2
    assert balancing_time_s(0.25, -2.0, cfg) == pytest.approx(450.0)  # charging works too
    # String current above the equalizer rating: time uses the clamped current.
    assert balancing_time_s(0.25, 50.0, cfg) == pytest.approx(180.0)
    # Below the minimum current: skipped.
    assert balancing_time_s(0.25, 0.1, cfg) == 0.0
    # No clamp to the update period (issue #15): the time is proportional to AH.
    assert balancing_time_s(0.4375, 2.0, cfg) == pytest.approx(787.5)
    assert balancing_time_s(0.0, 2.0, cfg) == 0.0


def test_balancing_time_fixed_current() -> None:
    cfg = EqualizationConfig(time_mode="fixed_current", fixed_current_a=1.5)
    assert balancing_time_s(0.3, 40.0, cfg) == pytest.approx(720.0)  # 3600·0.3/1.5
    assert balancing_time_s(0.3, 0.0, cfg) == 0.0  # gate closed at rest
    rest = cfg.model_copy(update={"balance_at_rest": True})
    assert balancing_time_s(0.3, 0.0, rest) == pytest.approx(720.0)


def test_equalizer_current() -> None:
    cfg = EqualizationConfig(equalizer_max_a=3.0, min_current_a=0.5)
    assert equalizer_current_a(-1.0, cfg) == 1.0
    assert equalizer_current_a(20.0, cfg) == 3.0
    assert equalizer_current_a(0.4, cfg) == 0.0


def test_lower_median() -> None:
    assert lower_median([0.0, 1.0, 1.0, 1.0]) == 1.0
    assert lower_median([0.0, 0.0, 1.0, 1.0]) == 0.0
    assert lower_median([1.0, 0.0, 0.0]) == 0.0


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"t1_s": 60.0, "t2_s": 60.0}, "t1_s"),
        ({"t1_s": 30.0, "t2_s": 60.0}, "t1_s"),
        ({"n_ah": 1.5}, "n_ah"),
        ({"n_ah": -0.1}, "n_ah"),
        ({"dv_set_v": 0.0}, "dv_set_v"),
        ({"dv_set_v": -0.005}, "dv_set_v"),
        ({"t2_s": -1.0}, "t2_s"),
        ({"sample_period_s": 0.0}, "sample_period_s"),
        ({"equalizer_max_a": 0.0}, "equalizer_max_a"),
        ({"fixed_current_a": 3.0, "equalizer_max_a": 2.0}, "fixed_current_a"),
        ({"balance_at_rest": True}, "balance_at_rest"),
        ({"max_balance_time_s": 500.0}, "max_balance_time_s"),
        ({"ah_per": "battery"}, "ah_per"),
        ({"min_current_a": float("nan")}, "min_current_a"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_config_rejections_name_the_field(kwargs: dict[str, object], field: str) -> None:
    with pytest.raises(ValidationError) as err:
        EqualizationConfig(**kwargs)
    assert field in str(err.value)


def test_config_defaults() -> None:
    assert (CFG.dv_set_v, CFG.t1_s, CFG.t2_s, CFG.n_ah) == (0.005, 120.0, 60.0, 0.5)
    assert CFG.max_balance_time_s is None
    assert CFG.ah_per == "cell"  # the claims: one unit balancing Ah per cell
    assert EqualizationConfig(n_ah=0.0).n_ah == 0.0
    assert EqualizationConfig(n_ah=1.0).n_ah == 1.0


def test_the_group_average_is_fsum_exactly_at_half_way_cases() -> None:
    """The average group voltage uses ``math.fsum`` (rules.exact_sum: Shewchuk's partials and
    CPython's half-even rounding across them). CPython's own fsum cases where that last
    correction decides (a sum exactly half-way between two floats, with a tiny partial below
    it that breaks the tie) must come out as fsum's, and so must the dv of every group
    (generated mutants b12c5bfc04: the correction skipped with two partials left;
    87b65a253d: applied when only one of the two partials agreed in sign)."""
    from packpilot.control.equalization.rules import exact_sum

    cases = [
        [2.0**53, 1.0, 2.0**-100],
        [2.0**53, 1.0, -(2.0**-100)],
        [2.0**53 + 10.0, 1.0, 2.0**-100],
        [2.0**53 - 4.0, 0.5, 2.0**-54],
        [2.0**53, -0.5, -(2.0**-54)],
        [1.0, 1e100, 1.0, -1e100],
        [1e16, 1.0, 1e-16],
        [13.0, 13.0 + 2.0**-49, 13.0, 13.0 - 2.0**-49],
        # partials whose top two add exactly, so the smallest one is still to come (generated
        # mutant c6ec6d8aaf: the top-down loop stopped one partial early; found by a random
        # search against math.fsum)
        [4.323455642275676e17, -917504.0, -1.7462298274040222e-10, 0.0234375,
         -4.323455642275676e17],
        [-2.7939677238464355e-09, -8.0, 3145728.0, 1.7462298274040222e-10, -4194304.0],
    ]
    for xs in cases:
        arr = np.array(xs, np.float64)
        assert exact_sum(arr, len(xs), np.zeros(len(xs) + 1)) == math.fsum(xs), xs
        res = sample_groups(xs, [0.0] * len(xs), [0.0] * len(xs), [0.0] * len(xs), 1.0, CFG)
        avg = math.fsum(xs) / len(xs)
        assert res.dv_v == tuple(avg - x for x in xs), xs
