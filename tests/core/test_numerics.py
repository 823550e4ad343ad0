"""Compiled sums in NumPy's order, bit for bit (sensors and metrics depend on it)."""

from __future__ import annotations

import numpy as np
import pytest

from packpilot.model.numerics import pairwise_sum, segment_sum


@pytest.mark.parametrize("n", [*range(0, 140), 255, 256, 257, 1000, 1023, 4097, 20001])
def test_pairwise_sum_is_numpys(n: int) -> None:
    rng = np.random.default_rng(n)
    x = rng.standard_normal(n + 3) * 10 ** rng.uniform(-3, 3, n + 3)
    want = x[2 : 2 + n].sum() if n else 0.0
    assert pairwise_sum(x, 2, n) == want


def test_segment_sum_is_reduceat() -> None:
    rng = np.random.default_rng(0)
    x = rng.standard_normal(1000) * 1e3
    starts = np.array([0, 5, 17, 200, 350, 999], np.int64)
    want = np.add.reduceat(x, starts)
    assert [segment_sum(x, starts, k) for k in range(starts.size)] == list(want)
