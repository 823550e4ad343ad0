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
OBS_INCONSISTENT = 3
CELL_SET_MISMATCH = 4

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
WEAK_HYST_V = 0.003
"""How much lower (V, per cell, low-passed) another group must read before the observer moves
to it (h28lfp): on an LFP plateau under load the groups' voltages coincide within the
low-pass's noise (telecom run 13: four groups 11 % of SOC apart read within 2 mV at 46 A,
the OCV's rise with SOC cancelled by the resistance's), so without a margin the choice
follows the noise and the observer's one SOC state is fed a different group every minute."""
V1_SIGMA0_OCV_V = 0.005
"""Prior standard deviation of the polarisation (V per cell) when the observer starts from a
reading taken as open-circuit (:func:`_open_circuit_start`), instead of the prior's 50 mV: of
the order of the reading's own noise, what that reading cannot exclude."""
STEP_RATIO = 3.0
"""A current step whose voltage change says a resistance this many times the cell set's counts
toward :func:`_step_resistance`'s mismatch ..."""
STEP_N = 3
"""... after this many such steps in a row (a step within the set's reach resets the count) ..."""
STEP_SIGMAS = 10.0
"""... each with a cell-voltage change of at least this many ``ekf_voltage_sigma_v`` (so the
noise moves the resistance it reads by a tenth at most) ..."""
STEP_DT_S = 1.0
"""... and within one period of at most this (s): the RC adds little in it."""
N_CV = 240
"""Steps of the time to full's constant-voltage phase, each an eighth of the taper's time
constant at its start (30 time constants: a current falling by e^30 at most)."""


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
    cells_per_group: I64
    """(B,) series cells in each of the battery's groups (its group voltage over this is the
    group's mean cell)."""
    bal_lo_a: float
    """The equalizers' current range per group (A; the plant clips a command to it) ..."""
    bal_hi_a: float
    bal_eff: float
    """... and their efficiency."""
    weak_tau_s: float
    """Time constant of the low-passed group cell voltages that pick the weakest group (s)."""
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
    du_t: F64
    """Temperature axis of the OCV's entropic coefficient (degC) ..."""
    du_tab: F64
    """... dOCV/dT (V/K) at each of its temperatures and each OCV point, T-major
    (``PackInfo.ocv_dudt_v_per_k``; ``[0, 0]`` on a 2-point axis where the set has none)."""
    t_ref_c: float
    """The temperature the OCV table holds at (degC); NaN: no temperature term."""
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
    cutoff_tau_s: float
    """Time constant (s) with which the time to cut-off shown, counted down between
    predictions, moves toward each new prediction."""
    predict_every_s: float
    full_cell_v: float
    """The charger's constant voltage per cell, which ``time_to_full_s`` ends at (V) ..."""
    full_current_a: F64
    """... (B,) once the charge current has tapered to this (A; the charge's end point)."""
    full_path_ohm: F64
    """(B,) the charge path per series cell (ohm): the charger holds ``full_cell_v`` at its
    regulation point, the cells see it lowered by this times the current."""
    consistency_sigma: float
    """The observer is rejected when its SOC departs from the fallback's by more than this
    many standard deviations of their difference (:func:`_inconsistency`; 0: not checked)."""


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
    grp_lp: F64
    """(P, B, G) each group's mean cell voltage, low-passed over ``weak_tau_s`` (NaN: not
    read yet): the weakest group is the lowest."""
    weak_g: I64
    """(P, B) the group the observer reads (-1: the min cell)."""
    bal_a: F64
    """(P, B, G) the equalizer currents of the last step's final commands (A into the group,
    clipped as the equalizers do): what flowed during the period the next measurement covers."""
    absent: NDArray[np.bool_]
    """(P, B) the battery was reported absent (not plugged in) since the observer last
    started: its next present sample is an insertion."""
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
    v_res_avg_v: F64
    """(P, B) the cell voltage the observer reads less the model's (after the correction, at
    the measured current), low-passed over ``weak_tau_s`` (V; 0 at a (re)start): how far the
    filter's voltage sits from the measured one, which the time to cut-off adds back."""
    load_exc_a: F64
    """(P, B) recent mean excess of the battery current over its recent average (A; the
    positive part, averaged like the load): the gusts above the average the time to cut-off
    keeps a margin for."""
    pred_age_s: F64
    """(P, B) time since the predictions were last computed (inf: never)."""
    time_to_go_s: F64
    """(P, B) shown SOC x capacity / recent average load (NaN unless discharging)."""
    time_to_cutoff_s: F64
    """(P, B) when the cell voltage reaches ``cutoff_cell_v`` at the recent average load, the
    polarisation relaxing toward its steady state on the way (NaN: not discharging, or not
    within the OCV table)."""
    time_to_full_s: F64
    """(P, B) when a CC/CV charge at the recent average charge current ends: the battery's
    mean cell at ``full_cell_v`` and the current tapered to ``full_current_a``
    (:func:`time_to_full`; NaN unless charging)."""
    cv_left_s: F64
    """(P, B) the constant-voltage phase's taper left (s), computed once when the phase
    begins and counted down (NaN outside that phase): see :func:`time_to_full`."""
    chg_temp0_c: F64
    """(P, B) the measured temperature when the present charge began (degC; NaN while not
    charging): what the cells cool back toward as the taper's current, and its heat, fall."""
    fb_var0: F64
    """(P, B) variance of the fallback's SOC at its last anchor (its start from an OCV reading
    or a stored SOC, or its last OCV correction after a rest; NaN: not anchored yet) ..."""
    fb_net: F64
    """(P, B) ... the SOC it has counted since (signed, the capacity as configured) ..."""
    fb_age_s: F64
    """(P, B) ... and the time since: with the capacity's and the current offset's prior
    uncertainty, what :func:`fallback_var` grows from."""
    prev_i_a: F64
    """(P, B) the current the observer read at its last sample (NaN: none) ..."""
    prev_v: F64
    """(P, B) ... and the cell voltage (V): the step a current change makes, read directly."""
    step_hi_n: I64
    """(P, B) current steps in a row whose resistance was above ``STEP_RATIO`` x the set's."""
    misfit: F64
    """(P, B) the step resistance over the cell set's when :func:`_step_resistance` found them
    apart (0: not found; kept for the run: the set does not change)."""
    fb_absent: NDArray[np.bool_]
    """(P, B) the battery was reported absent since the fallback last read it: its next
    present sample is an insertion, and the fallback starts again from its OCV."""


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
def ocv_t(prm: SocParams, soc: float, temp_c: float) -> tuple[float, float]:
    """(OCV, dOCV/dSOC) of the cell at ``soc`` and ``temp_c`` (the entropic term included)."""
    return ob.ocv_temp_at(prm.ocv_soc, prm.ocv_v, prm.du_t, prm.du_tab, prm.t_ref_c, soc,
                          temp_c)  # fmt: skip


@kernel_inline
def _cell_v(prm: SocParams, m: MeasArrays, p: int, i: int) -> float:
    if prm.use_min_cell:
        return float(m.bat.min_cell_v[p, i])
    return float(m.bat.voltage_v[p, i] / prm.series_cells[i])


@kernel_inline
def _observed_v(prm: SocParams, st: SocState, m: MeasArrays, p: int, i: int, dt: float) -> float:
    """The cell voltage the observer reads: with two or more groups reported (and ``voltage =
    "min"``), the weakest group's mean cell, the weakest being the lowest low-passed one; else
    the fallback's reading (:func:`_cell_v`, the min cell).

    Why not the min cell: each cell is read with its own noise, and the minimum of N noisy
    readings sits below the weakest cell by about sigma x E[min of N normals] (6 mV for 6
    cells, 9 mV for 16 at 5 mV), steadily, not as noise: on LFP's flat OCV that is ~10 %
    of SOC, at a cut-off knee seconds of time to cut-off. One chosen group's reading carries
    its noise unbiased (the choice rests on the low-passed past, not on this sample)."""
    ng = m.bat.n_groups[p, i]
    if not prm.use_min_cell or ng < 2 or ng > st.grp_lp.shape[2]:
        st.weak_g[p, i] = -1
        return _cell_v(prm, m, p, i)
    cpg = float(prm.cells_per_group[i])
    a = fmin(1.0, dt / prm.weak_tau_s) if dt > 0.0 else 0.0
    best = -1
    best_v = math.inf
    prev = st.weak_g[p, i]
    prev_v = math.inf
    for g in range(ng):  # chosen on the past, then this sample joins the low-pass
        v = m.bat.group_v[p, i, g] / cpg
        if not math.isfinite(v):
            st.weak_g[p, i] = -1
            return _cell_v(prm, m, p, i)  # a group unread may be the weakest
        lp = st.grp_lp[p, i, g]
        if not math.isfinite(lp):
            lp = v
        if lp < best_v:
            best_v = lp
            best = g
        if g == prev:
            prev_v = lp
        st.grp_lp[p, i, g] = lp + a * (v - lp)
    if prev_v - best_v < WEAK_HYST_V:  # the group read stays until another is clearly lower
        best = prev
    st.weak_g[p, i] = best
    return float(m.bat.group_v[p, i, best] / cpg)


@kernel_inline
def _group_current(prm: SocParams, st: SocState, m: MeasArrays, p: int, i: int,
                   cur: float) -> float:  # fmt: skip
    """The current through the cells of the group the observer reads (positive discharging):
    the battery's, plus what every equalizer of the battery draws from it as power (its
    current x its group's voltage, over the efficiency when charging a group, times it when
    taking charge out) over the battery voltage, minus that group's own equalizer current.
    Why: an equalizer feeding the weakest group for hours moves amperes the battery's current
    sensor never sees (telecom_string: 2.8 Ah into its weakest group over a recharge, 2.8 % of
    SOC that a flat LFP OCV cannot correct)."""
    g = st.weak_g[p, i]
    ng = m.bat.n_groups[p, i]
    if g < 0 or ng > st.bal_a.shape[2]:
        return cur
    p_in = 0.0
    v_sum = 0.0
    for k in range(ng):
        ib = st.bal_a[p, i, k]
        vg = m.bat.group_v[p, i, k]
        p_in += ib * vg / prm.bal_eff if ib > 0.0 else ib * vg * prm.bal_eff
        v_sum += vg
    if not (v_sum > 0.0 and math.isfinite(p_in)):
        return cur
    return float(cur + p_in / v_sum - st.bal_a[p, i, g])


@kernel_inline
def _anchor(st: SocState, p: int, i: int, var: float) -> None:
    """The fallback's SOC was just set with variance ``var``: its counting starts over."""
    st.fb_var0[p, i] = var
    st.fb_net[p, i] = 0.0
    st.fb_age_s[p, i] = 0.0


@kernel_inline
def _ocv_slope(prm: SocParams, soc: float) -> float:
    """dOCV/dSOC of the reference table's segment at ``soc`` (V per unit SOC, > 0)."""
    xs, ys = prm.ocv_soc, prm.ocv_v
    k = 1
    while k < xs.shape[0] - 1 and xs[k] < soc:
        k += 1
    return float((ys[k] - ys[k - 1]) / (xs[k] - xs[k - 1]))


@kernel_inline
def _ocv_var(prm: SocParams, soc: float, v1_sigma_v: float) -> float:
    """Variance of a SOC read off the OCV table at ``soc``: the voltage's (``var_v``) and a
    polarisation of ``v1_sigma_v`` left in the reading, over the OCV's slope there; at most the
    observer's prior (a flat OCV tells little, never less than a restart knows)."""
    slope = _ocv_slope(prm, soc)
    return fmin(prm.sig0[0] * prm.sig0[0], (prm.var_v + v1_sigma_v * v1_sigma_v) / (slope * slope))


@kernel_inline
def fallback_var(prm: SocParams, st: SocState, tp: PackArrays, p: int, i: int) -> float:
    """Variance of the fallback's SOC (the coulomb counter since its last anchor): the anchor's,
    plus the counted SOC times the capacity's prior relative uncertainty (a capacity, or a
    current gain, wrong by x makes the counted change wrong by x of itself), plus the current
    offset's prior over the time since (an offset of 0.3 A counts 0.3 A x that time).

    Why a model of it: the fallback is the one estimate that does not rest on the cell model
    (its R0, RC and OCV under load), so it is the reference against which a self-consistent but
    wrong observer shows (:func:`_inconsistency`)."""
    q = tp.capacity_ah[p, i] * 3600.0
    off = prm.sig0[4] * st.fb_age_s[p, i] / q
    cap = prm.sig0[3] * st.fb_net[p, i]
    return float(st.fb_var0[p, i] + cap * cap + off * off)


@kernel_inline
def _battery(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, i: int, dt: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    if not (m.bat.reported[p, i] and m.bat.present[p, i]):
        st.rest_s[p, i] = 0.0
        st.next_fix_s[p, i] = 0.0
        if m.bat.reported[p, i]:
            st.fb_absent[p, i] = True
        return
    if st.fb_absent[p, i]:  # inserted: where it has been is unknown, so read it as at power-up
        st.fb_absent[p, i] = False
        st.soc[p, i] = math.nan
    if not math.isfinite(st.soc[p, i]):
        st.soc[p, i] = soc_from_ocv(prm, _cell_v(prm, m, p, i))
        _anchor(st, p, i, _ocv_var(prm, st.soc[p, i], V1_SIGMA0_OCV_V))
        return  # initialised from this sample; its current belongs to the past
    if not math.isfinite(st.fb_var0[p, i]):  # a SOC restored at power-up: as uncertain as a start
        _anchor(st, p, i, prm.sig0[0] * prm.sig0[0])
    st.fb_age_s[p, i] += dt
    cur = m.bat.current_a[p, i]
    if not math.isfinite(cur):
        st.rest_s[p, i] = 0.0  # unknown current: hold, and no rest
        st.next_fix_s[p, i] = 0.0
        return
    counted = -cur * dt / (3600.0 * tp.capacity_ah[p, i])
    st.fb_net[p, i] += counted
    st.soc[p, i] = fmin(1.0, fmax(0.0, st.soc[p, i] + counted))
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
    _anchor(st, p, i, (1.0 - prm.blend) ** 2 * fallback_var(prm, st, tp, p, i)
            + prm.blend * prm.blend * _ocv_var(prm, ocv_soc, 0.0))  # fmt: skip
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
    ocv, _ = ocv_t(prm, soc, temp_c)
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
    st.v_res_avg_v[p, i] = 0.0


@kernel_inline
def _open_circuit_start(st: SocState, p: int, i: int) -> None:
    """After a (re)set whose SOC was read off this very sample as an open-circuit voltage (the
    observer's first start, from the fallback's first SOC; an inserted battery): the
    polarisation's prior narrowed to ``V1_SIGMA0_OCV_V``.

    Why: the SOC it starts from assumes no polarisation at that reading, so a wide prior on
    ``v1`` (50 mV) contradicts the reading the SOC came from, and opens a direction (SOC up,
    ``v1`` up) along which the voltage does not change. Measured (campaign, uav_dual_parallel,
    the batteries 2 V apart, so A's first seconds are a 37 A inrush into B): within 3 s the
    filter read the inrush's drop as 118 mV of polarisation (the RC builds ~20 mV in that
    time) and the SOC 7 % high with a SOC sigma of 0.8 %; the capacity state then fell to
    0.62x to undo it (runs 2, 16, 19, 20: 4-5 % max with the OCV over the SOC's spread and the
    offset state, 0.5-0.8 % with this prior). A restart after divergence keeps the wide
    prior: the battery may then be under load, its polarisation anything."""
    st.cov[p, i, ob.X_V1, ob.X_V1] = V1_SIGMA0_OCV_V * V1_SIGMA0_OCV_V


@kernel_inline
def soc_from_ocv_t(prm: SocParams, cell_v: float, temp_c: float) -> float:
    """The SOC whose OCV at ``temp_c`` is ``cell_v`` (the reference table's inverse, then
    Newton steps on :func:`ocv_t`, which is linear within a table segment), within 0..1."""
    s = soc_from_ocv(prm, cell_v)
    if not math.isfinite(s):
        return s
    for _ in range(4):
        ocv, slope = ocv_t(prm, s, temp_c)
        if not (slope > 0.0):
            break
        s = fmin(1.0, fmax(0.0, s - (ocv - cell_v) / slope))
    return s


@kernel_inline
def _start_from_ocv(
    prm: SocParams, st: SocState, tp: PackArrays, p: int, i: int, y: float, cur: float,
    temp: float,
) -> None:  # fmt: skip
    """A battery just inserted: its first present sample covers a period in which it was not
    connected (the sampling convention: a measurement at ``t`` carries the current of
    ``[t - dt, t]``), so its voltage is open-circuit whatever the current sensor's offset
    reads. The observer starts at the SOC that OCV gives (at its temperature) with the prior,
    corrected once by that same reading, so its SOC variance is what the reading supports (the
    voltage's variance and the unknown polarisation over the OCV's slope: large on a flat
    OCV); it is the source at once, its window test running as always. Why not the fallback's
    SOC: the BMS cannot know where an inserted battery has been, so any belief it held for that
    slot is stale. (A rest test on the current would fail exactly here: a +0.2 A offset reads
    above a 0.1 A rest threshold at zero current.)"""
    s = soc_from_ocv_t(prm, y, temp)
    if not math.isfinite(s):
        _restart(prm, st, tp, p, i)
        return
    ob.reset(st.x, st.cov, p, i, s, tp.capacity_ah[p, i], prm.r_nom[i], prm.sig0)
    _open_circuit_start(st, p, i)
    r0 = ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, s)
    ob.correct(st.x, st.cov, st.hv, st.kv, st.wk, p, i, y, cur, r0, prm.ocv_soc, prm.ocv_v,
               prm.du_t, prm.du_tab, prm.t_ref_c, temp, prm.var_v)  # fmt: skip
    ob.bound(st.x, st.cov, p, i, tp.capacity_ah[p, i], prm.r_nom[i], prm.offset_max_a)
    st.nis_avg[p, i] = 1.0
    st.obs_age_s[p, i] = 0.0
    st.v_res_avg_v[p, i] = 0.0
    st.obs_ok[p, i] = _finite_state(st, p, i)


@kernel_inline
def _note_residual(prm: SocParams, st: SocState, p: int, i: int, y: float, cur: float,
                   dt: float) -> None:  # fmt: skip
    """Low-pass (over ``weak_tau_s``) the reading ``y`` less the model's cell voltage after
    the correction, at the current ``cur`` the filter used (from :func:`_outputs`, battery
    units over the series cells). Why: a filter whose model falls more slowly than the cell
    (near the cut-off knee) trails the reading by a steady 1-2 mV, ~2 s of time to cut-off
    at 14 A on the test pack (measured, h28cut), which its state does not show."""
    ns = float(prm.series_cells[i])
    ic = cur - st.x[p, i, ob.X_OFFSET]
    r = y - (st.emf_v[p, i] - st.r0_ohm[p, i] * ic - st.v_rc_v[p, i]) / ns
    if math.isfinite(r) and dt > 0.0:
        st.v_res_avg_v[p, i] += fmin(1.0, dt / prm.weak_tau_s) * (r - st.v_res_avg_v[p, i])


@kernel_inline
def _observe(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, p: int, i: int, dt: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """One tick of battery ``i``'s observer, then its window test (after the fallback ran)."""
    if m.bat.reported[p, i] and not m.bat.present[p, i]:
        st.absent[p, i] = True
    if not (m.bat.reported[p, i] and m.bat.present[p, i]) or not math.isfinite(st.soc[p, i]):
        return
    cur = m.bat.current_a[p, i]
    temp = m.bat.temp_c[p, i]
    if not math.isfinite(temp):
        temp = 25.0
    y = _observed_v(prm, st, m, p, i, dt)
    if st.absent[p, i]:  # inserted: its first reading is open-circuit, it tells its SOC
        st.absent[p, i] = False
        st.prev_i_a[p, i] = math.nan
        _start_from_ocv(prm, st, tp, p, i, y, cur if math.isfinite(cur) else 0.0, temp)
        _outputs(prm, st, tp, p, i, temp)
        return
    if not math.isfinite(st.x[p, i, ob.X_SOC]):
        _restart(prm, st, tp, p, i)
        _open_circuit_start(st, p, i)
        return  # starts from this sample, like the fallback
    if not math.isfinite(cur) or dt <= 0.0:
        st.prev_i_a[p, i] = math.nan
        return
    cur = _group_current(prm, st, m, p, i, cur)
    _step_resistance(prm, st, p, i, y, cur, dt, temp, ev, src, m.t_s[p])
    soc = st.x[p, i, ob.X_SOC]
    r1 = ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    ob.predict(st.x, st.cov, st.fm, st.wk, p, i, cur, dt, r1, tau, prm.walk)
    r0 = ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, st.x[p, i, ob.X_SOC])
    nis = ob.correct(st.x, st.cov, st.hv, st.kv, st.wk, p, i, y, cur, r0,
                     prm.ocv_soc, prm.ocv_v, prm.du_t, prm.du_tab, prm.t_ref_c, temp,
                     prm.var_v)  # fmt: skip
    ob.bound(st.x, st.cov, p, i, tp.capacity_ah[p, i], prm.r_nom[i], prm.offset_max_a)
    st.obs_age_s[p, i] += dt
    if math.isfinite(nis):
        a = fmin(1.0, dt / prm.nis_window_s)
        st.nis_avg[p, i] += a * (nis - st.nis_avg[p, i])
    bad = not _finite_state(st, p, i) or not (st.nis_avg[p, i] <= prm.nis_limit)
    z = 0.0 if bad else _inconsistency(prm, st, tp, p, i)
    if bad:
        k = emit(ev, p, src, OBS_DIVERGED, i, m.t_s[p])
        ev.val[k, 0] = st.nis_avg[p, i]
        ev.val[k, 1] = prm.nis_window_s
        ev.val[k, 2] = st.soc[p, i]
        ev.val[k, 3] = st.x[p, i, ob.X_SOC]
        st.obs_ok[p, i] = False
        _restart(prm, st, tp, p, i)
    elif prm.consistency_sigma > 0.0 and z > prm.consistency_sigma:
        if st.obs_ok[p, i]:
            k = emit(ev, p, src, OBS_INCONSISTENT, i, m.t_s[p])
            ev.val[k, 0] = st.x[p, i, ob.X_SOC]
            ev.val[k, 1] = st.soc[p, i]
            ev.val[k, 2] = math.sqrt(fallback_var(prm, st, tp, p, i))
            ev.val[k, 3] = z
            st.obs_ok[p, i] = False
        st.obs_age_s[p, i] = 0.0  # a whole window consistent again before it is trusted
    elif st.misfit[p, i] > ob.R_SCALE_MAX:  # the set's R0 beyond the scale's reach: never
        st.obs_ok[p, i] = False
        st.obs_age_s[p, i] = 0.0
    elif not st.obs_ok[p, i] and st.obs_age_s[p, i] >= prm.nis_window_s - EPS:
        st.obs_ok[p, i] = True
        k = emit(ev, p, src, OBS_RESUMED, i, m.t_s[p])
        ev.val[k, 0] = st.nis_avg[p, i]
        ev.val[k, 1] = st.x[p, i, ob.X_SOC]
    _outputs(prm, st, tp, p, i, temp)
    if not bad:
        _note_residual(prm, st, p, i, y, cur, dt)


@kernel_inline
def _step_resistance(
    prm: SocParams, st: SocState, p: int, i: int, y: float, cur: float, dt: float,
    temp: float, ev: EventBuf, src: int, t_s: float,
) -> None:  # fmt: skip
    """The battery's resistance read off a current step (the cell voltage's change over the
    current's, within one short period), against the cell set's R0 at the battery's nominal
    scale: ``STEP_N`` steps in a row above ``STEP_RATIO`` x it say the set does not describe
    this battery (``SocCellSetMismatch``, once); beyond ``ob.R_SCALE_MAX`` the observer's
    resistance scale cannot reach it, and the observer is not trusted (the counter shown).

    Why: a model-free reading, independent of everything the filter estimates. Measured on the
    real dronekit tlog told the shipped ``uav_5ah`` set (R0 1.9 mOhm per cell): its take-off
    steps read 49, 49 and 53 mOhm per cell; the filter, bounded at 10x, diverged 11 times and
    explained the rest with its SOC and offset (`benchmarks/bench_soc_real.py`, setup A). Only
    the too-large direction is read: a voltage sampled late makes a step read low, never
    high, at a clean step."""
    di = cur - st.prev_i_a[p, i]
    dv = y - st.prev_v[p, i]
    st.prev_i_a[p, i] = cur
    st.prev_v[p, i] = y
    if not (math.isfinite(di) and math.isfinite(dv) and dt <= STEP_DT_S and di != 0.0):
        return
    if abs(dv) < STEP_SIGMAS * math.sqrt(prm.var_v) or not (-dv / di > 0.0):
        return
    r = -dv / di
    r_set = prm.r_nom[i] * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, st.x[p, i, ob.X_SOC])
    if not (r > STEP_RATIO * r_set):
        st.step_hi_n[p, i] = 0
        return
    st.step_hi_n[p, i] += 1
    if st.step_hi_n[p, i] == STEP_N and st.misfit[p, i] == 0.0:
        st.misfit[p, i] = r / r_set
        k = emit(ev, p, src, CELL_SET_MISMATCH, i, t_s)
        ev.val[k, 0] = r
        ev.val[k, 1] = r_set
        ev.val[k, 2] = r / r_set
        ev.val[k, 3] = di


@kernel_inline
def _inconsistency(prm: SocParams, st: SocState, tp: PackArrays, p: int, i: int) -> float:
    """How many standard deviations the observer's SOC (within 0..1, as shown) is from the
    fallback's: the difference over the root of the sum of their variances (the observer's
    own, and :func:`fallback_var`); 0 where either is not known.

    Why: the window test sees only whether the innovations match their predicted variance; a
    filter whose model is wrong (R0 off, a warm pack read with a cold table) can explain the
    voltage with a wrong SOC and stay within that test. Measured on the real dronekit tlog
    (bench_soc_real, R0 told 46.6 mOhm per cell): restarted in the warm third flight, the
    observer rose from the counter's 0.31 to 0.96 in 15 s while 19 A were drawn, and ended
    the log trusted at 0.93 where the OCV reads 0.44. The counter cannot move the SOC up while
    discharging; what it is uncertain of is bounded by its anchor, the capacity and the
    offset, and a model-based estimate far outside that has not earned trust."""
    s = fmin(1.0, fmax(0.0, st.x[p, i, ob.X_SOC]))
    var = fallback_var(prm, st, tp, p, i) + st.cov[p, i, ob.X_SOC, ob.X_SOC]
    d = s - st.soc[p, i]
    if not (math.isfinite(d) and var > 0.0):
        return 0.0
    return float(abs(d) / math.sqrt(var))


@kernel
def cell_v_at(prm: SocParams, st: SocState, p: int, i: int, cur: float, temp: float,
              t: float, q: float) -> float:  # fmt: skip
    """The model's cell voltage ``t`` seconds ahead at the constant current ``cur``: SOC
    falls linearly (capacity ``q``); R0, R1 and tau are the tables' at that SOC (and the
    present temperature) times the estimated resistance scale; the polarisation relaxes from
    its present value toward ``R1 * cur``."""
    soc = st.x[p, i, ob.X_SOC] - cur * t / (3600.0 * q)
    rs: float = st.x[p, i, ob.X_RSCALE]
    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, soc)
    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    ocv, _ = ocv_t(prm, soc, temp)
    v_ss = r1 * cur
    v1: float = v_ss + (st.x[p, i, ob.X_V1] - v_ss) * math.exp(-t / tau)
    return ocv - r0 * cur - v1


@kernel_inline
def cutoff_level_v(prm: SocParams, st: SocState, p: int, i: int, temp: float) -> float:
    """The level the model's cell voltage at the average load must reach for the cut-off:
    ``cutoff_cell_v`` less the reading's recent offset from the model (``v_res_avg_v``: the
    reading is what trips), plus the ohmic drop of the load's recent mean excess over its
    average (``load_exc_a`` x the present R0: the protection trips on the first gust that
    reaches the cut-off, not on the average)."""
    r0 = st.x[p, i, ob.X_RSCALE] * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp,
                                              st.x[p, i, ob.X_SOC])  # fmt: skip
    vc: float = prm.cutoff_cell_v
    res = st.v_res_avg_v[p, i]
    if math.isfinite(res):
        vc = vc - res
    exc = st.load_exc_a[p, i]
    if math.isfinite(exc) and math.isfinite(r0):
        vc = vc + r0 * exc
    return vc


@kernel
def time_to_cutoff(prm: SocParams, st: SocState, p: int, i: int, cur: float, temp: float) -> float:
    """Seconds until the model's cell voltage at the constant ``cur`` reaches the cut-off
    level (:func:`cutoff_level_v`), the SOC falling at the capacity state: the first crossing
    on a scan of ``N_SCAN`` points up to the end of the OCV table, then bisection in that
    bracket. 0 when already at or below; NaN when not discharging or when no crossing lies
    within the table. Why the capacity state and not the SOC's recent rate (h28soc's
    ``pred_capacity_ah``, removed): that rate carries the SOC's own convergence, so after a
    10 % wrong start it held the capacity at its 1.5x bound for minutes (time to cut-off 46 %
    late on the test pack, h28cut)."""
    if not (cur >= prm.rest_current_a):
        return math.nan
    vc = cutoff_level_v(prm, st, p, i, temp)
    q: float = st.x[p, i, ob.X_CAP]
    if cell_v_at(prm, st, p, i, cur, temp, 0.0, q) <= vc:
        return 0.0
    horizon = (st.x[p, i, ob.X_SOC] - prm.ocv_soc[0]) * 3600.0 * q / cur
    if not (horizon > 0.0):
        return math.nan
    lo = 0.0
    hi = math.nan
    for k in range(1, N_SCAN + 1):
        t = horizon * k / N_SCAN
        if cell_v_at(prm, st, p, i, cur, temp, t, q) <= vc:
            hi = t
            break
        lo = t
    if not math.isfinite(hi):
        return math.nan
    for _ in range(N_BISECT):
        mid = 0.5 * (lo + hi)
        if cell_v_at(prm, st, p, i, cur, temp, mid, q) <= vc:
            hi = mid
        else:
            lo = mid
    return hi


@kernel_inline
def _mean_cell_above_v(st: SocState, m: MeasArrays, p: int, i: int) -> float:
    """How far the battery's mean cell sits above the cell the observer reads (V): the mean
    of the low-passed group voltages (:func:`_observed_v`) less the weakest one's; 0 where the
    observer reads no chosen group. Why: the charger holds the *battery's* voltage, the sum of
    its cells, so the stronger cells bring its CV phase on before the weakest is full
    (measured on the 6S test pack: the weakest cell ends the charge at 4.145 V, SOC 97.5 %)."""
    g = st.weak_g[p, i]
    ng = m.bat.n_groups[p, i]
    if g < 0 or ng < 2 or ng > st.grp_lp.shape[2]:
        return 0.0
    tot = 0.0
    for k in range(ng):
        tot += st.grp_lp[p, i, k]
    d = tot / ng - st.grp_lp[p, i, g]
    return d if math.isfinite(d) and d > 0.0 else 0.0


@kernel_inline
def _taper_modes(r0: float, r1: float, tau: float, a: float, cur: float,
                 v1: float) -> tuple[float, float, float, float]:  # fmt: skip
    """The CV phase's current over one step with its coefficients frozen, exactly: the state
    ``(i, v1)`` obeys ``y' = A y`` with ``A = [[-(a + R1/tau)/R0, 1/(tau R0)], [R1/tau,
    -1/tau]]`` (``R0`` the cell's plus its share of the charge path, ``a = OCV'/(3600 q)``),
    whose two eigenvalues are real and negative (a passive RC network), so ``i(t) = c1
    exp(l1 t) + c2 exp(l2 t)``: returns ``(c1, l1, c2, l2)``; ``l1 == l2`` (NaN) when the
    eigenvalues coincide, which an RC branch (``R1 > 0``) rules out."""
    a11 = -(a + r1 / tau) / r0
    a12 = 1.0 / (tau * r0)
    a21 = r1 / tau
    a22 = -1.0 / tau
    tr = a11 + a22
    disc = (a11 - a22) * (a11 - a22) + 4.0 * a12 * a21
    if not (disc > 0.0):
        return math.nan, math.nan, math.nan, math.nan
    d = math.sqrt(disc)
    l1 = 0.5 * (tr + d)
    l2 = 0.5 * (tr - d)
    ay = a11 * cur + a12 * v1
    return (ay - l2 * cur) / d, l1, -(ay - l1 * cur) / d, l2


@kernel
def cv_taper_s(prm: SocParams, st: SocState, p: int, i: int, soc: float, v1: float,
               cur: float, temp: float, q: float) -> float:  # fmt: skip
    """Seconds for the charge current to taper from ``cur`` (< 0) to the end current with
    the charger's voltage held at its regulation point (``OCV(soc) - (R0 + Rp) i - v1``
    constant, ``Rp`` the charge path per cell, ``full_path_ohm``): differentiated, ``(R0 + Rp)
    di/dt = -OCV'(soc) i / (3600 q) - (R1 i - v1) / tau``, a linear system solved exactly
    over steps of an eighth of ``3600 q (R0 + Rp + R1) / OCV'`` (the taper's time constant
    at the start) with the tables and the OCV slope frozen within each step
    (:func:`_taper_modes`); the crossing of the end current bisected within its step. Why not
    the voltage equation itself: on R0 ~ 5 mOhm a 5 mV model error is 1 A; its derivative
    carries no offset. Why exact steps: implicit Euler at these steps read the taper 5 %
    long (21 s of 375 on the test pack), which hid part of the missing charge path. NaN
    when it does not taper within ``N_CV`` steps (an OCV flat to its end)."""
    i_end: float = -prm.full_current_a[i]
    if cur >= i_end:
        return 0.0
    rs: float = st.x[p, i, ob.X_RSCALE]
    rp: float = prm.full_path_ohm[i]
    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, soc) + rp
    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    _v, slope = ocv_t(prm, soc, temp)
    if not (slope > 0.0 and r0 > 0.0):
        return math.nan
    h = 3600.0 * q * (r0 + r1) / slope / 8.0
    t = 0.0
    for _ in range(N_CV):
        r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, soc) + rp
        r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
        tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
        _v, slope = ocv_t(prm, soc, temp)
        a = fmax(0.0, slope) / (3600.0 * q)
        c1, l1, c2, l2 = _taper_modes(r0, r1, tau, a, cur, v1)
        if not (l1 < 0.0 and l2 < l1):
            return math.nan
        e1 = math.exp(l1 * h)
        e2 = math.exp(l2 * h)
        nxt = c1 * e1 + c2 * e2
        if nxt >= i_end:
            lo = 0.0
            hi = h
            for _k in range(N_BISECT):
                mid = 0.5 * (lo + hi)
                if c1 * math.exp(l1 * mid) + c2 * math.exp(l2 * mid) >= i_end:
                    hi = mid
                else:
                    lo = mid
            return t + hi
        # each mode's v1 from the first row of A: v1 = tau (R0 l + a) i + R1 i
        v1 = c1 * e1 * (tau * (r0 * l1 + a) + r1) + c2 * e2 * (tau * (r0 * l2 + a) + r1)
        soc -= (c1 * (e1 - 1.0) / l1 + c2 * (e2 - 1.0) / l2) / (3600.0 * q)
        cur = nxt
        t += h
    return math.nan


@kernel
def _cc_cell_v(prm: SocParams, st: SocState, p: int, i: int, soc0: float, chg_a: float,
               temp: float, t: float, q: float) -> float:  # fmt: skip
    """The charger's voltage per cell at its regulation point ``t`` seconds into a charge at
    the constant ``chg_a`` (> 0) from ``soc0``: the mean cell's terminal voltage (as
    :func:`cell_v_at`, from that SOC instead of the observer's) plus the charge path's drop
    (``full_path_ohm`` x ``chg_a``): the CC phase ends when *that* reaches the CV voltage."""
    soc = soc0 + chg_a * t / (3600.0 * q)
    rs: float = st.x[p, i, ob.X_RSCALE]
    rp: float = prm.full_path_ohm[i]
    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, temp, soc) + rp
    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    ocv, _d = ocv_t(prm, soc, temp)
    v_ss = -r1 * chg_a
    v1: float = v_ss + (st.x[p, i, ob.X_V1] - v_ss) * math.exp(-t / tau)
    return ocv + r0 * chg_a - v1


@kernel
def time_to_full(prm: SocParams, st: SocState, m: MeasArrays, p: int, i: int, chg_a: float,
                 elapsed_s: float, temp: float) -> float:  # fmt: skip
    """Seconds until a CC/CV charge ends, on the battery's mean cell (the SOC whose OCV is
    the observer's OCV plus :func:`_mean_cell_above_v`, with the observer's polarisation,
    resistance scale and capacity state): constant current ``chg_a`` (the recent average
    charge current, A > 0) until its terminal voltage plus the charge path's drop reaches
    ``full_cell_v`` (:func:`_cc_cell_v`; a scan and bisection as for the cut-off), then the
    charger's voltage held until the current has tapered to ``full_current_a``
    (:func:`cv_taper_s`, at a temperature halfway back to the charge's start, never above
    the present one: the cells cool as the current's I^2 R heat falls away, 22.1 -> 20.6
    degC over the test pack's taper, which raises its resistance by ~2 % and its duration
    by 7 s). Once the model reaches that voltage now, the taper from the recent average
    current is computed once (``cv_left_s``) and counted down
    by the ``elapsed_s`` since the last prediction until the charge stops. Why not the taper
    from the present current: the current sensor's offset is of the order of the end current
    (+0.2 A against C/20 = 0.25 A on the test pack), so the last minutes read 30-60 s short;
    the model's taper from the CC current carries only its time-constant error. NaN unless
    charging, or when the CV voltage lies beyond the OCV table."""
    if not (chg_a >= prm.rest_current_a):
        st.cv_left_s[p, i] = math.nan
        st.chg_temp0_c[p, i] = math.nan
        return math.nan
    if not math.isfinite(st.chg_temp0_c[p, i]):
        st.chg_temp0_c[p, i] = temp
    if math.isfinite(st.cv_left_s[p, i]):  # in the CV phase: its taper counted down
        st.cv_left_s[p, i] = fmax(0.0, st.cv_left_s[p, i] - elapsed_s)
        return float(st.cv_left_s[p, i])
    q: float = st.x[p, i, ob.X_CAP]
    soc0: float = st.x[p, i, ob.X_SOC]
    ocv0, _d = ocv_t(prm, soc0, temp)
    mean = soc_from_ocv_t(prm, ocv0 + _mean_cell_above_v(st, m, p, i), temp)
    soc0 = fmax(soc0, mean) if math.isfinite(mean) else soc0
    v_full = prm.full_cell_v
    # the taper's temperature: halfway back to the charge's start (its I^2 R heat falls away)
    t_cv = fmin(temp, 0.5 * (temp + st.chg_temp0_c[p, i]))
    if _cc_cell_v(prm, st, p, i, soc0, chg_a, temp, 0.0, q) >= v_full:
        st.cv_left_s[p, i] = cv_taper_s(prm, st, p, i, soc0, st.x[p, i, ob.X_V1], -chg_a,
                                        t_cv, q)  # fmt: skip
        return float(st.cv_left_s[p, i])
    horizon = (prm.ocv_soc[prm.ocv_soc.shape[0] - 1] - soc0) * 3600.0 * q / chg_a
    if not (horizon > 0.0):
        return math.nan
    lo = 0.0
    hi = math.nan
    for k in range(1, N_SCAN + 1):
        t = horizon * k / N_SCAN
        if _cc_cell_v(prm, st, p, i, soc0, chg_a, temp, t, q) >= v_full:
            hi = t
            break
        lo = t
    if not math.isfinite(hi):
        return math.nan
    for _ in range(N_BISECT):
        mid = 0.5 * (lo + hi)
        if _cc_cell_v(prm, st, p, i, soc0, chg_a, temp, mid, q) >= v_full:
            hi = mid
        else:
            lo = mid
    soc = soc0 + chg_a * hi / (3600.0 * q)
    rs: float = st.x[p, i, ob.X_RSCALE]
    v_ss = -chg_a * rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, temp, soc)
    v1 = v_ss + (st.x[p, i, ob.X_V1] - v_ss) * math.exp(-hi / tau)
    return hi + cv_taper_s(prm, st, p, i, soc, v1, -chg_a, t_cv, q)


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
    exc = fmax(0.0, cur - st.load_avg_a[p, i])
    if not math.isfinite(st.load_exc_a[p, i]):
        st.load_exc_a[p, i] = exc
    else:
        st.load_exc_a[p, i] += a * (exc - st.load_exc_a[p, i])
    st.pred_age_s[p, i] += dt
    if st.pred_age_s[p, i] < prm.predict_every_s - EPS:
        # between predictions the time to cut-off counts down (a reading up to a whole
        # period old was up to 0.9 s late: 8 % at 11 s before the trip, h28cut)
        if st.time_to_cutoff_s[p, i] > 0.0:
            st.time_to_cutoff_s[p, i] = fmax(0.0, st.time_to_cutoff_s[p, i] - dt)
        return
    elapsed = st.pred_age_s[p, i]
    st.pred_age_s[p, i] = 0.0
    avg = st.load_avg_a[p, i]
    left_ah = st.shown_soc[p, i] * st.x[p, i, ob.X_CAP]
    st.time_to_go_s[p, i] = left_ah * 3600.0 / avg if avg >= prm.rest_current_a else math.nan
    temp = m.bat.temp_c[p, i]
    temp = temp if math.isfinite(temp) else 25.0
    st.time_to_full_s[p, i] = time_to_full(prm, st, m, p, i, -avg, elapsed, temp)
    raw = time_to_cutoff(prm, st, p, i, avg, temp)
    shown = st.time_to_cutoff_s[p, i]
    if math.isfinite(raw) and math.isfinite(shown):  # the countdown, moved toward the new value
        shown = fmax(0.0, shown - dt)
        raw = shown + fmin(1.0, elapsed / prm.cutoff_tau_s) * (raw - shown)
    st.time_to_cutoff_s[p, i] = raw


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


@kernel_inline
def note_balancer_packs(prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays,
                        cmd: CmdArrays) -> None:  # fmt: skip
    """After the step: the equalizer currents the final commands set (no opinion: as they
    were), clipped to the equalizers' range, for the next period's group current."""
    for p in range(cmd.balancer_set.shape[0]):
        if not cmd.balancer_set[p]:
            continue
        for i in range(st.bal_a.shape[1]):
            for g in range(st.bal_a.shape[2]):
                ib = cmd.balancer_a[p, i, g] if g < cmd.balancer_a.shape[2] else 0.0
                st.bal_a[p, i, g] = fmin(prm.bal_hi_a, fmax(prm.bal_lo_a, ib))


@kernel
def step_packs(
    prm: SocParams, st: SocState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
