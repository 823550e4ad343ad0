"""Staged-charging rules, compiled (``spec/staged_charging.md``).

Tying unequally discharged batteries to the charging busbar at once makes the emptiest one draw
a large current (and the fuller ones discharge into it). Instead, every control period the
traction batteries are sorted and grouped into voltage *levels*; only the lowest level (the
"first batteries") is charged up to just below the next level (S20), then the two lowest levels
are charged together (S30), and so on until all batteries sit on one level, which is then
charged in bounded steps (S40) and finally topped off to V_sat at constant voltage.

Design decisions (the spec's [I]/[REC] points, see ``docs/staged_charging.md``):

* **Voltages "while charging" (spec §7.7)** include the I·R rise, and batteries connected in
  parallel all show the same terminal voltage. Decisions therefore use an IR-compensated
  voltage ``v_est = v + i·R`` (``i`` positive = discharge), with ``R`` learned online from
  current steps (relay closing/opening, setpoint changes): ``R = -ΔV/ΔI`` between consecutive
  samples, filtered. The "battery is full" test uses the raw terminal voltage and the
  termination current, as a CC/CV charger does.
* **Levels** are built on the sorted ``v_est``: a new level starts when a voltage exceeds the
  current level's lowest voltage by more than ``eps_eq``, so a level never spans more than
  ``eps_eq`` (a level closed in parallel circulates at most ``eps_eq / R``).
* **Latching**: each stage keeps its members and setpoints until its own exit condition
  (S20: first batteries reach Vr1; S30: the connected levels merge or reach Vt; S40: reach
  Vr2), or until the grouping changes structurally. Only then is a fresh decision taken, so
  measurement noise cannot toggle relays every period.

The latched plan (stage, the first / second / connected batteries as bool rows, the setpoints)
lives in the state; a new plan is written into the ``new_*`` scratch rows and latched by
:func:`_set_plan`, which reports a ``StageChanged`` when the stage, the connected set or the
charger voltage differ.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import (
    emit,
    fmax,
    fmin,
    put_aux_charge,
    put_aux_relay,
    put_charger,
    put_chg,
    put_dsg,
)
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

# Stages (indices into the "stage" labels, the order of ``Stage`` in controller.py).
IDLE = 0
REST = 1
HOLD = 2
S20 = 3
S30 = 4
S40 = 5
TOP_OFF = 6
COMPLETE = 7
FAULT = 8

# Why a battery is out for the session (the "done" labels).
DONE_NONE = 0
DONE_FULL = 1
DONE_CELL_LIMIT = 2
DONE_OVERVOLTAGE = 3

# Why the stage changed (the "reason" labels): none, undocked, docked, the charger faults.
WHY_NONE = 0
WHY_UNDOCKED = 1
WHY_DOCKED = 2
WHY_LOST = 3
"""No charger status for ``charger_status_timeout_s``."""
WHY_OFFLINE = 4
WHY_FLAGS = 4
"""``WHY_FLAGS + mask``: the charger's raised flags (bit k = ``CHARGER_FLAGS[k]``), mask > 0."""

# Constant texts in event data (the "const" labels).
TXT_NONE = 0
TXT_INVALID = 1
TXT_AUX_INVALID = 2

# Reason codes (rows of the reason table in controller.py).
STAGE_CHANGED = 0
INVALID_MEASUREMENT = 1
AUX_INVALID = 2
CHARGER_FAULT = 3
"""The charger reports offline or a flag (its status in the data)."""
CHARGER_LOST = 4
"""No charger status at all."""
BATTERY_FULL = 5
"""Full or at the cell limit."""
BATTERY_OVERVOLTAGE = 6
CHARGE_COMPLETE = 7

# Status channels, in order.
ST_STAGE = 0
ST_GROUP = 1
ST_RELAY = 2
ST_EST_V = 3
ST_R_OHM = 4
ST_DONE = 5
ST_CMD_V = 6
ST_TARGET_V = 7

# Relay opinion of a step: none (undocked), every relay open, the plan's members closed.
RELAYS_NONE = -1
RELAYS_OPEN = 0
RELAYS_PLAN = 1


class ChargingParams(NamedTuple):
    # battery volts, resolved from the config and the series count (controller.Volts)
    delta_v1: float
    d1: float
    k1: float
    k2: float
    k3: float
    step: float
    delta_v2: float
    eps_eq: float
    reach_tol: float
    v_sat: float
    overvoltage_margin: float
    s40_hysteresis: float
    """Added to ΔV2 in the S40 test (``s40_hysteresis_v``, default 0: the test is exactly ΔV2)."""
    target_saturation: bool
    """``target_mode = "saturation"`` (else "levels")."""
    charger_current_limit_a: float
    has_battery_limit: bool
    battery_current_limit_a: float
    """NaN without a per-battery limit."""
    current_sqrt: bool
    """``current_law = "sqrt"``."""
    full_current_a: float
    """I_full of the sqrt law (the charger limit when unset)."""
    termination_current_a: float
    cell_v_limit_v: float
    r_comp_initial_ohm: float
    r_comp_adapt: bool
    r_est_min_step_a: float
    r_est_gain: float
    r_settle_s: float
    r_settle_max_ratio: float
    r_comp_max_ohm: float
    dock_rest_s: float
    charger_status_timeout_s: float
    charger_fault_clear_s: float
    aux_soc_floor: float
    aux_soc_target: float
    aux_soc_hysteresis: float
    aux_charge_current_a: float
    aux_cv_v: float
    aux_cv_band_v: float
    aux_charge_from_bus: bool
    """Also charge the aux battery undocked (from the traction bus); off by default."""


class ChargingState(NamedTuple):
    # the latched plan
    stage: I64
    """(P,) stage index."""
    members: B1
    """(P, B) batteries connected by the plan."""
    first: B1
    """(P, B) the first batteries (lowest level)."""
    second: B1
    """(P, B) the second batteries (next level)."""
    cmd_v: F64
    """(P,) charger voltage of the plan (NaN: none)."""
    vr1_v: F64
    vt_v: F64
    vr2_v: F64
    # resistance estimate
    r_ohm: F64
    """(P, B)."""
    r_kind: I64
    """(P, B): 0 = no estimate yet, 1 = from a step, 2 = settled (incl. polarization)."""
    ref_on: B1
    """(P, B): a current step is being followed for the settled estimate (``StepRef``)."""
    ref_v0: F64
    ref_i0: F64
    ref_i1: F64
    ref_t1: F64
    ref_r_step: F64
    ref_v_mid: F64
    clock_s: F64
    """(P,)."""
    prev_v: F64
    """(P, B)."""
    prev_i: F64
    # the session
    done: I64
    """(P, B) why the battery is out for this session (``DONE_*``); cleared on undocking."""
    invalid: B1
    """(P, B) left out for a non-finite reading."""
    no_status_s: F64
    """(P,)."""
    fault_clear_s: F64
    charger_fault: I64
    """(P,) the charger fault being reported (a ``WHY_*`` label, 0: none)."""
    session_s: F64
    rested: B1
    aux_charging: B1
    aux_invalid: B1
    # scratch of one step
    valid: B1
    """(P, B)."""
    est: F64
    """(P, B) IR-compensated voltage (NaN where not valid)."""
    r_use: F64
    """(P, B) resistance used for the compensation."""
    elig: B1
    """(P, B) valid and not done."""
    new_members: B1
    """(P, B) the plan being decided ..."""
    new_first: B1
    new_second: B1
    sort_v: F64
    """(P, B) cluster input: voltages ..."""
    sort_i: I64
    """... and battery indices ..."""
    order: I64
    """... positions in sorted order ..."""
    level: I64
    """... and the level of each sorted position."""


# ------------------------------------------------------------------------------ helpers



@kernel_inline
def _set_row(dst: Any, p: int, src: Any) -> None:
    """``dst[p, :] = src`` element by element: a slice assignment may allocate a temporary
    (numba guards against overlap), and the core's kernels run without an allocator."""
    for i in range(src.shape[0]):
        dst[p, i] = src[i]

@kernel_inline
def stage_current(
    limit_a: float, sqrt_law: bool, full_a: float, has_battery_limit: bool,
    battery_limit_a: float, n_connected: int, n_to_charge: int,
) -> float:  # fmt: skip
    """Charger current limit for a stage with ``n_connected`` of ``n_to_charge`` batteries.

    Always ``≤ limit_a`` and, with a per-battery limit, ``≤ n_connected × battery_limit_a``.
    With the square-root law also ``≤ I_full·sqrt(n_connected / n_to_charge)``: a stage
    that delivers charge Q through n similar batteries of resistance R at current I heats them
    by ≈ Q·I·R/n in Q/I seconds, and minimising Σ Q_k·I_k·R/n_k for a fixed Σ Q_k/I_k
    (Lagrange) gives I_k ∝ sqrt(n_k): the same heat rate I_k²·R/n_k in every stage.
    """
    current = limit_a
    n = n_connected if n_connected > 1 else 1
    if sqrt_law:
        total = n_to_charge if n_to_charge > n else n
        current = fmin(current, full_a * math.sqrt(n / total))
    if has_battery_limit:
        current = fmin(current, n * battery_limit_a)
    return current


@kernel_inline
def cluster(vals: F64, keys: I64, count: int, eps_v: float, order: I64, level: I64) -> int:
    """Group the first ``count`` entries of ``vals`` into levels of span ≤ ``eps_v``.

    Sorted by voltage, then by ``keys`` (a stable insertion sort of positions into ``order``);
    ``level[k]`` is the level of the k-th sorted entry, lowest level 0. A level is anchored
    at its lowest voltage (not single-linkage), so a chain of small gaps cannot grow one level
    wider than ``eps_v``. Returns the number of levels.
    """
    for k in range(count):
        j = k
        v, key = vals[k], keys[k]
        while j > 0:
            o = order[j - 1]
            if vals[o] < v or (vals[o] == v and keys[o] < key):
                break
            order[j] = o
            j -= 1
        order[j] = k
    n_levels = 0
    anchor = -math.inf
    for k in range(count):
        v = vals[order[k]]
        if n_levels == 0 or v - anchor > eps_v:
            n_levels += 1
            anchor = v
        level[k] = n_levels - 1
    return n_levels


@kernel_inline
def _mask(row: B1) -> float:
    """A bool row as the bit mask of an ``m`` field."""
    bits = 0
    for i in range(row.shape[0]):
        if row[i]:
            bits |= 1 << i
    return float(bits)


@kernel_inline
def _target_v(stage: int, cmd_v: float, vr1_v: float, vt_v: float, vr2_v: float) -> float:
    """The voltage a stage charges towards (telemetry)."""
    if stage == S20:
        return vr1_v
    if stage == S30:
        return vt_v
    if stage == S40:
        return vr2_v
    if stage == TOP_OFF:
        return cmd_v
    return math.nan


# ------------------------------------------------------------------------------ plans
# A call that passes the state (or the measurements) costs about a microsecond of reference
# counting, so the per-period rules are written inline in ``step_pack``; what only runs when
# the plan changes (decide afresh, latch, report) is in functions.


@kernel_inline
def _set_plan(
    st: ChargingState, p: int, stage: int, cmd_v: float, vr1_v: float, vt_v: float,
    vr2_v: float, why: int, ev: EventBuf, src: int, t_s: float,
) -> None:  # fmt: skip
    """Latch the plan in the ``new_*`` rows; ``StageChanged`` when the stage, the connected
    batteries or the charger voltage differ from the latched plan."""
    same = stage == st.stage[p] and (
        (math.isnan(cmd_v) and math.isnan(st.cmd_v[p])) or cmd_v == st.cmd_v[p]
    )
    if same:
        for i in range(st.members.shape[1]):
            if st.members[p, i] != st.new_members[p, i]:
                same = False
                break
    if not same:
        k = emit(ev, p, src, STAGE_CHANGED, -1, t_s)
        ev.val[k, 0] = stage
        ev.val[k, 1] = st.stage[p]
        ev.val[k, 2] = _mask(st.new_first[p])
        ev.val[k, 3] = _mask(st.new_second[p])
        ev.val[k, 4] = _mask(st.new_members[p])
        ev.val[k, 5] = vr1_v
        ev.val[k, 6] = vt_v
        ev.val[k, 7] = vr2_v
        ev.val[k, 8] = cmd_v
        ev.val[k, 9] = why
    st.stage[p] = stage
    _set_row(st.members, p, st.new_members[p])
    _set_row(st.first, p, st.new_first[p])
    _set_row(st.second, p, st.new_second[p])
    st.cmd_v[p] = cmd_v
    st.vr1_v[p] = vr1_v
    st.vt_v[p] = vt_v
    st.vr2_v[p] = vr2_v


@kernel_inline
def _set_simple(
    st: ChargingState, p: int, stage: int, why: int, ev: EventBuf, src: int, t_s: float
) -> None:
    """Latch a plan that connects nothing (idle, rest, hold, complete, fault)."""
    st.new_members[p].fill(False)
    st.new_first[p].fill(False)
    st.new_second[p].fill(False)
    _set_plan(st, p, stage, math.nan, math.nan, math.nan, math.nan, why, ev, src, t_s)


@kernel_inline
def _set_top_off(prm: ChargingParams, st: ChargingState, p: int, ev: EventBuf, src: int,
                 t_s: float) -> None:  # fmt: skip
    """Latch a kept top-off: every eligible battery, no first / second, at V_sat."""
    _set_row(st.new_members, p, st.elig[p])
    st.new_first[p].fill(False)
    st.new_second[p].fill(False)
    _set_plan(st, p, TOP_OFF, prm.v_sat, math.nan, math.nan, math.nan, WHY_NONE, ev, src, t_s)


@kernel_inline
def _join_ok(st: ChargingState, p: int, v_ref: float, cmd_v: float, i_stage_a: float) -> float:
    """Takes out of the plan in the ``new_*`` rows every battery whose relay it would close
    although that battery would not be *charged* once closed (issue #24 item 3); returns the
    highest IR-compensated voltage of those (−inf: every join is fit). Batteries already
    connected stay.

    The plan's bus is predicted as it settles with the charger in current limit:
    (I + Σ v_est_k/R_k) / (Σ 1/R_k) over the plan's batteries, capped at ``cmd_v`` (in voltage
    limit the bus is held there), with v_est the IR-compensated (rest) voltages and R the
    learned, settled resistances; a closing battery is charged iff its v_est is at most that.
    The highest unfit battery waits and the rest are predicted again. The bus measured now
    (``v_ref``, the charging batteries' terminal voltage) is *not* the test: it carries their
    RC polarization, which decays once the current is shared, and a battery that joined on it
    (96/96.4/97 V at 20 A) discharged at up to 10 A for 80 s as it did. Without a learned R the
    measured bus is used, and with nothing charging either only the lowest batteries (ties
    within 1 mV) close; the others join from the next periods' estimates.
    """
    n = st.elig.shape[1]
    est, r_use = st.est[p], st.r_use[p]
    worst = -math.inf
    lo = math.inf
    known = True
    for i in range(n):
        if st.new_members[p, i]:
            lo = fmin(lo, est[i])
            known = known and r_use[i] > 0.0
    while True:
        g = 0.0
        x = i_stage_a
        hi = -math.inf
        top = -1
        for i in range(n):
            if st.new_members[p, i]:
                if known:
                    g += 1.0 / r_use[i]
                    x += est[i] / r_use[i]
                if not st.members[p, i] and est[i] > hi:
                    hi = est[i]
                    top = i
        if known and g > 0.0:
            bus = fmin(cmd_v, x / g)
        elif not math.isnan(v_ref):
            bus = v_ref
        else:
            bus = lo + 1e-3
        if top < 0 or hi <= bus:
            return worst
        st.new_members[p, top] = False
        worst = fmax(worst, hi)


@kernel_inline
def _fresh(prm: ChargingParams, st: ChargingState, p: int, ev: EventBuf, src: int,
           t_s: float, v_ref: float, plan_ok: bool, n_elig: int) -> None:  # fmt: skip
    """Decide afresh from the levels of the eligible batteries (non-empty), and latch it,
    unless a relay it would close is unfit (:func:`_join_ok`): then a latched plan that is
    still whole keeps running (it raises the bus towards the waiting battery), else the plan
    is latched without the unfit batteries."""
    n = st.elig.shape[1]
    est = st.est[p]
    count = 0
    for i in range(n):
        if st.elig[p, i]:
            st.sort_v[p, count] = est[i]
            st.sort_i[p, count] = i
            count += 1
    order, level, idx = st.order[p], st.level[p], st.sort_i[p]
    n_levels = cluster(st.sort_v[p], idx, count, prm.eps_eq, order, level)
    st.new_members[p].fill(False)
    st.new_first[p].fill(False)
    st.new_second[p].fill(False)
    stage = S30
    vr1 = math.nan
    vt = math.nan
    vr2 = math.nan
    if n_levels == 1:
        vp = math.nan
        for k in range(count):
            i = idx[order[k]]
            st.new_members[p, i] = True
            st.new_first[p, i] = True
        for i in range(n):  # min over the members in index order (Python's frozenset order)
            if st.new_members[p, i]:
                vp = est[i] if math.isnan(vp) else fmin(vp, est[i])
        v_at = vp
        if st.stage[p] == S40 and vp >= st.vr2_v[p] - prm.reach_tol:
            # the S40 step just ended by reaching Vr2 (within reach_tol: CV only approaches
            # it): the batteries are at Vr2 for the S40 test, which is exactly ΔV2 from there
            v_at = fmax(vp, st.vr2_v[p])
        elif st.stage[p] == S30 and vp >= st.vt_v[p] - prm.reach_tol:
            v_at = fmax(vp, st.vt_v[p])  # likewise an S30 that ended by reaching its Vt
        if prm.v_sat - v_at > prm.delta_v2 + prm.s40_hysteresis:  # S40 [T]: V_sat − V > ΔV2
            stage = S40
            vr2 = fmin(prm.v_sat, vp + prm.delta_v2)
            cmd_v = fmin(prm.v_sat, vr2 + prm.k3)
        else:
            stage = TOP_OFF
            cmd_v = prm.v_sat
    else:
        v1 = math.nan
        v2 = math.nan
        for k in range(count):
            i = idx[order[k]]
            lv = level[k]
            if lv == 0:
                st.new_first[p, i] = True
                st.new_members[p, i] = True
                v1 = est[i] if math.isnan(v1) else fmax(v1, est[i])
            elif lv == 1:
                st.new_second[p, i] = True
                st.new_members[p, i] = True
                v2 = est[i] if math.isnan(v2) else fmin(v2, est[i])
        vr1 = v2 - prm.d1
        if v1 < vr1:
            stage = S20
            _set_row(st.new_members, p, st.new_first[p])
            cmd_v = fmin(prm.v_sat, vr1 + prm.k1)
        else:
            # S30 [T]: Vt "according to the second battery voltage" (issue #24 item 4):
            # V2 + step_v (example 1: 90 -> 100 V, example 3: 90 -> 100, then 100 -> 110 V);
            # 'saturation' mode: V_sat once no third level is left (example 4: 120 V)
            vt = v2 + prm.step
            if prm.target_saturation and n_levels < 3:
                vt = prm.v_sat
            vt = fmin(vt, prm.v_sat)
            cmd_v = fmin(prm.v_sat, vt + prm.k2)
    n_new = 0
    for i in range(n):
        n_new += 1 if st.new_members[p, i] else 0
    i_stage = stage_current(
        prm.charger_current_limit_a, prm.current_sqrt, prm.full_current_a,
        prm.has_battery_limit, prm.battery_current_limit_a, n_new, n_elig,
    )  # fmt: skip
    worst = _join_ok(st, p, v_ref, cmd_v, i_stage)
    if worst > -math.inf and plan_ok and st.cmd_v[p] > worst:
        adds = False
        for i in range(n):
            adds = adds or (st.new_members[p, i] and not st.members[p, i])
        if not adds:
            return  # the latched plan goes on charging: its bus rises towards the waiting one
    # else latch the plan without the unfit batteries (they join from a later decision: each
    # is within eps_eq of the connected level, or the latched plan could not go on or could
    # not lift the bus above it)
    _set_plan(st, p, stage, cmd_v, vr1, vt, vr2, WHY_NONE, ev, src, t_s)


@kernel_inline
def _charger_event(m: MeasArrays, p: int, fault: int, ev: EventBuf, src: int) -> None:
    """``Fault`` "charger: ...", with the charger's status (or none)."""
    c = m.charger
    if c.reported[p]:
        k = emit(ev, p, src, CHARGER_FAULT, -1, m.t_s[p])
        ev.val[k, 0] = fault
        ev.val[k, 1] = 1.0 if c.online[p] else 0.0
        ev.val[k, 2] = c.output_v[p]
        ev.val[k, 3] = c.output_a[p]
        for j in range(c.flags.shape[1]):
            ev.val[k, 4 + j] = 1.0 if c.flags[p, j] else 0.0
    else:
        k = emit(ev, p, src, CHARGER_LOST, -1, m.t_s[p])
        ev.val[k, 0] = fault
        ev.val[k, 1] = TXT_NONE


# ------------------------------------------------------------------------------ the period


@kernel_inline
def step_pack(
    prm: ChargingParams, st: ChargingState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One control period of pack ``p``. Never raises on bad measurements: a battery with a
    non-finite reading is left out of the sort with its relay open (``Fault`` once); charger
    faults stop the charger and open every relay until the charger has reported healthy for
    ``charger_fault_clear_s``."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    t = m.t_s[p]
    n = st.valid.shape[1]
    bat = m.bat
    volt, amps = bat.voltage_v[p], bat.current_a[p]
    valid, est, r_use = st.valid[p], st.est[p], st.r_use[p]

    # -- validity: a present battery with a non-finite reading is left out (Fault once)
    for i in range(n):
        here = bat.reported[p, i] and bat.present[p, i]
        ok = (
            here
            and math.isfinite(volt[i])
            and math.isfinite(amps[i])
            and math.isfinite(bat.temp_c[p, i])
            and math.isfinite(bat.min_cell_v[p, i])
            and math.isfinite(bat.max_cell_v[p, i])
            and math.isfinite(bat.soc[p, i])
        )
        for g in range(min(bat.n_groups[p, i], bat.group_v.shape[2])):
            ok = ok and math.isfinite(bat.group_v[p, i, g])
        valid[i] = ok
        bad = here and not ok
        if bad and not st.invalid[p, i]:
            k = emit(ev, p, src, INVALID_MEASUREMENT, i, t)
            ev.val[k, 0] = TXT_INVALID
        st.invalid[p, i] = bad
    st.clock_s[p] += dt

    # -- resistance from current steps (V = OCV − I·R, I positive = discharge). Two
    # estimates of R = −ΔV/ΔI. Across the step itself (one period): mostly the ohmic R0,
    # available at once. Settled: if the current then holds steady for two windows of
    # r_settle_s, R = −(V(T) − V(0) − (V(2T) − V(T))) / ΔI — the voltage change to the end
    # of the first window includes the RC polarization (what separates a charging battery's
    # terminal voltage from its rest voltage) plus the OCV drift of the charge delivered
    # meanwhile, and the second window, with the polarization nearly settled, measures that
    # drift. The settled value is accepted only within [1, r_settle_max_ratio] × the step
    # value and, once known, is the one used.
    r_ohm, r_kind = st.r_ohm[p], st.r_kind[p]
    for i in range(n):
        if not valid[i]:
            st.prev_v[p, i] = math.nan
            st.prev_i[p, i] = math.nan
            st.ref_on[p, i] = False
            continue
        v, cur = volt[i], amps[i]
        di = cur - st.prev_i[p, i]
        if prm.r_comp_adapt and math.isfinite(di) and abs(di) >= prm.r_est_min_step_a:
            r_step = -(v - st.prev_v[p, i]) / di
            if 0.0 <= r_step <= prm.r_comp_max_ohm:
                if r_kind[i] < 2:
                    gain = prm.r_est_gain if r_kind[i] == 1 else 1.0  # first: take it
                    r_ohm[i] += gain * (r_step - r_ohm[i])
                    r_kind[i] = 1
                st.ref_on[p, i] = True
                st.ref_v0[p, i] = st.prev_v[p, i]
                st.ref_i0[p, i] = st.prev_i[p, i]
                st.ref_i1[p, i] = cur
                st.ref_t1[p, i] = st.clock_s[p]
                st.ref_r_step[p, i] = r_step
                st.ref_v_mid[p, i] = math.nan
            else:
                st.ref_on[p, i] = False
        if prm.r_comp_adapt and prm.r_settle_s > 0.0 and st.ref_on[p, i]:
            i0, i1 = st.ref_i0[p, i], st.ref_i1[p, i]
            elapsed = st.clock_s[p] - st.ref_t1[p, i]
            if abs(cur - i1) > fmax(0.1 * abs(i1 - i0), 0.5 * prm.r_est_min_step_a):
                st.ref_on[p, i] = False  # the current moved on: no clean settled response
            elif math.isnan(st.ref_v_mid[p, i]):
                if elapsed >= prm.r_settle_s:
                    st.ref_v_mid[p, i] = v
            elif elapsed >= 2.0 * prm.r_settle_s:
                st.ref_on[p, i] = False
                v_mid, r_step = st.ref_v_mid[p, i], st.ref_r_step[p, i]
                r_new = -((v_mid - st.ref_v0[p, i]) - (v - v_mid)) / (i1 - i0)
                if r_step <= r_new <= fmin(prm.r_settle_max_ratio * r_step, prm.r_comp_max_ohm):
                    gain = prm.r_est_gain if r_kind[i] == 2 else 1.0
                    r_ohm[i] += gain * (r_new - r_ohm[i])
                    r_kind[i] = 2
        st.prev_v[p, i] = v
        st.prev_i[p, i] = cur

    # -- R for the compensation: own estimate once learned; before that the mean of the
    # learned ones (batteries of one pack are alike), else r_comp_initial_ohm. A battery
    # that joins a running group may see too small a current step to learn from, yet
    # already carries current.
    best = r_kind[0]
    for i in range(1, n):
        if r_kind[i] > best:
            best = r_kind[i]
    total = 0.0
    count = 0
    for i in range(n):
        if r_kind[i] == best and best > 0:
            total += r_ohm[i]
            count += 1
    fallback = total / count if count > 0 else prm.r_comp_initial_ohm
    for i in range(n):
        r_use[i] = r_ohm[i] if r_kind[i] == best and best > 0 else fallback
        est[i] = volt[i] + amps[i] * r_use[i] if valid[i] else math.nan

    # -- aux: an independent channel, charged from the dock (to the target, and always when
    # below the floor); undocked only with aux_charge_from_bus (below the floor, from the
    # traction bus). Relay -1: no opinion
    aux_relay = -1
    aux_a = math.nan
    if tp.has_aux and m.has_aux[p]:
        a = m.aux
        aux_ok = (
            math.isfinite(a.voltage_v[p, 0])
            and math.isfinite(a.current_a[p, 0])
            and math.isfinite(a.temp_c[p, 0])
            and math.isfinite(a.min_cell_v[p, 0])
            and math.isfinite(a.max_cell_v[p, 0])
            and math.isfinite(a.soc[p, 0])
        )
        for g in range(min(a.n_groups[p, 0], a.group_v.shape[2])):
            aux_ok = aux_ok and math.isfinite(a.group_v[p, 0, g])
        if not aux_ok:
            if not st.aux_invalid[p]:
                k = emit(ev, p, src, AUX_INVALID, -1, t)
                ev.val[k, 0] = TXT_AUX_INVALID
            st.aux_invalid[p] = True
            st.aux_charging[p] = False
            aux_relay, aux_a = 0, 0.0
        else:
            st.aux_invalid[p] = False
            soc = a.soc[p, 0]
            if m.docked[p]:
                stop_at = prm.aux_soc_target
                start_below = prm.aux_soc_target - prm.aux_soc_hysteresis
            elif prm.aux_charge_from_bus:
                stop_at = prm.aux_soc_floor + prm.aux_soc_hysteresis
                start_below = prm.aux_soc_floor
            else:  # the source charges battery 230 from the dock only
                stop_at = -math.inf
                start_below = -math.inf
            if st.aux_charging[p]:
                st.aux_charging[p] = soc < stop_at
            else:
                st.aux_charging[p] = soc < start_below or (
                    soc < prm.aux_soc_floor and start_below > -math.inf
                )
            if st.aux_charging[p]:
                taper = fmin(1.0, fmax(0.0, (prm.aux_cv_v - a.voltage_v[p, 0]) / prm.aux_cv_band_v))
                aux_relay, aux_a = 1, prm.aux_charge_current_a * taper
            else:
                aux_relay, aux_a = 0, 0.0

    # -- the traction decision: relays (-1: no opinion, 0: all open, 1: the plan's members)
    # and the charger setpoint
    relays = RELAYS_OPEN
    ch_v, ch_a, ch_on = 0.0, 0.0, False
    if not m.docked[p]:
        if st.stage[p] != IDLE:
            _set_simple(st, p, IDLE, WHY_UNDOCKED, ev, src, t)
        st.done[p].fill(DONE_NONE)  # the session ends
        st.no_status_s[p] = 0.0
        st.fault_clear_s[p] = 0.0
        st.charger_fault[p] = WHY_NONE
        st.session_s[p] = 0.0
        st.rested[p] = False
        relays = RELAYS_NONE
    else:
        if st.stage[p] != IDLE:
            st.session_s[p] += dt  # the first docked period starts the session clock at 0
        # charger health: WHY_NONE when usable, else why not
        fault = WHY_NONE
        if not m.charger.reported[p]:
            st.no_status_s[p] += dt
            if st.no_status_s[p] >= prm.charger_status_timeout_s:
                fault = WHY_LOST
        else:
            st.no_status_s[p] = 0.0
            if not m.charger.online[p]:
                fault = WHY_OFFLINE
            else:
                bits = 0
                for j in range(m.charger.flags.shape[1]):
                    if m.charger.flags[p, j]:
                        bits |= 1 << j
                if bits:
                    fault = WHY_FLAGS + bits
        go = True  # on to the traction decision
        complete = False  # charging complete: the dock only feeds the aux DC/DC
        if fault != WHY_NONE:
            if st.stage[p] != FAULT or fault != st.charger_fault[p]:
                _charger_event(m, p, fault, ev, src)
            st.charger_fault[p] = fault
            st.fault_clear_s[p] = 0.0
            if st.stage[p] != FAULT:
                _set_simple(st, p, FAULT, fault, ev, src, t)
            go = False
        elif st.stage[p] == FAULT:
            st.fault_clear_s[p] += dt
            if st.fault_clear_s[p] < prm.charger_fault_clear_s:
                go = False
            else:
                st.charger_fault[p] = WHY_NONE  # the fresh decision is reported as a change
        if go and st.stage[p] == COMPLETE:
            go = False
            complete = True
        if go and not st.rested[p]:
            if st.stage[p] != REST:
                _set_simple(st, p, REST, WHY_DOCKED, ev, src, t)
            st.rested[p] = st.session_s[p] >= prm.dock_rest_s
            go = st.rested[p]
        if go:
            relays = RELAYS_PLAN
            # battery limits: latch out batteries that are full, hit the cell limit or are
            # over-voltage
            for i in range(n):
                if not valid[i] or st.done[p, i] != DONE_NONE:
                    continue
                v, cur, cell = volt[i], amps[i], bat.max_cell_v[p, i]
                reason = DONE_NONE
                if cell >= prm.cell_v_limit_v:
                    reason = DONE_CELL_LIMIT
                elif v >= prm.v_sat + prm.overvoltage_margin:
                    reason = DONE_OVERVOLTAGE
                elif v >= prm.v_sat - prm.reach_tol and -cur <= prm.termination_current_a:
                    reason = DONE_FULL
                if reason == DONE_NONE:
                    continue
                st.done[p, i] = reason
                code = BATTERY_OVERVOLTAGE if reason == DONE_OVERVOLTAGE else BATTERY_FULL
                k = emit(ev, p, src, code, i, t)
                ev.val[k, 0] = reason
                ev.val[k, 1] = v
                ev.val[k, 2] = cur
                ev.val[k, 3] = cell
            elig = st.elig[p]
            n_elig = 0
            n_done = 0
            for i in range(n):
                elig[i] = valid[i] and st.done[p, i] == DONE_NONE
                n_elig += 1 if elig[i] else 0
                n_done += 1 if st.done[p, i] != DONE_NONE else 0
            # keep the latched plan while its exit condition is unmet, else decide afresh
            stage = st.stage[p]
            keep = False
            if n_elig == 0:
                simple = COMPLETE if n_done > 0 else HOLD
                if stage != simple:
                    _set_simple(st, p, simple, WHY_NONE, ev, src, t)
            elif stage == TOP_OFF:
                lo = math.inf
                hi = -math.inf
                for i in range(n):
                    if elig[i]:
                        hi = est[i] if hi == -math.inf else fmax(hi, est[i])
                        lo = est[i] if lo == math.inf else fmin(lo, est[i])
                keep = hi - lo <= prm.delta_v1
            elif stage in (S20, S30, S40):
                keep = True
                lo = math.inf
                hi = -math.inf
                for i in range(n):
                    if st.members[p, i]:
                        keep = keep and elig[i]  # a connected battery dropped out: regroup
                        hi = est[i] if hi == -math.inf else fmax(hi, est[i])
                        lo = est[i] if lo == math.inf else fmin(lo, est[i])
                # another battery at or below the connected level: regroup. An S30 does so
                # once its batteries are within d1 of the next level, i.e. at that pair's Vr1,
                # where the next stage's S20 would end (its charge to Vt goes past the next
                # level; met only within eps_eq, the levels merge and the stage after is an
                # S40 step instead of the source's S30 of example 3/4's stage 2)
                near = fmax(prm.eps_eq, prm.d1) if stage == S30 else 0.0
                for i in range(n):
                    if elig[i] and not st.members[p, i] and (
                        est[i] <= hi + prm.eps_eq or est[i] <= hi + near
                    ):
                        keep = False
                if keep and stage == S20:
                    keep = lo < st.vr1_v[p]
                elif keep and stage == S30:
                    # S30 [T] charges the first and second batteries until both reach Vt: the
                    # merge of the two groups is no exit (issue #24 item 4; until then
                    # 'levels' mode re-grouped at the merge and never reached Vt)
                    keep = lo < st.vt_v[p] - prm.reach_tol
                elif keep:
                    keep = lo < st.vr2_v[p] - prm.reach_tol and hi - lo <= prm.delta_v1
            if n_elig == 0:
                pass
            elif keep and stage == TOP_OFF:
                # a kept top-off follows the eligible set, with no first / second batteries
                changed = False
                for i in range(n):
                    changed = changed or st.members[p, i] != elig[i] or st.first[p, i]
                    changed = changed or st.second[p, i]
                if changed:
                    _set_top_off(prm, st, p, ev, src, t)
            elif not keep:
                # the bus voltage measured now, if the latched plan is charging: the highest
                # terminal voltage of its charging batteries (the bus less a relay's drop)
                v_ref = math.nan
                plan_ok = stage in (S20, S30, S40, TOP_OFF)
                for i in range(n):
                    if st.members[p, i]:
                        plan_ok = plan_ok and elig[i]
                        if valid[i] and amps[i] < 0.0:
                            v_ref = volt[i] if math.isnan(v_ref) else fmax(v_ref, volt[i])
                _fresh(prm, st, p, ev, src, t, v_ref, plan_ok, n_elig)
            if st.stage[p] == COMPLETE:
                k = emit(ev, p, src, CHARGE_COMPLETE, -1, t)
                ev.val[k, 0] = st.session_s[p]
                ev.val[k, 1] = n_done
                complete = True
            n_members = 0
            for i in range(n):
                n_members += 1 if st.members[p, i] else 0
            if n_members > 0:
                ch_v = st.cmd_v[p]
                ch_a = stage_current(
                    prm.charger_current_limit_a, prm.current_sqrt, prm.full_current_a,
                    prm.has_battery_limit, prm.battery_current_limit_a, n_members, n_elig,
                )  # fmt: skip
                ch_on = True
        if complete and aux_relay == 1:
            # traction charging done: the dock stays on (every traction relay open) only
            # while the aux battery is still charging, since its DC/DC draws from the dock
            ch_v, ch_a, ch_on = prm.v_sat, prm.charger_current_limit_a, True

    # -- the opinions and the status channels
    target_v = _target_v(st.stage[p], st.cmd_v[p], st.vr1_v[p], st.vt_v[p], st.vr2_v[p])
    for i in range(n):
        if relays == RELAYS_NONE:
            relay = -1
        elif relays == RELAYS_OPEN:
            relay = 0
        else:
            relay = 1 if st.members[p, i] else 0
        if relay >= 0:
            put_chg(cmd, p, i, relay == 1)
            put_dsg(cmd, p, i, relay == 1)
        if st.done[p, i] != DONE_NONE or st.invalid[p, i]:
            group = -1
        elif st.first[p, i]:
            group = 1
        elif st.second[p, i]:
            group = 2
        else:
            group = 0
        row = status[p, i]
        row[s0 + ST_STAGE] = st.stage[p]
        row[s0 + ST_GROUP] = group
        row[s0 + ST_RELAY] = relay
        row[s0 + ST_EST_V] = est[i]
        row[s0 + ST_R_OHM] = r_use[i]
        row[s0 + ST_DONE] = st.done[p, i]
        row[s0 + ST_CMD_V] = ch_v if ch_on else 0.0
        row[s0 + ST_TARGET_V] = target_v
    put_charger(cmd, p, ch_v, ch_a, ch_on)
    if aux_relay >= 0:
        put_aux_relay(cmd, p, aux_relay == 1)
        put_aux_charge(cmd, p, aux_a)


@kernel
def step_packs(
    prm: ChargingParams, st: ChargingState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
