"""Fused multiply-add with the same bits compiled and interpreted.

The cell model's kernels used to let LLVM contract ``a * b + c`` into one FMA instruction
(``fastmath={"contract"}``): faster and more accurate, but *where* LLVM contracted was its own
choice, invisible in the source, so the same source run as plain Python
(``NUMBA_DISABLE_JIT=1``) rounded twice where the compiled code rounded once, and every
example's golden hashes differed interpreted (issue #25: the interpreted run must be
bit-identical, so that a first run can start interpreted while the kernels compile).

The kernels now write each of those fused operations as ``fma(a, b, c)`` (exactly the ones
LLVM contracted: the golden hashes did not move) and are compiled without ``contract``:

* compiled, :func:`fma` is LLVM's ``llvm.fma.f64`` intrinsic: the ``vfmadd`` instruction the
  contraction emitted (and a correctly rounded libm call on a CPU without FMA, so the results
  no longer depend on the CPU either);
* interpreted, it is the C library's ``fma`` (correctly rounded by C99 / IEEE 754), called
  through :mod:`ctypes` (~1 µs); where no C library offers it, an exact rational computation.

Both round ``a * b + c`` once, so they agree to the bit.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import math
from collections.abc import Callable
from fractions import Fraction
from typing import Any

from llvmlite import ir  # type: ignore[import-untyped]
from numba.core import types
from numba.extending import intrinsic, overload


def _exact_fma(a: float, b: float, c: float) -> float:
    """``a * b + c`` rounded once, by exact rational arithmetic (slow; the fallback)."""
    a, b, c = float(a), float(b), float(c)
    if not (math.isfinite(a) and math.isfinite(b)):
        return a * b + c  # the product is inf or NaN exactly: IEEE's fma does the same
    if not math.isfinite(c):
        return c  # a finite product (never overflowing: it is exact) plus inf or NaN
    r = Fraction(a) * Fraction(b) + Fraction(c)
    if r == 0:
        return a * b + c  # exact zero: a*b == -c exactly, so this has IEEE's sign of zero
    try:
        return float(r)  # int / int true division: correctly rounded (subnormals too)
    except OverflowError:
        return math.inf if r > 0 else -math.inf


def _libm_fma() -> Callable[[float, float, float], float] | None:
    """The C library's ``fma`` when it is there and rounds once (checked on a case where
    rounding twice gives another answer)."""
    name = ctypes.util.find_library("m") or ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        fn = ctypes.CDLL(name).fma
    except (OSError, AttributeError):
        return None
    fn.restype = ctypes.c_double
    fn.argtypes = (ctypes.c_double, ctypes.c_double, ctypes.c_double)
    a = 1.0 + 2.0**-27
    b = 1.0 - 2.0**-27  # a * b = 1 - 2**-54 exactly; rounded, it is 1.0
    if fn(a, b, -1.0) != -(2.0**-54):
        return None
    return fn


_impl: Callable[[float, float, float], float] = _libm_fma() or _exact_fma


def fma(a: float, b: float, c: float) -> float:
    """``a * b + c`` with a single rounding (the compiled kernels use one FMA instruction)."""
    return _impl(a, b, c)


@intrinsic
def _llvm_fma(typingctx: Any, a: Any, b: Any, c: Any) -> Any:
    sig = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, signature: Any, args: Any) -> Any:
        d = ir.DoubleType()
        fnty = ir.FunctionType(d, [d, d, d])
        fn = builder.module.declare_intrinsic("llvm.fma", [d], fnty)
        return builder.call(fn, list(args))

    return sig, codegen


@overload(fma, inline="always")
def _fma_compiled(a: Any, b: Any, c: Any) -> Any:
    def impl(a: Any, b: Any, c: Any) -> Any:  # pragma: no cover - compiled
        return _llvm_fma(a, b, c)  # type: ignore[call-arg]

    return impl


__all__ = ["fma"]
