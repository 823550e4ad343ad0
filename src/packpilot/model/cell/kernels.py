"""Numba kernels of the cell model, and the arrays a parameter set hands them.

The scalar helpers (table lookups, the exact RC step, one cell over one step) are inlined into
the loops over cells: :func:`_advance_kernel`, :func:`_thevenin_kernel`, the fused
:func:`_step_kernel`, :func:`_ocv_kernel` and the single-cell :func:`_simulate_kernel`.
:func:`_tables` and :func:`_thermal_coeffs` give a parameter set's packed tables and exact
thermal step coefficients in the order the kernels take them. Discretization: see
:mod:`packpilot.model.cell` and docs/cell_model.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any, TypeVar, cast

import numba
import numpy as np
from numpy.typing import NDArray

from packpilot.model.cell.params import F64, CellParams
from packpilot.model.fma import fma
from packpilot.model.thermal import step_coefficients

_F = TypeVar("_F", bound=Callable[..., Any])


# error_model="numpy": no zero-division checks; _nrt=False: kernels never allocate, so no
# reference counting of the array arguments (which otherwise costs ~10x in the inlined helpers).
# No fastmath: each fused multiply-add is written ``fma(a, b, c)`` (packpilot.model.fma), the
# ones LLVM's ``contract`` flag used to fuse, so the same source interpreted gives the same bits.
_NUMBA_OPTIONS: dict[str, Any] = {
    "cache": True,
    "nogil": True,
    "error_model": "numpy",
    "_nrt": False,
}


def _jit(fn: _F) -> _F:
    """``numba.njit`` with the options above, keeping the Python signature visible to mypy."""
    return cast(_F, numba.njit(**_NUMBA_OPTIONS)(fn))


def _jit_inline(fn: _F) -> _F:
    """A kernel helper inlined into its callers at numba-IR level (no call, hoistable loads)."""
    return cast(_F, numba.njit(inline="always", **_NUMBA_OPTIONS)(fn))


# --------------------------------------------------------------------------------------------
# Kernels (numba). The scalar helpers are inlined into the fleet and single-cell loops.
# --------------------------------------------------------------------------------------------


@_jit_inline
def _frac(x: float, ax: F64, inv: float) -> tuple[int, float]:
    """Bracket i (0..n-2) of x on ax and the unclamped fraction of x within it.

    Uniform axes (``inv`` = 1/spacing > 0) take O(1) and no division; others a binary search.
    At a node, rounding may pick either neighbouring bracket: the interpolated value is the
    same to rounding. NaN gives bracket 0 (never an out-of-range index) and a NaN fraction.
    """
    n = ax.shape[0]
    if inv > 0.0:
        f = (x - ax[0]) * inv
        g = f
        if not g > 0.0:
            g = 0.0
        i = int(g) if g < n - 2 else n - 2
        return i, f - i
    lo, hi = 0, n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if x >= ax[mid]:
            lo = mid
        else:
            hi = mid
    return lo, (x - ax[lo]) / (ax[lo + 1] - ax[lo])


@_jit_inline
def _lim(t: float, clamp: bool) -> float:
    """Fraction used for interpolation: held in [0, 1] (clamp) or not (linear extrapolation)."""
    if clamp:
        if t < 0.0:
            return 0.0
        if t > 1.0:
            return 1.0
    return t


@_jit_inline
def _interp1(x: float, ax: F64, inv: float, y: F64, clamp: bool) -> float:
    i, t = _frac(x, ax, inv)
    t = _lim(t, clamp)
    return float(fma(t, y[i + 1] - y[i], y[i]))


@_jit_inline
def _col2(y: F64, i: int, t: float, j: int) -> tuple[float, float]:
    """Bilinear table: values at z nodes j and j+1, interpolated along x (bracket i, fraction t)."""
    a0, a1 = y[i, j], y[i, j + 1]
    return fma(t, y[i + 1, j] - a0, a0), fma(t, y[i + 1, j + 1] - a1, a1)


@_jit_inline
def _planes3(
    flat: F64, m: int, base: int, di: int, dj: int, dk: int, u: float, v: float
) -> tuple[float, float]:  # fmt: skip
    """Table m at (I, SoC) on the two temperature nodes bracketing T.

    The flat layout [T][I][SoC][table] puts all tables of one corner side by side.
    """
    b = base + m
    c00 = fma(v, flat[b + dk] - flat[b], flat[b])
    c01 = fma(v, flat[b + dj + dk] - flat[b + dj], flat[b + dj])
    c10 = fma(v, flat[b + di + dk] - flat[b + di], flat[b + di])
    c11 = fma(v, flat[b + di + dj + dk] - flat[b + di + dj], flat[b + di + dj])
    return fma(u, c01 - c00, c00), fma(u, c11 - c10, c10)


@_jit_inline
def _ocv_at(
    soc: float, temp: float, jd: int, w: float, ocv_x: F64, ocv_y: F64, du_x: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> float:  # fmt: skip
    """OCV including the entropic term, given the bracket (jd, unclamped w) of ``temp`` on the
    dU/dT temperature axis, so that a caller that already has it does not look it up again."""
    clamp = imeta[2] == 1
    u_ref = _interp1(soc, ocv_x, fmeta[3], ocv_y, clamp)
    t_ref = fmeta[6]
    if math.isnan(t_ref):
        return u_ref
    x = u_ref if imeta[1] == 1 else soc
    i, t = _frac(x, du_x, fmeta[4])
    c0, c1 = _col2(du_y, i, _lim(t, clamp), jd)
    return float(fma(temp - t_ref, fma(_lim(w, clamp), c1 - c0, c0), u_ref))


@_jit_inline
def _ocv_scalar(
    soc: float, temp: float, ocv_x: F64, ocv_y: F64, du_x: F64, du_t: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> float:  # fmt: skip
    """OCV including the entropic term (none when the reference temperature is NaN)."""
    jd, w = _frac(temp, du_t, fmeta[5])
    return _ocv_at(soc, temp, jd, w, ocv_x, ocv_y, du_x, du_y, fmeta, imeta)


@_jit_inline
def _terminal_at(
    soc: float, eta_sum: float, temp: float, r_scale: float, i: int, t: float, j: int, u: float,
    jd: int, w: float, flat: F64, ax_s: F64, ocv_x: F64, ocv_y: F64, du_x: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> tuple[float, float]:  # fmt: skip
    """(OCV - sum eta, R0 r_scale) given the brackets of ``temp`` (i, t on the RC axis; jd, w
    on the dU/dT axis) and of the current (j, u); fractions may be unclamped. A step shares
    these with its own lookups (:func:`_step_scalar`)."""
    clamp = imeta[2] == 1
    dk = imeta[6]
    dj = imeta[5] * dk
    di = imeta[4] * dj
    k, v = _frac(soc, ax_s, fmeta[2])
    base = i * di + j * dj + k * dk
    p0, p1 = _planes3(flat, 0, base, di, dj, dk, _lim(u, clamp), _lim(v, clamp))
    r0 = fma(_lim(t, clamp), p1 - p0, p0)
    ocv = _ocv_at(soc, temp, jd, w, ocv_x, ocv_y, du_x, du_y, fmeta, imeta)
    return ocv - eta_sum, r0 * r_scale


@_jit_inline
def _terminal_scalar(
    soc: float, eta_sum: float, temp: float, cur: float, r_scale: float,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
) -> tuple[float, float]:  # fmt: skip
    """(source voltage OCV - sum eta, series resistance R0 at this current)."""
    i, t = _frac(temp, ax_t, fmeta[0])
    j, u = _frac(cur, ax_i, fmeta[1])
    jd, w = _frac(temp, du_t, fmeta[5])
    return _terminal_at(
        soc, eta_sum, temp, r_scale, i, t, j, u, jd, w,
        flat, ax_s, ocv_x, ocv_y, du_x, du_y, fmeta, imeta,
    )  # fmt: skip


@_jit_inline
def _one_minus_exp_neg(x: float) -> float:
    """1 - exp(-x), inline for |x| < 0.25 (RC steps shorter than tau/4: the usual case).

    A libm call inside the cell loop makes the compiler spill every live register around it;
    the nested Taylor form x(1 - x/2(1 - x/3(... (1 - x/13)))) has a relative error < 1e-17.
    """
    if abs(x) < 0.25:
        p = fma(-x, 1.0 / 13.0, 1.0)
        p = fma(-(x * (1.0 / 12.0)), p, 1.0)
        p = fma(-(x * (1.0 / 11.0)), p, 1.0)
        p = fma(-(x * (1.0 / 10.0)), p, 1.0)
        p = fma(-(x * (1.0 / 9.0)), p, 1.0)
        p = fma(-(x * (1.0 / 8.0)), p, 1.0)
        p = fma(-(x * (1.0 / 7.0)), p, 1.0)
        p = fma(-(x * (1.0 / 6.0)), p, 1.0)
        p = fma(-(x * (1.0 / 5.0)), p, 1.0)
        p = fma(-(x * (1.0 / 4.0)), p, 1.0)
        p = fma(-(x * (1.0 / 3.0)), p, 1.0)
        p = fma(-(x * 0.5), p, 1.0)
        return x * p
    return -math.expm1(-x)


@_jit_inline
def _rc_branch(
    eta: float, cur: float, r: float, c: float, r_scale: float, h: float, inv_h: float
) -> tuple[float, float]:
    """Exact RC step: (drop at step end, drop averaged over the step); tau = R C."""
    tau = r * c
    target = cur * r * r_scale
    frac = _one_minus_exp_neg(h / tau)
    d = eta - target
    return fma(d, 1.0 - frac, target), fma(d * frac * tau, inv_h, target)


@_jit_inline
def _step_scalar(
    soc: float, eta1: float, eta2: float, tc: float, tj: float,
    cur: float, h: float, ta: float, cap_ah: float, r_scale: float, th: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64], with_v: bool,
) -> tuple[float, float, float, float, float, float, float, float]:  # fmt: skip
    """One cell over one step of constant current:
    (soc, eta1, eta2, T_cell, T_jig, heat_w, e_v, r0_ohm).

    Tables are read at mid-step: SoC exactly (it is linear in time), the cell temperature from
    a predictor (exact half-step of the thermal network under the heat at step start).
    ``with_v`` (a constant at each call site, so the other branch compiles away) also returns
    :func:`_terminal_scalar` at the step-start state, reusing the temperature and current
    brackets of the predictor; otherwise e_v = r0_ohm = 0.
    """
    clamp = imeta[2] == 1
    nt = imeta[6]
    dk = nt
    dj = imeta[5] * dk
    di = imeta[4] * dj
    soc1 = soc - cur * h / (3600.0 * cap_ah)
    sm = 0.5 * (soc + soc1)
    inv_h = 1.0 / h
    i, tu = _frac(tc, ax_t, fmeta[0])
    j, u = _frac(cur, ax_i, fmeta[1])
    k, v = _frac(sm, ax_s, fmeta[2])
    u = _lim(u, clamp)
    v = _lim(v, clamp)
    t = _lim(tu, clamp)
    base = i * di + j * dj + k * dk
    u_ref = _interp1(sm, ocv_x, fmeta[3], ocv_y, clamp)
    xd = u_ref if imeta[1] == 1 else sm
    # predictor: heat at step start -> cell temperature at mid-step
    p0, p1 = _planes3(flat, 0, base, di, dj, dk, u, v)
    xi, xt = _frac(xd, du_x, fmeta[4])
    xt = _lim(xt, clamp)
    jd, w = _frac(tc, du_t, fmeta[5])
    d0, d1 = _col2(du_y, xi, xt, jd)
    r0 = fma(t, p1 - p0, p0) * r_scale
    ev, r0v = 0.0, 0.0
    if with_v:
        ev, r0v = _terminal_at(
            soc, eta1 + eta2, tc, r_scale, i, tu, j, u, jd, w,
            flat, ax_s, ocv_x, ocv_y, du_x, du_y, fmeta, imeta,
        )  # fmt: skip
    q0 = cur * fma(-(tc + 273.15), fma(_lim(w, clamp), d1 - d0, d0), fma(cur, r0, eta1) + eta2)
    yc = tc - ta
    yj = tj - ta
    tmid = fma(th[10], q0, fma(th[7], yj, fma(th[6], yc, ta)))
    # corrector: every table at (T_mid, I, SoC_mid); the brackets rarely change
    im, tm = _frac(tmid, ax_t, fmeta[0])
    tm = _lim(tm, clamp)
    if im != i:
        base += (im - i) * di
        p0, p1 = _planes3(flat, 0, base, di, dj, dk, u, v)
    heat = cur * cur * fma(tm, p1 - p0, p0) * r_scale
    p0, p1 = _planes3(flat, 1, base, di, dj, dk, u, v)
    r = fma(tm, p1 - p0, p0)
    p0, p1 = _planes3(flat, 2, base, di, dj, dk, u, v)
    eta1_new, mean = _rc_branch(eta1, cur, r, fma(tm, p1 - p0, p0), r_scale, h, inv_h)
    heat = fma(cur, mean, heat)
    eta2_new = 0.0
    if imeta[0] == 2:
        p0, p1 = _planes3(flat, 3, base, di, dj, dk, u, v)
        r = fma(tm, p1 - p0, p0)
        p0, p1 = _planes3(flat, 4, base, di, dj, dk, u, v)
        eta2_new, mean = _rc_branch(eta2, cur, r, fma(tm, p1 - p0, p0), r_scale, h, inv_h)
        heat = fma(cur, mean, heat)
    jm, w = _frac(tmid, du_t, fmeta[5])
    if jm != jd:
        d0, d1 = _col2(du_y, xi, xt, jm)
    heat = fma(-(cur * (tmid + 273.15)), fma(_lim(w, clamp), d1 - d0, d0), heat)
    tc_new = fma(th[4], heat, fma(th[1], yj, fma(th[0], yc, ta)))
    tj_new = fma(th[5], heat, fma(th[3], yj, fma(th[2], yc, ta)))
    return soc1, eta1_new, eta2_new, tc_new, tj_new, heat, ev, r0v


@_jit
def _advance_kernel(
    soc: F64, eta: F64, tc: F64, tj: F64, cur: F64, ta: F64, cap: F64, rs: F64,
    h: float, th: F64, flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    soc_o: F64, eta_o: F64, tc_o: F64, tj_o: F64, heat_o: F64,
) -> None:  # fmt: skip
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        e2 = eta[c, 1] if two else 0.0
        s1, a1, a2, t1, j1, q, _e, _r = _step_scalar(
            soc[c], eta[c, 0], e2, tc[c], tj[c], cur[c], h, ta[c], cap[c], rs[c], th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, False,
        )  # fmt: skip
        soc_o[c] = s1
        eta_o[c, 0] = a1
        if two:
            eta_o[c, 1] = a2
        tc_o[c] = t1
        tj_o[c] = j1
        heat_o[c] = q


@_jit
def _step_kernel(
    soc: F64, eta: F64, tc: F64, tj: F64, cur: F64, ta: F64, cap: F64, rs: F64,
    h: float, th: F64, flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    v_o: F64, soc_o: F64, eta_o: F64, tc_o: F64, tj_o: F64, heat_o: F64,
) -> None:  # fmt: skip
    """``_thevenin_kernel`` then ``_advance_kernel`` in one pass, sharing the axis lookups."""
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        i = cur[c]
        e2 = eta[c, 1] if two else 0.0
        s1, a1, a2, t1, j1, q, e, r0 = _step_scalar(
            soc[c], eta[c, 0], e2, tc[c], tj[c], i, h, ta[c], cap[c], rs[c], th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, True,
        )  # fmt: skip
        v_o[c] = fma(-r0, i, e)
        soc_o[c] = s1
        eta_o[c, 0] = a1
        if two:
            eta_o[c, 1] = a2
        tc_o[c] = t1
        tj_o[c] = j1
        heat_o[c] = q


@_jit
def _ocv_kernel(
    soc: F64, temp: F64, ocv_x: F64, ocv_y: F64, du_x: F64, du_t: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64], out: F64,
) -> None:  # fmt: skip
    for c in range(soc.shape[0]):
        out[c] = _ocv_scalar(soc[c], temp[c], ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta)


@_jit
def _thevenin_kernel(
    soc: F64, eta: F64, tc: F64, cur: F64, rs: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    e_o: F64, r_o: F64,
) -> None:  # fmt: skip
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        s = eta[c, 0] + eta[c, 1] if two else eta[c, 0]
        e, r = _terminal_scalar(
            soc[c], s, tc[c], cur[c], rs[c],
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        )  # fmt: skip
        e_o[c] = e
        r_o[c] = r


@_jit
def _simulate_kernel(
    cur: F64, amb: F64, h: float, soc0: float, cap_ah: float, r_scale: float, th: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    v_o: F64, soc_o: F64, tc_o: F64, tj_o: F64,
) -> None:  # fmt: skip
    n = cur.shape[0]
    soc, e1, e2, tc, tj = soc0, 0.0, 0.0, amb[0], amb[0]
    ev, r0 = _terminal_scalar(
        soc, 0.0, tc, cur[0], r_scale,
        flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
    )  # fmt: skip
    v_o[0] = fma(-r0, cur[0], ev)
    soc_o[0], tc_o[0], tj_o[0] = soc, tc, tj
    for k in range(n):
        soc, e1, e2, tc, tj, _q, _e, _r = _step_scalar(
            soc, e1, e2, tc, tj, cur[k], h, amb[k], cap_ah, r_scale, th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, False,
        )  # fmt: skip
        ev, r0 = _terminal_scalar(
            soc, e1 + e2, tc, cur[k], r_scale,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        )  # fmt: skip
        v_o[k + 1] = fma(-r0, cur[k], ev)
        soc_o[k + 1], tc_o[k + 1], tj_o[k + 1] = soc, tc, tj


def _thermal_coeffs(params: CellParams, h: float) -> F64:
    """Exact thermal step coefficients for dt = h (6) and for the mid-step predictor h/2 (6)."""
    cached = params._thermal_cache.get(h)
    if cached is None:
        th = params.thermal
        cached = np.array(step_coefficients(th, h) + step_coefficients(th, 0.5 * h))
        cached.setflags(write=False)
        if len(params._thermal_cache) < 64:
            params._thermal_cache[h] = cached
    return cached


_Tables = tuple[F64, F64, F64, F64, F64, F64, F64, F64, F64, F64, NDArray[np.int64]]


def _tables(params: CellParams) -> _Tables:
    k = params._packed
    return (k.rc_flat, k.ax_t, k.ax_i, k.ax_s, k.ocv_x, k.ocv_y, k.du_x, k.du_t, k.du_y,
            k.fmeta, k.imeta)  # fmt: skip
