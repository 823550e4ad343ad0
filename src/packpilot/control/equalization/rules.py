"""Equalization rules, compiled: the Newton-iterated unit balancing Ah of every series group.

Method of CN102255114A (spec: ``/work/shared/spec/equalization.md``; ``docs/equalization.md``).
Per string (a traction battery = one string of series groups), every sample period:

* ΔV_g = V_avg − V_g (positive = group g lags the string average), V_avg the exactly rounded
  mean (``math.fsum``) of the group voltages;
* ΔV_g > ``dv_set_v`` for ``t1_s`` → AH_g ← (AH_g + N)/2 (formula 1), repeated every further
  ``t1_s`` while the condition persists; ΔV_g < ``dv_set_v`` for ``t2_s`` → AH_g ← AH_g/2
  (formula 2), likewise; equality resets both timers and updates nothing;
* if every AH_g > 0, the minimum is subtracted from all (S41/S42);
* at every AH update of group g (formula 1 or 2 applied, even when the value does not change,
  or the subtraction) its balancing time is recomputed, replacing what remained:
  t_g = 3600·AH_g/I with I the current the equalizer will carry (the string current clamped to
  ``equalizer_max_a``, or the fixed ``fixed_current_a``), clamped to ``max_balance_time_s``.

While t_g > 0 and the gate is open (|I_string| ≥ ``min_current_a``, or always in fixed-current
mode with ``balance_at_rest``) group g's equalizer pushes that current into the group and t_g
counts down (the last partial step prorated). With bidirectional equalizers the string's
currents are shifted by their lower median. A string whose group voltages or current cannot
drive the method is held: equalizers at 0 A, timers and remaining times cleared, AH kept, one
``Fault`` (``FaultCleared`` when valid data returns); an absent battery is held silently.

State is (P, B, G) for the per-group values (G = the most series groups of any battery; a
battery with fewer groups leaves the rest of its row unused) and (P, B) per string.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import claim_balancer, emit, fmax, fmin, put_balancer
from packpilot.jit import kernel

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

EVENT_MIN_CHANGE_AH = 1e-6
"""AH changes smaller than 1 µAh are applied and counted but not emitted as events: halving an
already negligible AH every ``t2_s`` would otherwise flood telemetry for hours."""

SAMPLE_TOL = 1e-9

# Formulas (label indices of the "formula" list in controller.py).
FORMULA1 = 0
FORMULA2 = 1
SUBTRACT_MIN = 2

# Reason codes (rows of the reason table in controller.py).
BALANCING_UPDATED = 0
FAULT_GROUP_COUNT = 1
FAULT_GROUP_VOLTAGE = 2
FAULT_CURRENT = 3
FAULT_CLEARED = 4

# Status channels: ``eq_fault``, then per group k the four channels below at 1 + 4k + j.
ST_FAULT = 0
ST_DV_MV = 0
ST_AH = 1
ST_TIME = 2
ST_I = 3
PER_GROUP = 4


class EqParams(NamedTuple):
    dv_set_v: float
    t1_s: float
    t2_s: float
    n_ah: float
    sample_period_s: float
    fixed_current: bool
    """``time_mode = 'fixed_current'`` (else the equalizer current follows the string's)."""
    min_current_a: float
    equalizer_max_a: float
    fixed_current_a: float
    balance_at_rest: bool
    clamp_s: float
    """Clamp of one balancing time (``max_balance_time_s``, or ``t1_s`` when unset)."""
    bidirectional: bool
    status_groups: int
    """Groups of the status layout: channels ``1 + 4k + j`` for k < this."""


class EqState(NamedTuple):
    ah: F64
    """(P, B, G) unit balancing Ah of each group."""
    hi_timer_s: F64
    """(P, B, G) how long ΔV_g > dv_set has persisted (less the T1 already spent)."""
    lo_timer_s: F64
    """(P, B, G) how long ΔV_g < dv_set has persisted (less the T2 already spent)."""
    remaining_s: F64
    """(P, B, G) balancing time left."""
    dv_v: F64
    """(P, B, G) ΔV of the last sample (NaN after a hold)."""
    current_a: F64
    """(P, B, G) equalizer currents of the last step (after the bidirectional shift)."""
    ledger_time_s: F64
    """(P, B, G) seconds each group's balancing was active (prorated on the last step)."""
    ledger_gross_ah: F64
    """(P, B, G) charge the AH rule commanded into each group: Σ I_eq·time/3600."""
    ledger_net_ah: F64
    """(P, B, G) charge actually commanded (after the median shift): Σ balancer_a·dt/3600."""
    since_sample_s: F64
    """(P, B) time accumulated towards the next sample."""
    faulted: B1
    """(P, B) the inputs were invalid at the last present step."""
    n_formula1: I64
    """(P, B) applications of formula 1 (including those that left AH unchanged)."""
    n_formula2: I64
    n_subtract_min: I64
    """(P, B) samples that subtracted the minimum."""
    partials: F64
    """(P, G) scratch: the partial sums of the exact mean."""
    sort_buf: F64
    """(P, G) scratch: the sorted currents of the bidirectional shift."""
    updated: B1
    """(P, G) scratch: groups whose AH a sample updated."""
    log: F64
    """(P, L, 4) every AH update of the last sample: group, formula, old, new (L may be 0:
    the log is for :func:`~packpilot.control.equalization.sample_groups`)."""
    log_n: I64
    """(P,) updates of the last sample (may exceed L; only L are logged)."""


# --------------------------------------------------------------------------- pure rules


@kernel
def formula1(ah: float, n_ah: float) -> float:
    """Newton-style averaging toward N: AH ← (AH + N)/2."""
    return (ah + n_ah) / 2.0


@kernel
def formula2(ah: float) -> float:
    """Decay: AH ← AH/2."""
    return ah / 2.0


@kernel
def equalizer_current(prm: EqParams, string_current_a: float) -> float:
    """Current one equalizer carries while balancing, or 0 when the gate is closed."""
    mag = abs(string_current_a)
    if prm.fixed_current:
        if mag >= prm.min_current_a or prm.balance_at_rest:
            return prm.fixed_current_a
        return 0.0
    if mag < prm.min_current_a or mag == 0.0:
        return 0.0
    return fmin(mag, prm.equalizer_max_a)


@kernel
def balancing_time(prm: EqParams, ah: float, string_current_a: float) -> float:
    """S43: seconds of balancing that deliver ``ah`` Ah at the equalizer current, clamped to
    ``clamp_s``; zero when the gate is closed."""
    i_eq = equalizer_current(prm, string_current_a)
    if ah <= 0.0 or i_eq <= 0.0:
        return 0.0
    return fmin(3600.0 * ah / i_eq, prm.clamp_s)


@kernel
def exact_sum(xs: F64, n: int, partials: F64) -> float:
    """``math.fsum(xs[:n])`` for finite ``xs`` (CPython's algorithm: Shewchuk's partials, then
    half-even rounding across them); ``partials`` is scratch of at least ``n`` entries. An
    intermediate overflow gives inf where ``math.fsum`` raises."""
    k = 0
    for j in range(n):
        x = xs[j]
        i = 0
        for q in range(k):
            y = partials[q]
            if abs(x) < abs(y):
                x, y = y, x
            hi = x + y
            yr = hi - x
            lo = y - yr
            if lo != 0.0:
                partials[i] = lo
                i += 1
            x = hi
        k = i
        if x != 0.0:
            if not math.isfinite(x):
                return x
            partials[k] = x
            k += 1
    hi = 0.0
    lo = 0.0
    if k > 0:
        k -= 1
        hi = partials[k]
        while k > 0:
            x = hi
            k -= 1
            y = partials[k]
            hi = x + y
            yr = hi - x
            lo = y - yr
            if lo != 0.0:
                break
        if k > 0 and ((lo < 0.0 and partials[k - 1] < 0.0) or (lo > 0.0 and partials[k - 1] > 0.0)):
            y = lo * 2.0
            x = hi + y
            yr = x - hi
            if y == yr:
                hi = x
    return hi


@kernel
def lower_median(xs: F64, n: int, buf: F64) -> float:
    """``sorted(xs[:n])[(n - 1) // 2]``: ties favour not drawing charge from groups; ``buf``
    is scratch of at least ``n`` entries (a stable insertion sort)."""
    for j in range(n):
        x = xs[j]
        q = j
        while q > 0 and x < buf[q - 1]:
            buf[q] = buf[q - 1]
            q -= 1
        buf[q] = x
    return float(buf[(n - 1) // 2])


# --------------------------------------------------------------------------- one string


@kernel
def _updated(
    st: EqState, p: int, i: int, g: int, formula: int, old: float, new: float, t_s: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """Book one application of a rule to group ``g``: counts, log, event."""
    if formula == FORMULA1:
        st.n_formula1[p, i] += 1
    elif formula == FORMULA2:
        st.n_formula2[p, i] += 1
    # Every application counts, even one that leaves AH unchanged: formula 1 at AH = N must
    # re-grant the balancing time of a group that still lags.
    st.updated[p, g] = True
    k = st.log_n[p]
    if k < st.log.shape[1]:
        st.log[p, k, 0] = g
        st.log[p, k, 1] = formula
        st.log[p, k, 2] = old
        st.log[p, k, 3] = new
    st.log_n[p] = k + 1
    if abs(new - old) >= EVENT_MIN_CHANGE_AH:
        e = emit(ev, p, src, BALANCING_UPDATED, i, t_s)
        ev.val[e, 0] = g
        ev.val[e, 1] = formula
        ev.val[e, 2] = old
        ev.val[e, 3] = new
        ev.val[e, 4] = st.dv_v[p, i, g]


@kernel
def sample_string(
    prm: EqParams, st: EqState, m: MeasArrays, p: int, i: int, n: int, ts_s: float,
    current_a: float, ev: EventBuf, src: int,
) -> bool:  # fmt: skip
    """Steps S1-S43 for string ``i`` of pack ``p`` (its ``n`` group voltages are valid):
    ΔV, persistence timers, formula 1/2, subtract-the-minimum, then the balancing time of every
    updated group. ``ts_s`` is the time this sample stands for (zero-order hold): a timer that
    reaches its set time fires and is reduced by it, so a long sample applies the formula
    repeatedly. Returns whether the minimum was subtracted."""
    volts = m.bat.group_v[p, i]
    v_avg = exact_sum(volts, n, st.partials[p]) / n
    st.log_n[p] = 0
    for g in range(n):
        st.updated[p, g] = False
        st.dv_v[p, i, g] = v_avg - volts[g]
    t_s = m.t_s[p]
    for g in range(n):
        dv = st.dv_v[p, i, g]
        if dv > prm.dv_set_v:
            st.hi_timer_s[p, i, g] += ts_s
            st.lo_timer_s[p, i, g] = 0.0
            while st.hi_timer_s[p, i, g] >= prm.t1_s - SAMPLE_TOL:
                old = st.ah[p, i, g]
                st.ah[p, i, g] = formula1(old, prm.n_ah)
                st.hi_timer_s[p, i, g] = fmax(0.0, st.hi_timer_s[p, i, g] - prm.t1_s)
                _updated(st, p, i, g, FORMULA1, old, st.ah[p, i, g], t_s, ev, src)
        elif dv < prm.dv_set_v:
            st.lo_timer_s[p, i, g] += ts_s
            st.hi_timer_s[p, i, g] = 0.0
            while st.lo_timer_s[p, i, g] >= prm.t2_s - SAMPLE_TOL:
                old = st.ah[p, i, g]
                st.ah[p, i, g] = formula2(old)
                st.lo_timer_s[p, i, g] = fmax(0.0, st.lo_timer_s[p, i, g] - prm.t2_s)
                _updated(st, p, i, g, FORMULA2, old, st.ah[p, i, g], t_s, ev, src)
        else:
            st.hi_timer_s[p, i, g] = 0.0
            st.lo_timer_s[p, i, g] = 0.0
    subtracted = n > 0
    for g in range(n):
        if not st.ah[p, i, g] > 0.0:
            subtracted = False
    if subtracted:
        low = st.ah[p, i, 0]
        for g in range(1, n):
            low = fmin(low, st.ah[p, i, g])
        for g in range(n):
            old = st.ah[p, i, g]
            st.ah[p, i, g] = old - low
            _updated(st, p, i, g, SUBTRACT_MIN, old, st.ah[p, i, g], t_s, ev, src)
        st.n_subtract_min[p, i] += 1
    for g in range(n):
        if st.updated[p, g]:
            st.remaining_s[p, i, g] = balancing_time(prm, st.ah[p, i, g], current_a)
    return subtracted


@kernel
def _drive(prm: EqParams, st: EqState, p: int, i: int, n: int, current_a: float, dt: float) -> None:
    """Equalizer currents for the next ``dt`` into ``st.current_a``; counts the remaining
    time down and books the ledger."""
    i_eq = equalizer_current(prm, current_a)
    cur = st.current_a[p, i]
    for g in range(n):
        cur[g] = 0.0
    if i_eq > 0.0 and dt > 0.0:
        for g in range(n):
            used = fmin(st.remaining_s[p, i, g], dt)
            if used <= 0.0:
                continue
            # Prorate the last partial step so that charge = time × current exactly.
            cur[g] = i_eq * used / dt
            st.remaining_s[p, i, g] -= used
            st.ledger_time_s[p, i, g] += used
            st.ledger_gross_ah[p, i, g] += i_eq * used / 3600.0
    if prm.bidirectional and n > 1:
        shift = lower_median(cur, n, st.sort_buf[p])
        for g in range(n):
            cur[g] = cur[g] - shift
    for g in range(n):
        st.ledger_net_ah[p, i, g] += cur[g] * dt / 3600.0


@kernel
def _hold(st: EqState, p: int, i: int) -> None:
    """Forget persistence and pending balancing (invalid inputs or battery absent); AH and
    the fault flag are kept; the equalizers idle."""
    st.hi_timer_s[p, i].fill(0.0)
    st.lo_timer_s[p, i].fill(0.0)
    st.remaining_s[p, i].fill(0.0)
    st.dv_v[p, i].fill(np.nan)
    st.current_a[p, i].fill(0.0)
    st.since_sample_s[p, i] = 0.0


@kernel
def _fault(
    st: EqState, m: MeasArrays, p: int, i: int, code: int, slot1: float, slot2: float,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """Invalid inputs: one event when the fault starts (the source label, then the reason's
    numbers), then hold."""
    if not st.faulted[p, i]:
        e = emit(ev, p, src, code, i, m.t_s[p])
        ev.val[e, 0] = 0.0
        ev.val[e, 1] = slot1
        ev.val[e, 2] = slot2
    st.faulted[p, i] = True
    _hold(st, p, i)


@kernel
def _string(
    prm: EqParams, st: EqState, tp: PackArrays, m: MeasArrays, p: int, i: int, dt: float,
    ev: EventBuf, src: int,
) -> bool:  # fmt: skip
    """One step of string ``i``; returns whether its inputs are faulted."""
    n = int(tp.groups[i])
    if not (m.bat.reported[p, i] and m.bat.present[p, i]):
        _hold(st, p, i)
        return False
    # Only what the method uses is checked (group voltages and string current): a NaN
    # temperature must not stop it.
    got = int(m.bat.n_groups[p, i])
    if got != n:
        _fault(st, m, p, i, FAULT_GROUP_COUNT, float(n), float(got), ev, src)
        return True
    for g in range(n):
        v = m.bat.group_v[p, i, g]
        if not math.isfinite(v) or v <= 0.0:
            _fault(st, m, p, i, FAULT_GROUP_VOLTAGE, float(g), v, ev, src)
            return True
    cur = m.bat.current_a[p, i]
    if not math.isfinite(cur):
        _fault(st, m, p, i, FAULT_CURRENT, cur, np.nan, ev, src)
        return True
    if st.faulted[p, i]:
        st.faulted[p, i] = False
        e = emit(ev, p, src, FAULT_CLEARED, i, m.t_s[p])
        ev.val[e, 0] = 0.0
    st.since_sample_s[p, i] += dt
    if n > 0 and st.since_sample_s[p, i] >= prm.sample_period_s * (1.0 - SAMPLE_TOL):
        ts = st.since_sample_s[p, i]
        st.since_sample_s[p, i] = 0.0
        sample_string(prm, st, m, p, i, n, ts, cur, ev, src)
    _drive(prm, st, p, i, n, cur, dt)
    return False


@kernel
def step_pack(
    prm: EqParams, st: EqState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One step of pack ``p``: every string's equalizer currents (an opinion only where the
    pack has balancers), events, and the status channels."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    nb = st.since_sample_s.shape[1]
    if tp.has_balancers:
        claim_balancer(cmd, p)
    for i in range(nb):
        faulted = _string(prm, st, tp, m, p, i, dt, ev, src)
        n = int(tp.groups[i])
        if tp.has_balancers:
            for g in range(n):
                put_balancer(cmd, p, i, g, st.current_a[p, i, g])
        status[p, i, s0 + ST_FAULT] = 1.0 if faulted else 0.0
        for k in range(prm.status_groups):
            c = s0 + 1 + PER_GROUP * k
            if k < n:
                status[p, i, c + ST_DV_MV] = st.dv_v[p, i, k] * 1000.0
                status[p, i, c + ST_AH] = st.ah[p, i, k]
                status[p, i, c + ST_TIME] = st.remaining_s[p, i, k]
                status[p, i, c + ST_I] = st.current_a[p, i, k]
            else:  # this battery has no group k (None to a reader)
                status[p, i, c + ST_DV_MV] = np.nan
                status[p, i, c + ST_AH] = np.nan
                status[p, i, c + ST_TIME] = np.nan
                status[p, i, c + ST_I] = np.nan


@kernel
def step_packs(
    prm: EqParams, st: EqState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
