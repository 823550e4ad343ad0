"""SOC estimation rules, compiled: the battery observer (an extended Kalman filter,
:mod:`.observer`) as the SOC source, and coulomb counting corrected from the OCV after a rest
as its fallback (and the whole estimator where the pack's cell tables are unknown).

The fallback:

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
from packpilot.control.soc import observer as ob
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

EPS = 1e-9

# Reason codes (rows of the reason table in controller.py).
SOC_CORRECTED = 0
OBS_DIVERGED = 1
OBS_RESUMED = 2

# Status channels, in order.
ST_SOC = 0
ST_REST = 1
ST_FALLBACK = 2
ST_SOC_SIGMA = 3
ST_EMF = 4
ST_R0 = 5
ST_VRC = 6
ST_CAP = 7
ST_OFFSET = 8
ST_NIS = 9
ST_OK = 10
ST_TTG = 11
ST_TTC = 12
ST_TTF = 13
ST_LOAD = 14

N_SCAN = 32
"""Points of the coarse scan for the cut-off crossing (then bisection within the first
bracket that crosses)."""
N_BISECT = 30


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
    observer: bool
    """Run the observer (needs the cell tables below; else the fallback is the estimate)."""
    ax_t: F64
    """Temperature axis of the observer's tables (degC) ..."""
    ax_s: F64
    """... and their SOC axis."""
    r0_tab: F64
    """Cell R0 (ohm) at zero current, T-major (len(ax_t) * len(ax_s))."""
    r1_tab: F64
    """Cell R1 (ohm), same layout."""
    tau_tab: F64
    """Cell R1 * C1 (s), same layout."""
    r_nom: F64
    """(B,) the battery's nominal resistance scale on the tables (its stated resistance)."""
    sig0: F64
    """(5,) prior standard deviations: soc, v1 (V), r_scale and capacity (relative), offset (A)."""
    walk: F64
    """(4,) process noise: current (A), r_scale and capacity (relative, 1/sqrt(s)),
    offset (A/sqrt(s))."""
    var_v: float
    """Variance of the cell-voltage measurement (V^2): sensor noise plus model error."""
    nis_window_s: float
    nis_limit: float
    offset_max_a: float
    load_tau_s: float
    """Time constant of the recent average load the predictions assume (s)."""
    cutoff_cell_v: float
    """The cell voltage whose crossing ``time_to_cutoff_s`` predicts (V)."""
    predict_every_s: float


class SocState(NamedTuple):
    soc: F64
    """(P, B) estimate; NaN until initialised from the OCV."""
    rest_s: F64
    next_fix_s: F64
    corrections: I64
    shown_soc: F64
    """(P, B) THE SOC of the BMS: the observer's while it is healthy, else ``soc`` (the
    coulomb counter with rest corrections, the fallback)."""
    x: F64
    """(P, B, 5) observer state, ``observer.X_*`` order: SOC, cell polarisation V, resistance
    scale, cell capacity Ah, current offset A."""
    cov: F64
    """(P, B, 5, 5) its covariance."""
    fm: F64
    wk: F64
    hv: F64
    kv: F64
    nis_avg: F64
    """(P, B) normalised innovation squared, exponentially averaged over ``nis_window_s``."""
    obs_age_s: F64
    """(P, B) time since the observer (re)started."""
    obs_ok: NDArray[np.bool_]
    """(P, B) the observer is the SOC source (passed its window test)."""
    emf_v: F64
    """(P, B) battery EMF: series cells x OCV(observer SOC) (V)."""
    r0_ohm: F64
    """(P, B) battery ohmic resistance: r_scale x R0(T, SOC) x series cells (ohm)."""
    r0_var_ohm2: F64
    r1_ohm: F64
    """(P, B) battery RC resistance (ohm) ..."""
    tau_s: F64
    """... and its time constant (s)."""
    v_rc_v: F64
    """(P, B) battery polarisation voltage: series cells x v1 (V, positive discharging):
    terminal = emf_v - r0_ohm * current - v_rc_v."""
    v_rc_var_v2: F64
    soc_var: F64
    capacity_ah: F64
    """(P, B) battery capacity: the tracked cell's (Ah; every cell is in series)."""
    capacity_var_ah2: F64
    offset_a: F64
    """(P, B) estimated current-sensor offset (A; measured = true + offset)."""
    offset_var_a2: F64
    load_avg_a: F64
    """(P, B) recent average battery current (exponential, ``load_tau_s``; offset removed)."""
    load_age_s: F64
    """(P, B) time the average has run (it is the plain mean until ``load_tau_s``)."""
    pred_age_s: F64
    """(P, B) time since the predictions were last computed (inf: never)."""
    time_to_go_s: F64
    """(P, B) shown SOC x capacity / recent average load (NaN unless discharging)."""
    time_to_cutoff_s: F64
    """(P, B) when the cell voltage reaches ``cutoff_cell_v`` at the recent average load, the
    polarisation relaxing toward its steady state on the way (NaN: not discharging, or not
    within the OCV table)."""
    time_to_full_s: F64
    """(P, B) (1 - shown SOC) x capacity / recent average charge current (NaN unless
    charging; constant current to full: optimistic where a charger tapers)."""


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
def _outputs(prm: SocParams, st: SocState, tp: PackArrays, p: int, i: int, temp_c: float) -> None:
    """The observer's state in battery units (what state of power and sequencing read)."""
    ns = float(prm.series_cells[i])
    soc = st.x[p, i, ob.X_SOC]
    rs = st.x[p, i, ob.X_RSCALE]
    r0 = ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp_c, soc)
    ocv, _ = ob.ocv_at(prm.ocv_soc, prm.ocv_v, soc)
    st.emf_v[p, i] = ns * ocv
    st.r0_ohm[p, i] = rs * r0 * ns
    st.r0_var_ohm2[p, i] = st.cov[p, i, ob.X_RSCALE, ob.X_RSCALE] * (r0 * ns) ** 2
    st.r1_ohm[p, i] = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp_c, soc) * ns
    st.tau_s[p, i] = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp_c, soc)
    st.v_rc_v[p, i] = ns * st.x[p, i, ob.X_V1]
    st.v_rc_var_v2[p, i] = ns * ns * st.cov[p, i, ob.X_V1, ob.X_V1]
    st.soc_var[p, i] = st.cov[p, i, ob.X_SOC, ob.X_SOC]
    st.capacity_ah[p, i] = st.x[p, i, ob.X_CAP]
    st.capacity_var_ah2[p, i] = st.cov[p, i, ob.X_CAP, ob.X_CAP]
    st.offset_a[p, i] = st.x[p, i, ob.X_OFFSET]
    st.offset_var_a2[p, i] = st.cov[p, i, ob.X_OFFSET, ob.X_OFFSET]


@kernel_inline
def _finite_state(st: SocState, p: int, i: int) -> bool:
    for r in range(ob.N_X):
        if not (math.isfinite(st.x[p, i, r]) and math.isfinite(st.cov[p, i, r, r])):
            return False
    return True


@kernel_inline
def _restart(prm: SocParams, st: SocState, tp: PackArrays, p: int, i: int) -> None:
    """(Re)start the observer at the fallback's SOC with its prior; not the source until it
    has passed a whole window."""
    ob.reset(st.x, st.cov, p, i, st.soc[p, i], tp.capacity_ah[p, i], prm.r_nom[i], prm.sig0)
    st.nis_avg[p, i] = 1.0
    st.obs_age_s[p, i] = 0.0


@kernel_inline
def _observe(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, i: int, dt: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """One tick of battery ``i``'s observer, then its window test (after the fallback ran)."""
    if not (m.bat.reported[p, i] and m.bat.present[p, i]) or not math.isfinite(st.soc[p, i]):
        return
    if not math.isfinite(st.x[p, i, ob.X_SOC]):
        _restart(prm, st, tp, p, i)
        return  # starts from this sample, like the fallback
    cur = m.bat.current_a[p, i]
    if not math.isfinite(cur) or dt <= 0.0:
        return
    temp = m.bat.temp_c[p, i]
    if not math.isfinite(temp):
        temp = 25.0
    soc = st.x[p, i, ob.X_SOC]
    r1 = ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    ob.predict(st.x, st.cov, st.fm, st.wk, p, i, cur, dt, r1, tau, prm.walk)
    r0 = ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, st.x[p, i, ob.X_SOC])
    nis = ob.correct(st.x, st.cov, st.hv, st.kv, st.wk, p, i, _cell_v(prm, m, p, i), cur, r0,
                     prm.ocv_soc, prm.ocv_v, prm.var_v)  # fmt: skip
    ob.bound(st.x, st.cov, p, i, tp.capacity_ah[p, i], prm.r_nom[i], prm.offset_max_a)
    st.obs_age_s[p, i] += dt
    if math.isfinite(nis):
        a = fmin(1.0, dt / prm.nis_window_s)
        st.nis_avg[p, i] += a * (nis - st.nis_avg[p, i])
    bad = not _finite_state(st, p, i) or not (st.nis_avg[p, i] <= prm.nis_limit)
    if bad:
        k = emit(ev, p, src, OBS_DIVERGED, i, m.t_s[p])
        ev.val[k, 0] = st.nis_avg[p, i]
        ev.val[k, 1] = prm.nis_window_s
        ev.val[k, 2] = st.soc[p, i]
        ev.val[k, 3] = st.x[p, i, ob.X_SOC]
        st.obs_ok[p, i] = False
        _restart(prm, st, tp, p, i)
    elif not st.obs_ok[p, i] and st.obs_age_s[p, i] >= prm.nis_window_s - EPS:
        st.obs_ok[p, i] = True
        k = emit(ev, p, src, OBS_RESUMED, i, m.t_s[p])
        ev.val[k, 0] = st.nis_avg[p, i]
        ev.val[k, 1] = st.x[p, i, ob.X_SOC]
    _outputs(prm, st, tp, p, i, temp)


@kernel_inline
def cell_v_at(prm: SocParams, st: SocState, p: int, i: int, cur: float, temp: float,
              t: float) -> float:  # fmt: skip
    """The model's cell voltage ``t`` seconds ahead at the constant current ``cur``: SOC
    falls linearly; R0, R1 and tau are the tables' at that SOC (and the present temperature)
    times the estimated resistance scale; the polarisation relaxes from its present value
    toward ``R1 * cur``."""
    soc = st.x[p, i, ob.X_SOC] - cur * t / (3600.0 * st.x[p, i, ob.X_CAP])
    rs: float = st.x[p, i, ob.X_RSCALE]
    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, soc)
    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    ocv, _ = ob.ocv_at(prm.ocv_soc, prm.ocv_v, soc)
    v_ss = r1 * cur
    v1: float = v_ss + (st.x[p, i, ob.X_V1] - v_ss) * math.exp(-t / tau)
    return ocv - r0 * cur - v1


@kernel_inline
def time_to_cutoff(prm: SocParams, st: SocState, p: int, i: int, cur: float, temp: float) -> float:
    """Seconds until the model's cell voltage reaches the cut-off at the constant ``cur``:
    the first crossing on a scan of ``N_SCAN`` points up to the end of the OCV table, then
    bisection in that bracket. 0 when already at or below; NaN when not discharging or when
    no crossing lies within the table."""
    if not (cur >= prm.rest_current_a):
        return math.nan
    vc = prm.cutoff_cell_v
    if cell_v_at(prm, st, p, i, cur, temp, 0.0) <= vc:
        return 0.0
    horizon = (st.x[p, i, ob.X_SOC] - prm.ocv_soc[0]) * 3600.0 * st.x[p, i, ob.X_CAP] / cur
    if not (horizon > 0.0):
        return math.nan
    lo = 0.0
    hi = math.nan
    for k in range(1, N_SCAN + 1):
        t = horizon * k / N_SCAN
        if cell_v_at(prm, st, p, i, cur, temp, t) <= vc:
            hi = t
            break
        lo = t
    if not math.isfinite(hi):
        return math.nan
    for _ in range(N_BISECT):
        mid = 0.5 * (lo + hi)
        if cell_v_at(prm, st, p, i, cur, temp, mid) <= vc:
            hi = mid
        else:
            lo = mid
    return hi


@kernel_inline
def _predict(prm: SocParams, st: SocState, m: MeasArrays, p: int, i: int, dt: float) -> None:
    """The recent average load, and every ``predict_every_s`` the three times from it."""
    cur = m.bat.current_a[p, i]
    if not (math.isfinite(cur) and math.isfinite(st.x[p, i, ob.X_SOC])):
        return
    cur = cur - st.x[p, i, ob.X_OFFSET]
    # the mean since the start until a whole time constant has passed, exponential after
    st.load_age_s[p, i] += dt
    a = fmin(1.0, dt / fmin(prm.load_tau_s, st.load_age_s[p, i]))
    if not math.isfinite(st.load_avg_a[p, i]):
        st.load_avg_a[p, i] = cur
    else:
        st.load_avg_a[p, i] += a * (cur - st.load_avg_a[p, i])
    st.pred_age_s[p, i] += dt
    if st.pred_age_s[p, i] < prm.predict_every_s - EPS:
        return
    st.pred_age_s[p, i] = 0.0
    avg = st.load_avg_a[p, i]
    left_ah = st.shown_soc[p, i] * st.x[p, i, ob.X_CAP]
    st.time_to_go_s[p, i] = left_ah * 3600.0 / avg if avg >= prm.rest_current_a else math.nan
    missing_ah = (1.0 - st.shown_soc[p, i]) * st.x[p, i, ob.X_CAP]
    st.time_to_full_s[p, i] = (
        missing_ah * 3600.0 / -avg if avg <= -prm.rest_current_a else math.nan
    )
    temp = m.bat.temp_c[p, i]
    st.time_to_cutoff_s[p, i] = time_to_cutoff(
        prm, st, p, i, avg, temp if math.isfinite(temp) else 25.0
    )


@kernel_inline
def step_pack(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One tick of pack ``p``: no commands; the estimates and the rest time as status."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    for i in range(st.soc.shape[1]):
        _battery(prm, st, tp, m, p, i, dt, ev, src)
        if prm.observer:
            _observe(prm, st, tp, m, p, i, dt, ev, src)
        if prm.observer and st.obs_ok[p, i]:
            st.shown_soc[p, i] = fmin(1.0, fmax(0.0, st.x[p, i, ob.X_SOC]))
        else:
            st.shown_soc[p, i] = st.soc[p, i]
        if prm.observer:
            _predict(prm, st, m, p, i, dt)
        status[p, i, s0 + ST_SOC] = st.shown_soc[p, i]
        status[p, i, s0 + ST_REST] = st.rest_s[p, i]
        status[p, i, s0 + ST_FALLBACK] = st.soc[p, i]
        status[p, i, s0 + ST_SOC_SIGMA] = math.sqrt(st.soc_var[p, i])
        status[p, i, s0 + ST_EMF] = st.emf_v[p, i]
        status[p, i, s0 + ST_R0] = st.r0_ohm[p, i]
        status[p, i, s0 + ST_VRC] = st.v_rc_v[p, i]
        status[p, i, s0 + ST_CAP] = st.capacity_ah[p, i]
        status[p, i, s0 + ST_OFFSET] = st.offset_a[p, i]
        status[p, i, s0 + ST_NIS] = st.nis_avg[p, i]
        status[p, i, s0 + ST_OK] = 1.0 if st.obs_ok[p, i] else 0.0
        status[p, i, s0 + ST_TTG] = st.time_to_go_s[p, i]
        status[p, i, s0 + ST_TTC] = st.time_to_cutoff_s[p, i]
        status[p, i, s0 + ST_TTF] = st.time_to_full_s[p, i]
        status[p, i, s0 + ST_LOAD] = st.load_avg_a[p, i]


@kernel
def step_packs(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
