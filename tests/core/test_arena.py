"""Arenas: named tuples moved into flat buffers and rebuilt inside kernels as views."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest
from numpy.typing import NDArray

from packpilot.arena import Arena, unpack
from packpilot.jit import kernel


class Inner(NamedTuple):
    x: NDArray[np.float64]
    n: NDArray[np.int32]


class Outer(NamedTuple):
    a: NDArray[np.float64]
    flags: NDArray[np.bool_]
    inner: Inner
    gain: float
    count: int
    on: bool
    codes: NDArray[np.int8]
    cube: NDArray[np.int64]


def _outer() -> Outer:
    return Outer(
        a=np.arange(6.0).reshape(2, 3),
        flags=np.array([True, False]),
        inner=Inner(np.array([1.5, 2.5]), np.array([7], np.int32)),
        gain=0.25,
        count=3,
        on=True,
        codes=np.array([-1, 1], np.int8),
        cube=np.arange(8, dtype=np.int64).reshape(2, 2, 2),
    )


@kernel
def _touch(f, i, h, c, b, lay, k):  # type: ignore[no-untyped-def]
    o = unpack(Outer, f, i, h, c, b, lay, k)
    o.a[1, 2] += o.gain
    o.inner.x[1] += o.count
    o.inner.n[0] += 1
    o.flags[1] = o.on
    o.codes[0] = 0
    o.cube[1, 1, 1] = -5
    return o.a.sum() + o.inner.x.sum() + o.cube[1, 0, 1]


def test_views_keep_values_and_writes_reach_python() -> None:
    ar = Arena()
    k0 = ar.add(_outer())
    k1 = ar.add(Inner(np.zeros(3), np.zeros(2, np.int32)))
    arenas, (o, inner), (r0, r1) = ar.seal()
    assert (r0, r1) == (0, 1 + 8 + 1) and (k0, k1) == (0, 1)  # Outer: 8 fields + a nested marker
    ref = _outer()
    np.testing.assert_array_equal(o.a, ref.a)
    assert o.gain == 0.25 and o.count == 3 and o.on is True
    got = _touch(*arenas, r0)
    assert got == pytest.approx(15.0 + 0.25 + 4.0 + 3.0 + 5.0)
    assert o.a[1, 2] == 5.25 and o.inner.x[1] == 5.5 and o.inner.n[0] == 8
    assert o.flags[1] and o.codes[0] == 0 and o.cube[1, 1, 1] == -5
    assert inner.x.shape == (3,) and not inner.x.any()  # the other bundle is untouched


def test_python_unpack_matches_the_views() -> None:
    ar = Arena()
    ar.add(_outer())
    arenas, (o,), (r0,) = ar.seal()
    again = unpack(Outer, *arenas, r0)
    o.a[0, 0] = 42.0
    assert again.a[0, 0] == 42.0  # same memory
    assert again.inner.n.dtype == np.int32 and again.codes.dtype == np.int8


def test_an_instance_with_other_field_kinds_is_refused() -> None:
    ar = Arena()
    ar.add(_outer())
    bad = _outer()._replace(count=1.5)
    with pytest.raises(TypeError, match="fields differ"):
        ar.add(bad)
