"""Thin long series for plotting without hiding what matters in them.

A 10-hour run at 0.1 s has 360,000 samples per series; a figure 1,000 pixels wide cannot show
more than a few thousand. Plain decimation (every k-th sample) would drop a short current spike
or a brief trip, exactly what a BMS report must show. So each bucket keeps its minimum and its
maximum (and its first NaN, so a gap in the data stays a gap), and step-like series (switch
states, controller states) keep every change point, which is exact.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

MAX_POINTS = 5000
"""Default cap of plotted points per series."""


def minmax_indices(y: NDArray[np.float64], max_points: int = MAX_POINTS) -> NDArray[np.intp]:
    """Sorted sample indices, at most ``max_points``, keeping each bucket's min and max.

    The first and last samples are always kept so the plotted span is the run's span. A bucket
    with NaN also keeps its first NaN so the line breaks there as it would at full resolution.
    """
    n = len(y)
    if max_points < 8:
        raise ValueError(f"max_points must be >= 8, got {max_points}")
    if n <= max_points:
        return np.arange(n, dtype=np.intp)
    y = np.asarray(y, dtype=np.float64)
    nan = np.isnan(y)
    per_bucket = 3 if nan.any() else 2
    n_buckets = (max_points - 2) // per_bucket
    size = -(-n // n_buckets)  # ceil
    n_buckets = -(-n // size)
    pad = n_buckets * size - n
    lo = np.concatenate([np.where(nan, np.inf, y), np.full(pad, np.inf)]).reshape(n_buckets, size)
    hi = np.concatenate([np.where(nan, -np.inf, y), np.full(pad, -np.inf)]).reshape(n_buckets, size)
    base = np.arange(n_buckets, dtype=np.intp) * size
    parts = [
        np.array([0, n - 1], dtype=np.intp),
        base + np.argmin(lo, axis=1),
        base + np.argmax(hi, axis=1),
    ]
    if per_bucket == 3:
        nb = np.concatenate([nan, np.zeros(pad, dtype=bool)]).reshape(n_buckets, size)
        has = nb.any(axis=1)
        parts.append((base + np.argmax(nb, axis=1))[has])
    idx = np.unique(np.concatenate(parts))
    return idx[idx < n]


def downsample(
    t: NDArray[np.float64], y: NDArray[np.float64], max_points: int = MAX_POINTS
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(t, y)`` thinned by :func:`minmax_indices` of ``y``."""
    idx = minmax_indices(y, max_points)
    return np.asarray(t)[idx], np.asarray(y)[idx]


def change_indices(values: NDArray[Any]) -> NDArray[np.intp]:
    """Indices where a step series takes a new value, plus the first and last sample.

    Drawn with ``drawstyle="steps-post"`` these points reproduce the series exactly. Works on
    float arrays (NaN to NaN counts as unchanged) and on object arrays (labels, None).
    """
    v = np.asarray(values)
    n = len(v)
    if n == 0:
        return np.zeros(0, dtype=np.intp)
    if v.dtype.kind == "f":
        a, b = v[1:], v[:-1]
        changed = (a != b) & ~(np.isnan(a) & np.isnan(b))
    else:
        changed = np.asarray(v[1:] != v[:-1], dtype=bool)
    idx = np.concatenate([[0], np.flatnonzero(changed) + 1, [n - 1]]).astype(np.intp)
    return np.unique(idx)


def step_indices(values: NDArray[np.float64], max_points: int = MAX_POINTS) -> NDArray[np.intp]:
    """Change points of a numeric step series; min/max buckets if it changes too often."""
    idx = change_indices(values)
    if len(idx) <= max_points:
        return idx
    return minmax_indices(np.asarray(values, dtype=np.float64), max_points)


__all__ = ["MAX_POINTS", "change_indices", "downsample", "minmax_indices", "step_indices"]
