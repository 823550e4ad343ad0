"""``packpilot.model.fma``: one rounding, the same bits compiled and interpreted."""

from __future__ import annotations

import math
import random
from fractions import Fraction

import numba
import numpy as np

from packpilot.model import fma as F

EDGE = [0.0, -0.0, 1.0, -1.0, 2.0**-1074, -(2.0**-1074), 2.0**-1022, 1e308, -1e308,
        math.inf, -math.inf, math.nan, 1.0 + 2.0**-52, 1.0 - 2.0**-53, 3.0, 0.1]  # fmt: skip


def _cases() -> list[tuple[float, float, float]]:
    rng = random.Random(25)
    out = [(a, b, c) for a in EDGE for b in EDGE for c in EDGE[::3]]
    for _ in range(3000):
        e = rng.randint(-30, 30)
        out.append((rng.uniform(-4, 4) * 2.0**e, rng.uniform(-4, 4), rng.uniform(-4, 4) * 2.0**e))
    a = 1.0 + 2.0**-27
    out.append((a, 1.0 - 2.0**-27, -1.0))  # rounding twice gives 0.0, once -2**-54
    return out


def _same(x: float, y: float) -> bool:
    return (math.isnan(x) and math.isnan(y)) or (
        x == y and math.copysign(1, x) == math.copysign(1, y)
    )


def test_interpreted_fma_rounds_once() -> None:
    for a, b, c in _cases():
        got = F.fma(a, b, c)
        assert _same(got, F._exact_fma(a, b, c)), (a, b, c)
        if all(math.isfinite(v) for v in (a, b, c)):
            exact = Fraction(a) * Fraction(b) + Fraction(c)
            if exact != 0 and abs(exact) < Fraction(1e308):
                assert got == float(exact), (a, b, c)
    a = 1.0 + 2.0**-27
    assert F.fma(a, 1.0 - 2.0**-27, -1.0) == -(2.0**-54) != a * (1.0 - 2.0**-27) - 1.0


def test_compiled_fma_gives_the_interpreted_bits() -> None:
    @numba.njit(cache=False)
    def many(x: np.ndarray, out: np.ndarray) -> None:
        for k in range(x.shape[0]):
            out[k] = F.fma(x[k, 0], x[k, 1], x[k, 2])

    x = np.array(_cases())
    out = np.empty(len(x))
    many(x, out)
    for k, (a, b, c) in enumerate(x):
        assert _same(float(out[k]), F.fma(a, b, c)), (a, b, c)
