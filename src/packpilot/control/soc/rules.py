"""SOC estimation rules, compiled: coulomb counting, corrected from the OCV after a rest.

Coulomb counting is exact for the charge that flowed but drifts with current-sensor offset and
starts from whatever the initial SOC was; the open-circuit voltage tells the SOC directly, but
only once the cell has rested (the RC overpotentials have decayed). So: integrate the measured
current every tick; when a battery's current has stayed below ``rest_current_a`` for
``rest_time_s``, read the SOC off the OCV table at the cell voltage and move the estimate there
(fully, or by ``blend``), then again after every further ``rest_time_s`` of the same rest.

Timing: a measurement at ``t`` carries the current that flowed during ``[t - dt, t]`` (the
simulator's and a sampling BMS's convention), so that current times ``dt_s`` is exactly the
charge moved since the previous tick.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import emit, fmax, fmin
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

EPS = 1e-9

# Reason codes (rows of the reason table in controller.py).
SOC_CORRECTED = 0

# Status channels, in order.
ST_SOC = 0
ST_REST = 1


class SocParams(NamedTuple):
    rest_current_a: float
    rest_time_s: float
    blend: float
    use_min_cell: bool
    """Read the OCV table at the min cell voltage (else battery voltage / series cells)."""
    ocv_v: F64
    """Strictly increasing cell OCV (V) ..."""
    ocv_soc: F64
    """... and the SOC at each point."""
    series_cells: I64
    """(B,)."""


class SocState(NamedTuple):
    soc: F64
    """(P, B) estimate; NaN until initialised from the OCV."""
    rest_s: F64
    next_fix_s: F64
    corrections: I64


@kernel_inline
def soc_from_ocv(prm: SocParams, cell_v: float) -> float:
    """Inverse of the OCV table, clamped to its ends and to 0..1 (NaN for a NaN input)."""
    if not math.isfinite(cell_v):
        return math.nan
    xs, ys = prm.ocv_v, prm.ocv_soc
    n = xs.shape[0]
    if cell_v <= xs[0]:
        s = ys[0]
    elif cell_v >= xs[n - 1]:
        s = ys[n - 1]
    else:
        k = 1
        while xs[k] <= cell_v:  # bisect_right: first point above the voltage
            k += 1
        x0, x1, y0, y1 = xs[k - 1], xs[k], ys[k - 1], ys[k]
        s = y0 + (y1 - y0) * (cell_v - x0) / (x1 - x0)
    return fmin(1.0, fmax(0.0, s))


@kernel_inline
def _cell_v(prm: SocParams, m: MeasArrays, p: int, i: int) -> float:
    if prm.use_min_cell:
        return float(m.bat.min_cell_v[p, i])
    return float(m.bat.voltage_v[p, i] / prm.series_cells[i])


@kernel_inline
def _battery(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, i: int, dt: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    if not (m.bat.reported[p, i] and m.bat.present[p, i]):
        st.rest_s[p, i] = 0.0
        st.next_fix_s[p, i] = 0.0
        return
    if not math.isfinite(st.soc[p, i]):
        st.soc[p, i] = soc_from_ocv(prm, _cell_v(prm, m, p, i))
        return  # initialised from this sample; its current belongs to the past
    cur = m.bat.current_a[p, i]
    if not math.isfinite(cur):
        st.rest_s[p, i] = 0.0  # unknown current: hold, and no rest
        st.next_fix_s[p, i] = 0.0
        return
    st.soc[p, i] = fmin(1.0, fmax(0.0, st.soc[p, i] - cur * dt / (3600.0 * tp.capacity_ah[p, i])))
    if abs(cur) >= prm.rest_current_a:
        st.rest_s[p, i] = 0.0
        st.next_fix_s[p, i] = 0.0
        return
    st.rest_s[p, i] += dt
    if st.next_fix_s[p, i] == 0.0:
        st.next_fix_s[p, i] = prm.rest_time_s
    if st.rest_s[p, i] < st.next_fix_s[p, i] - EPS:
        return
    v = _cell_v(prm, m, p, i)
    ocv_soc = soc_from_ocv(prm, v)
    if not math.isfinite(ocv_soc):
        return  # retry on the next tick of this rest
    before = st.soc[p, i]
    st.soc[p, i] = (1.0 - prm.blend) * before + prm.blend * ocv_soc
    st.next_fix_s[p, i] += prm.rest_time_s
    st.corrections[p, i] += 1
    k = emit(ev, p, src, SOC_CORRECTED, i, m.t_s[p])
    ev.val[k, 0] = before
    ev.val[k, 1] = st.soc[p, i]
    ev.val[k, 2] = ocv_soc
    ev.val[k, 3] = v


@kernel_inline
def step_pack(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One tick of pack ``p``: no commands; the estimate and the rest time as status."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    for i in range(st.soc.shape[1]):
        _battery(prm, st, tp, m, p, i, dt, ev, src)
        status[p, i, s0 + ST_SOC] = st.soc[p, i]
        status[p, i, s0 + ST_REST] = st.rest_s[p, i]


@kernel
def step_packs(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
