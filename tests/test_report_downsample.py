"""Downsampling for report plots: few points, yet every extreme, gap and step survives."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from packpilot.report.charts import spans
from packpilot.report.downsample import (
    change_indices,
    downsample,
    minmax_indices,
    step_indices,
)
from tests.budget import budget

floats = st.one_of(st.floats(-1e6, 1e6), st.just(math.nan))
series = hnp.arrays(np.float64, st.integers(0, 3000), elements=floats)


@budget(200)
@given(y=series, max_points=st.integers(8, 400))
def test_minmax_keeps_extremes_gaps_and_ends(y: np.ndarray, max_points: int) -> None:
    idx = minmax_indices(y, max_points)
    n = len(y)
    assert len(idx) <= max_points
    assert np.all(np.diff(idx) > 0) and (n == 0 or (idx[0] == 0 and idx[-1] == n - 1))
    sel = y[idx]
    finite = np.isfinite(y)
    if finite.any():
        assert np.nanmin(sel) == np.nanmin(y) and np.nanmax(sel) == np.nanmax(y)
    if np.isnan(y).any():
        assert np.isnan(sel).any()  # a gap in the data stays a gap in the line


@budget(200)
@given(y=hnp.arrays(np.float64, st.integers(500, 4000), elements=st.floats(-10, 10)))
def test_minmax_keeps_each_buckets_extremes(y: np.ndarray) -> None:
    """Every bucket keeps a sample at its minimum and one at its maximum."""
    max_points = 50
    idx = minmax_indices(y, max_points)
    size = -(-len(y) // ((max_points - 2) // 2))
    kept = np.zeros(len(y), dtype=bool)
    kept[idx] = True
    for start in range(0, len(y), size):
        win = slice(start, start + size)
        assert np.min(y[win][kept[win]]) == np.min(y[win])
        assert np.max(y[win][kept[win]]) == np.max(y[win])


def test_spike_survives_and_point_count_is_capped() -> None:
    t = np.arange(1_000_000) * 0.1
    y = np.sin(t / 100.0)
    y[777_777] = 50.0
    y[333_333] = -50.0
    tt, yy = downsample(t, y, 5000)
    assert len(yy) <= 5000 and yy.max() == 50.0 and yy.min() == -50.0
    assert tt[0] == t[0] and tt[-1] == t[-1]


def test_minmax_rejects_a_silly_budget() -> None:
    with pytest.raises(ValueError, match="max_points"):
        minmax_indices(np.zeros(10), 3)


def _forward_fill(n: int, idx: np.ndarray, vals: np.ndarray) -> list[object]:
    out: list[object] = []
    j = 0
    for i in range(n):
        while j + 1 < len(idx) and idx[j + 1] <= i:
            j += 1
        out.append(vals[j])
    return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return a == b


@budget(200)
@given(
    y=hnp.arrays(
        np.float64, st.integers(0, 400), elements=st.sampled_from([0.0, 1.0, 2.5, math.nan])
    )
)
def test_change_points_reproduce_a_step_series(y: np.ndarray) -> None:
    idx = change_indices(y)
    assert len(idx) <= len(y)
    rebuilt = _forward_fill(len(y), idx, y[idx])
    assert all(_same(a, b) for a, b in zip(rebuilt, y.tolist(), strict=True))


@budget(200)
@given(labels=st.lists(st.sampled_from(["OFF", "ON", "STANDBY", None]), max_size=300))
def test_change_points_of_labels(labels: list[str | None]) -> None:
    arr = np.empty(len(labels), dtype=object)
    arr[:] = labels
    idx = change_indices(arr)
    assert _forward_fill(len(labels), idx, arr[idx]) == labels


def test_step_indices_fall_back_when_a_flag_flickers() -> None:
    y = (np.arange(100_000) % 2).astype(float)
    idx = step_indices(y, 1000)
    assert len(idx) <= 1000 and set(np.unique(y[idx])) == {0.0, 1.0}


@budget(200)
@given(on=st.lists(st.booleans(), min_size=1, max_size=200))
def test_spans_cover_exactly_the_held_time(on: list[bool]) -> None:
    """The shaded spans of a flag (a trip, a conducting diode) cover its time, in order."""
    x = np.cumsum(np.r_[0.0, np.full(len(on) - 1, 0.5)])
    flags = np.array(on)
    runs = spans(x, flags, min_frac=0.0)
    held = sum(0.5 for i, f in enumerate(on) if f and i < len(on) - 1)  # last sample: no width
    assert math.isclose(sum(b - a for a, b in runs), held, abs_tol=1e-9)
    assert all(a <= b for a, b in runs)
    assert all(b1 < a2 for (_, b1), (a2, _) in itertools.pairwise(runs))


def test_spans_widen_slivers_and_merge_a_flicker() -> None:
    x = np.arange(100_000, dtype=float)
    assert len(spans(x, np.arange(100_000) % 3 == 0)) <= 2000
    (a, b), *_ = spans(x[:10], np.array([False] * 4 + [True] + [False] * 5), min_frac=1 / 3)
    assert a == 4.0 and b == 7.0
