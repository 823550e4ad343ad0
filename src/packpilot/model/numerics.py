"""Sums in NumPy's order, compiled: what ``ndarray.sum`` and ``np.add.reduceat`` return, bit
for bit, so compiled sensors and metrics read the same numbers as the NumPy reference.

NumPy sums a contiguous run pairwise: below 8 values one after the other (from 0.0), up to
128 in eight interleaved accumulators, above that by halves (rounded to multiples of 8). The
halving is written here as a loop over an explicit stack rather than recursion: a cached
recursive kernel, once linked into a new caller, crashed the process (numba 0.68).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from packpilot.jit import kernel, kernel_inline


@kernel_inline
def _block(x: Any, lo: int, n: int) -> float:
    """NumPy's pairwise sum of ``x[lo:lo+n]`` for ``n <= 128``."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += x[lo + i]
        return res
    r0, r1, r2, r3 = x[lo], x[lo + 1], x[lo + 2], x[lo + 3]
    r4, r5, r6, r7 = x[lo + 4], x[lo + 5], x[lo + 6], x[lo + 7]
    i = 8
    m = n - n % 8
    while i < m:
        k = lo + i
        r0 += x[k]
        r1 += x[k + 1]
        r2 += x[k + 2]
        r3 += x[k + 3]
        r4 += x[k + 4]
        r5 += x[k + 5]
        r6 += x[k + 6]
        r7 += x[k + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += x[lo + i]
        i += 1
    return float(res)


@kernel
def pairwise_sum(x: Any, lo: int, n: int) -> float:
    """Sum of ``x[lo:lo+n]`` in NumPy's pairwise order (what ``ndarray.sum`` returns)."""
    if n <= 128:
        return _block(x, lo, n)
    # NumPy's halving tree, walked with explicit frames. A frame's phase says which child it
    # launched last: 1 = its left half, 2 = its right half.
    f_lo = np.empty(64, np.int64)
    f_n = np.empty(64, np.int64)
    f_phase = np.zeros(64, np.int64)
    f_left = np.zeros(64)
    d = 0
    f_lo[0], f_n[0] = lo, n
    while True:
        a, m = f_lo[d], f_n[d]
        half = m // 2 - (m // 2) % 8
        if f_phase[d] == 0:
            f_phase[d] = 1
            c_lo, c_n = a, half
        else:
            f_phase[d] = 2
            c_lo, c_n = a + half, m - half
        if c_n > 128:
            d += 1
            f_lo[d], f_n[d], f_phase[d] = c_lo, c_n, 0
            continue
        val = _block(x, c_lo, c_n)
        while True:  # hand the finished subtree to its frame, upwards while frames complete
            if f_phase[d] == 1:
                f_left[d] = val
                break
            val = f_left[d] + val
            d -= 1
            if d < 0:
                return float(val)


@kernel_inline
def short_sum(x: Any, lo: int, n: int) -> float:
    """:func:`pairwise_sum`, inlined into its caller for a short run: the same additions in
    the same order, without a call that passes (and reference-counts) an array view per sum
    (14 sums per uav_mission pack cost ~0.5 us that way)."""
    return _block(x, lo, n) if n <= 128 else pairwise_sum(x, lo, n)


@kernel_inline
def segment_sum(x: Any, starts: Any, k: int) -> float:
    """``np.add.reduceat(x, starts)[k]`` for increasing ``starts``: first item + pairwise rest."""
    lo = starts[k]
    hi = starts[k + 1] if k + 1 < starts.size else x.size
    return float(x[lo] + short_sum(x, lo + 1, hi - lo - 1))


__all__ = ["pairwise_sum", "segment_sum", "short_sum"]
