"""NumPy reference of the cell model, used in tests to check the kernels.

Independent of the kernels: binary search instead of O(1) lookups on uniform axes, vectorized
over cells, the same equations written directly.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from packpilot.model.cell.model import CellState, _cells
from packpilot.model.cell.params import F64, CellParams
from packpilot.model.thermal import KELVIN, step_coefficients


def _np_locate(x: F64, ax: F64) -> tuple[NDArray[np.intp], F64]:
    """Bracket and unclamped fraction, by binary search (the kernels use O(1) on uniform axes)."""
    i = np.clip(np.searchsorted(ax, x, side="right") - 1, 0, ax.size - 2)
    return i, (x - ax[i]) / (ax[i + 1] - ax[i])


def _np_lim(t: F64, clamp: bool) -> F64:
    return np.clip(t, 0.0, 1.0) if clamp else t


def _np_interp2(x: F64, z: F64, ax: F64, az: F64, y: F64, clamp: bool) -> F64:
    """Bilinear y(x, z)."""
    i, t = _np_locate(x, ax)
    j, u = _np_locate(z, az)
    t, u = _np_lim(t, clamp), _np_lim(u, clamp)
    a = y[i, j] * (1 - u) + y[i, j + 1] * u
    b = y[i + 1, j] * (1 - u) + y[i + 1, j + 1] * u
    return a * (1 - t) + b * t


def _np_interp3(params: CellParams, key: str, temp: F64, cur: F64, soc: F64) -> F64:
    """Trilinear table at (temp, cur, soc)."""
    clamp = params.extrapolation == "clamp"
    tab = getattr(params, key)
    i, t = _np_locate(temp, params.rc_temp_c)
    t = _np_lim(t, clamp)
    j, u = _np_locate(cur, params.rc_current_a)
    k, v = _np_locate(soc, params.rc_soc)
    u, v = _np_lim(u, clamp), _np_lim(v, clamp)
    out = np.zeros_like(t)
    for di, wi in ((0, 1 - t), (1, t)):
        for dj, wj in ((0, 1 - u), (1, u)):
            for dk, wk in ((0, 1 - v), (1, v)):
                out += wi * wj * wk * tab[i + di, j + dj, k + dk]
    return out


def _ocv_numpy(params: CellParams, soc: F64, temp: F64) -> tuple[F64, F64]:
    """(OCV at the reference temperature, OCV including the entropic term)."""
    clamp = params.extrapolation == "clamp"
    i, t = _np_locate(soc, params.ocv_soc)
    t = _np_lim(t, clamp)
    y = params.ocv_table_v
    u_ref = y[i] * (1 - t) + y[i + 1] * t
    if params.ocv_ref_temp_c is None:
        return u_ref, u_ref
    x = u_ref if params.dudt_axis == "ocv_v" else soc
    dudt = _np_interp2(x, temp, params.dudt_x, params.dudt_temp_c, params.dudt_v_per_k, clamp)
    return u_ref, u_ref + (temp - params.ocv_ref_temp_c) * dudt


def thevenin_numpy(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, F64]:
    """NumPy reference of :func:`thevenin`."""
    n = state.soc.shape[0]
    cur, rs = _cells(current_a, n), _cells(r_scale, n)
    r0 = _np_interp3(params, "r0_ohm", state.temp_c, cur, state.soc) * rs
    e = _ocv_numpy(params, state.soc, state.temp_c)[1] - state.eta_v.sum(axis=1)
    return e, r0


def advance_numpy(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[CellState, F64]:
    """NumPy reference of :func:`advance` (same equations, written directly)."""
    n = state.soc.shape[0]
    h = float(dt_s)
    cur, ta = _cells(current_a, n), _cells(ambient_c, n)
    cap, rs = _cells(capacity_ah, n), _cells(r_scale, n)
    clamp = params.extrapolation == "clamp"
    soc1 = state.soc - cur * h / (3600.0 * cap)
    sm = 0.5 * (state.soc + soc1)
    tc = state.temp_c
    yc, yj = tc - ta, state.jig_temp_c - ta
    u_ref = _ocv_numpy(params, sm, tc)[0]
    x = u_ref if params.dudt_axis == "ocv_v" else sm
    du_args = (params.dudt_x, params.dudt_temp_c, params.dudt_v_per_k, clamp)
    # predictor: heat at step start held over half a step gives the mid-step cell temperature
    q0 = cur * (
        cur * _np_interp3(params, "r0_ohm", tc, cur, sm) * rs
        + state.eta_v.sum(axis=1)
        - (tc + KELVIN) * _np_interp2(x, tc, *du_args)
    )
    h11, h12, _, _, hkc, _ = step_coefficients(params.thermal, 0.5 * h)
    tm = ta + h11 * yc + h12 * yj + hkc * q0
    # corrector: tables at (T_mid, I, SoC_mid), exact RC and thermal steps
    heat = cur**2 * _np_interp3(params, "r0_ohm", tm, cur, sm) * rs
    eta1 = np.empty_like(state.eta_v)
    for b, (rk, ck) in enumerate((("r1_ohm", "c1_f"), ("r2_ohm", "c2_f"))[: params.n_rc]):
        r = _np_interp3(params, rk, tm, cur, sm) * rs
        c = _np_interp3(params, ck, tm, cur, sm) / rs
        tau = r * c
        decay = np.exp(-h / tau)
        target = cur * r
        eta1[:, b] = target + (state.eta_v[:, b] - target) * decay
        mean = target + (state.eta_v[:, b] - target) * (1 - decay) * tau / h
        heat = heat + cur * mean
    heat = heat - cur * (tm + KELVIN) * _np_interp2(x, tm, *du_args)
    e11, e12, e21, e22, kc, kj = step_coefficients(params.thermal, h)
    new = CellState(
        soc=soc1,
        eta_v=eta1,
        temp_c=ta + e11 * yc + e12 * yj + kc * heat,
        jig_temp_c=ta + e21 * yc + e22 * yj + kj * heat,
    )
    return new, heat
