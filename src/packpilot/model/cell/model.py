"""The cell model's array API: the state of n cells and the functions that read and advance it.

Every function takes a parameter set and per-cell arrays (scalars broadcast), checks shapes and
calls one kernel of :mod:`packpilot.model.cell.kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from packpilot.model.cell.kernels import (
    _advance_kernel,
    _ocv_kernel,
    _simulate_kernel,
    _step_kernel,
    _tables,
    _thermal_coeffs,
    _thevenin_kernel,
)
from packpilot.model.cell.params import F64, CellParams

# --------------------------------------------------------------------------------------------
# State
# --------------------------------------------------------------------------------------------


@dataclass
class CellState:
    """State of n cells: SoC (fraction), RC drops ``eta_v`` (n, n_rc), cell and jig temps."""

    soc: F64
    eta_v: F64
    temp_c: F64
    jig_temp_c: F64

    def copy(self) -> CellState:
        return CellState(
            self.soc.copy(), self.eta_v.copy(), self.temp_c.copy(), self.jig_temp_c.copy()
        )


@dataclass(frozen=True)
class CellTrace:
    """A single-cell simulation sampled at the step boundaries ``t_s = k dt`` (len n+1).

    Sample 0 is taken with the first step's current; sample k >= 1 at the end of step k-1 with
    that step's current still flowing (the left limit before the current changes), so
    ``current_a[k]`` is the current that produced ``voltage_v[k]``.
    """

    t_s: F64
    current_a: F64
    voltage_v: F64
    soc: F64
    temp_c: F64
    jig_temp_c: F64


def _cells(x: ArrayLike, n: int) -> F64:
    """x as a C-contiguous float64 array of shape (n,) (scalars broadcast; no copy if fine)."""
    if isinstance(x, float | int):
        return np.full(n, float(x))
    a = np.asarray(x, dtype=np.float64)
    if a.shape == (n,):
        return a if a.flags.c_contiguous else np.ascontiguousarray(a)
    if a.ndim == 0:
        return np.full(n, float(a))
    return np.ascontiguousarray(np.broadcast_to(a, (n,)))


def _state_arrays(params: CellParams, state: CellState) -> tuple[int, F64, F64, F64, F64]:
    """State arrays as the kernels need them (C-contiguous float64, no copy when they already
    are); shapes checked, since the kernels do no bounds checking."""
    f64 = np.float64
    soc = np.ascontiguousarray(state.soc, dtype=f64)
    eta = np.ascontiguousarray(state.eta_v, dtype=f64)
    tc = np.ascontiguousarray(state.temp_c, dtype=f64)
    tj = np.ascontiguousarray(state.jig_temp_c, dtype=f64)
    n = soc.shape[0]
    if eta.shape != (n, params.n_rc) or tc.shape != (n,) or tj.shape != (n,) or soc.ndim != 1:
        raise ValueError(
            f"inconsistent CellState shapes: soc {soc.shape}, eta_v {eta.shape} (n_rc = "
            f"{params.n_rc}), temp_c {tc.shape}, jig_temp_c {tj.shape}"
        )
    return n, soc, eta, tc, tj


def initial_state(params: CellParams, n: int, soc0: ArrayLike, ambient_c: ArrayLike) -> CellState:
    """n cells at rest: RC branches relaxed, cell and jig at ambient."""
    amb = _cells(ambient_c, n).copy()
    return CellState(
        soc=_cells(soc0, n).copy(),
        eta_v=np.zeros((n, params.n_rc)),
        temp_c=amb,
        jig_temp_c=amb.copy(),
    )


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def ocv_v(params: CellParams, soc: ArrayLike, temp_c: ArrayLike) -> F64:
    """Open-circuit voltage at (SoC, cell temperature), including the entropic term if enabled.

    Broadcasts ``soc`` against ``temp_c``; the result has their broadcast shape.
    """
    s, t = np.broadcast_arrays(np.asarray(soc, np.float64), np.asarray(temp_c, np.float64))
    out = np.empty(s.shape)
    k = params._packed
    _ocv_kernel(
        np.ascontiguousarray(s).ravel(), np.ascontiguousarray(t).ravel(),
        k.ocv_x, k.ocv_y, k.du_x, k.du_t, k.du_y, k.fmeta, k.imeta, out.reshape(-1),
    )  # fmt: skip
    return out


def thevenin(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, F64]:
    """Per cell (e_v, r0_ohm) so that the terminal voltage is ``e_v - r0_ohm * I``.

    ``e_v = OCV(soc, T) - sum(eta)``; R0 is read at ``current_a`` and scaled by ``r_scale``.
    ``capacity_ah`` does not enter (the source has no capacity term); it is accepted so that
    :func:`thevenin` and :func:`advance` take the same per-cell arguments.
    """
    n, soc, eta, tc, _ = _state_arrays(params, state)
    e = np.empty(n)
    r = np.empty(n)
    _thevenin_kernel(
        soc, eta, tc, _cells(current_a, n), _cells(r_scale, n),
        *_tables(params), e, r,
    )  # fmt: skip
    return e, r


def advance(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[CellState, F64]:
    """Advance n cells over ``dt_s`` at constant current; returns (new state, mean heat W).

    ``r_scale`` multiplies every resistance and divides every capacitance (time constants
    unchanged); ``capacity_ah`` is the per-cell capacity used for coulomb counting. Thermal
    masses and conductances are the parameter set's for every cell.
    """
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    n, soc, eta, tc, tj = _state_arrays(params, state)
    th = _thermal_coeffs(params, h)
    new = CellState(np.empty(n), np.empty((n, params.n_rc)), np.empty(n), np.empty(n))
    heat = np.empty(n)
    _advance_kernel(
        soc, eta, tc, tj,
        _cells(current_a, n), _cells(ambient_c, n), _cells(capacity_ah, n), _cells(r_scale, n),
        h, th, *_tables(params), new.soc, new.eta_v, new.temp_c, new.jig_temp_c, heat,
    )  # fmt: skip
    return new, heat


def step(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, CellState, F64]:
    """One closed-loop step of n cells: (terminal voltage V, new state, mean heat W).

    The voltage is ``e_v - r0_ohm * I`` of :func:`thevenin` at the *start* state; the new state
    and heat are those of :func:`advance`. Same arguments as :func:`advance`; one fused kernel
    (one pass over the cells, shared axis lookups), so it is faster than the two calls.
    """
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    n, soc, eta, tc, tj = _state_arrays(params, state)
    th = _thermal_coeffs(params, h)
    new = CellState(np.empty(n), np.empty((n, params.n_rc)), np.empty(n), np.empty(n))
    v = np.empty(n)
    heat = np.empty(n)
    _step_kernel(
        soc, eta, tc, tj,
        _cells(current_a, n), _cells(ambient_c, n), _cells(capacity_ah, n), _cells(r_scale, n),
        h, th, *_tables(params), v, new.soc, new.eta_v, new.temp_c, new.jig_temp_c, heat,
    )  # fmt: skip
    return v, new, heat


def simulate_current(
    params: CellParams,
    current_a: ArrayLike,
    dt_s: float,
    soc0: float,
    ambient_c: ArrayLike,
    *,
    capacity_ah: float | None = None,
    r_scale: float = 1.0,
) -> CellTrace:
    """Simulate one cell from rest at ambient under a piecewise-constant current.

    ``current_a[k]`` (+ = discharge) flows over ``[k dt, (k+1) dt)``; ``ambient_c`` is a scalar
    or one value per step. Samples follow the :class:`CellTrace` convention (len n+1).
    """
    cur = np.ascontiguousarray(np.asarray(current_a, dtype=np.float64).ravel())
    n = cur.size
    if n == 0:
        raise ValueError("current_a must have at least one step")
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    amb = _cells(ambient_c, n)
    cap = params.capacity_ah if capacity_ah is None else float(capacity_ah)
    th = _thermal_coeffs(params, h)
    v, soc, tc, tj = (np.empty(n + 1) for _ in range(4))
    _simulate_kernel(
        cur, amb, h, float(soc0), cap, float(r_scale), th, *_tables(params), v, soc, tc, tj
    )
    return CellTrace(
        t_s=np.arange(n + 1, dtype=np.float64) * h,
        current_a=np.concatenate([cur[:1], cur]),
        voltage_v=v,
        soc=soc,
        temp_c=tc,
        jig_temp_c=tj,
    )
