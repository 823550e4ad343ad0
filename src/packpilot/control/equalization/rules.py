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
  or the subtraction) the group is granted AH_g (S43): its **owed Ah** becomes AH_g
  (``granted`` books the change). Formula 1 raises it, so a balance the equalizer's current
  limit cannot deliver before the next update is carried over, not dropped (issue #15; the
  spec's [REC] clamped the time to the update period, which dropped it); formula 2 and the
  subtraction lower it with AH (issue #24: the charge still to deliver falls with AH);
* a group at or above the string average (ΔV_g <= 0) receives nothing: its owed Ah waits.

While Ah is owed, the group lags (ΔV_g > 0) and the gate is open (|I_string| ≥
``min_current_a``, or always in fixed-current mode with ``balance_at_rest``) group g's
equalizer carries the current I (the string current clamped to ``equalizer_max_a``, or the
fixed ``fixed_current_a``) and the owed Ah drops by I·dt (the last partial step prorated):
the balancing time is 3600·AH/I, from AH and the battery current (S43). With bidirectional
equalizers the string's currents are shifted by their lower median. A string whose group
voltages or current cannot drive the method is held: equalizers at 0 A, timers cleared, AH
and owed Ah kept, one ``Fault`` (``FaultCleared`` when valid data returns); an absent battery
is held silently.

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

EVENT_RESOLUTION_AH = 1e-4
"""Resolution of ``BalancingUpdated`` (0.1 mAh, the precision its message prints): an AH update
is emitted only when it changes AH by more than this. Smaller changes (re-applying formula 1 at
AH = N, halving an AH that is already ≈ 0 every ``t2_s``) are applied and counted but not
emitted: they rendered as "AH 0.0000 -> 0.0000"."""

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

# Status channels: ``eq_fault``, then per group k the five channels below at 1 + 5k + j.
ST_FAULT = 0
ST_DV_MV = 0
ST_AH = 1
ST_TIME = 2
ST_I = 3
ST_OWED = 4
PER_GROUP = 5


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
    bidirectional: bool
    status_groups: int
    """Groups of the status layout: channels ``1 + 5k + j`` for k < this."""


class EqState(NamedTuple):
    ah: F64
    """(P, B, G) unit balancing Ah of each group."""
    hi_timer_s: F64
    """(P, B, G) how long ΔV_g > dv_set has persisted (less the T1 already spent)."""
    lo_timer_s: F64
    """(P, B, G) how long ΔV_g < dv_set has persisted (less the T2 already spent)."""
    owed_ah: F64
    """(P, B, G) charge granted to each group and not yet delivered (carried over)."""
    remaining_s: F64
    """(P, B, G) time to deliver the owed Ah at the equalizer's present current (while the gate
    is closed: at its nominal current, ``fixed_current_a`` or ``equalizer_max_a``)."""
    dv_v: F64
    """(P, B, G) ΔV of the last sample (NaN after a hold)."""
    current_a: F64
    """(P, B, G) equalizer currents of the last step (after the bidirectional shift)."""
    ledger_time_s: F64
    """(P, B, G) seconds each group's balancing was active (prorated on the last step)."""
    ledger_granted_ah: F64
    """(P, B, G) charge granted by S43: Σ of the changes of the owed Ah at the updates (raises
    by formula 1, cuts by formula 2 and the subtraction; = delivered + owed)."""
    ledger_gross_ah: F64
    """(P, B, G) charge the AH rule delivered into each group: Σ I_eq·time/3600."""
    ledger_net_ah: F64
    """(P, B, G) charge actually commanded (after the median shift): Σ balancer_a·dt/3600."""
    since_sample_s: F64
    """(P, B) time accumulated towards the next sample."""
    faulted: B1
    """(P, B) the inputs were invalid at the last present step."""
    counts: I64
    """(P, B, 3) applications of formula 1, of formula 2 (including those that left AH
    unchanged) and samples that subtracted the minimum."""
    partials: F64
    """(P, G) scratch: the partial sums of the exact mean."""
    sort_buf: F64
    """(P, G) scratch: the sorted currents of the bidirectional shift."""
    updated: B1
    """(P, G) scratch: groups whose AH a sample updated."""
    rec_n: I64
    """(P,) events the rules recorded this step (``step_pack`` emits them)."""
    rec_code: I64
    """(P, E, 2) reason code and battery of each recorded event."""
    rec_val: F64
    """(P, E, 5) its numbers (the reason's slots)."""
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
    """S43: seconds of balancing that deliver ``ah`` Ah at the equalizer current (the string
    current within the equalizer's rating, else the rating; or the fixed current): proportional
    to AH, never clamped (what one update period cannot deliver is owed). Zero when the gate
    is closed."""
    i_eq = equalizer_current(prm, string_current_a)
    if ah <= 0.0 or i_eq <= 0.0:
        return 0.0
    return 3600.0 * ah / i_eq


@kernel
def nominal_current(prm: EqParams) -> float:
    """The current the remaining time is quoted at while the gate is closed."""
    return prm.fixed_current_a if prm.fixed_current else prm.equalizer_max_a


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
                return float(x)
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
    return float(hi)


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


# --------------------------------------------------------------------------- the rules
#
# Speed: every call of a compiled function that receives the big named tuples (state,
# measurements, commands, events) costs an atomic reference-count pair per array in them,
# which numba's pruning removes only in the simplest bodies (about 20-30 ns each on a busy
# machine: the first version of this file, a function per string and per AH update, took
# 20 µs per pack-step). So the rules run in two calls per pack (``_pack``, and
# ``sample_string`` per sample), record their events in the state, and ``step_pack`` emits
# them, claims the balancers and hands out the currents.


@kernel
def _book(
    st: EqState, p: int, i: int, g: int, formula: int, old: float, new: float, dv: float
) -> None:
    """One application of a rule to group ``g`` of string ``i``: logged, and recorded as a
    ``BalancingUpdated`` event when it moved AH by more than ``EVENT_RESOLUTION_AH``."""
    st.updated[p, g] = True
    e = st.log_n[p]
    if e < st.log.shape[1]:
        st.log[p, e, 0] = g
        st.log[p, e, 1] = formula
        st.log[p, e, 2] = old
        st.log[p, e, 3] = new
    st.log_n[p] = e + 1
    if abs(new - old) > EVENT_RESOLUTION_AH:
        e = st.rec_n[p]
        if e < st.rec_code.shape[1]:
            st.rec_code[p, e, 0] = BALANCING_UPDATED
            st.rec_code[p, e, 1] = i
            st.rec_val[p, e, 0] = g
            st.rec_val[p, e, 1] = formula
            st.rec_val[p, e, 2] = old
            st.rec_val[p, e, 3] = new
            st.rec_val[p, e, 4] = dv
        st.rec_n[p] = e + 1


@kernel
def sample_string(
    prm: EqParams, st: EqState, group_v: F64, p: int, i: int, n: int, ts_s: float,
    current_a: float,
) -> bool:  # fmt: skip
    """Steps S1-S43 for string ``i`` of pack ``p`` (its ``n`` group voltages are valid):
    ΔV, persistence timers, formula 1/2, subtract-the-minimum, then the grant (S43) of every
    updated group. ``ts_s`` is the time this sample stands for (zero-order hold): a timer that
    reaches its set time fires and is reduced by it, so a long sample applies the formula
    repeatedly. Every update is logged; those that change AH by more than
    ``EVENT_RESOLUTION_AH`` are recorded as events. Returns whether the minimum was
    subtracted."""
    ah, hi, lo, dvs = st.ah, st.hi_timer_s, st.lo_timer_s, st.dv_v
    counts, upd = st.counts, st.updated
    v_avg = exact_sum(group_v[p, i], n, st.partials[p]) / n
    st.log_n[p] = 0
    for g in range(n):
        upd[p, g] = False
        dvs[p, i, g] = v_avg - group_v[p, i, g]
    for g in range(n):
        dv = dvs[p, i, g]
        if dv > prm.dv_set_v:
            hi[p, i, g] += ts_s
            lo[p, i, g] = 0.0
            formula = FORMULA1
        elif dv < prm.dv_set_v:
            lo[p, i, g] += ts_s
            hi[p, i, g] = 0.0
            formula = FORMULA2
        else:
            hi[p, i, g] = 0.0
            lo[p, i, g] = 0.0
            continue
        while True:
            old = ah[p, i, g]
            if formula == FORMULA1:
                if not hi[p, i, g] >= prm.t1_s - SAMPLE_TOL:
                    break
                new = formula1(old, prm.n_ah)
                hi[p, i, g] = fmax(0.0, hi[p, i, g] - prm.t1_s)
            else:
                if not lo[p, i, g] >= prm.t2_s - SAMPLE_TOL:
                    break
                new = formula2(old)
                lo[p, i, g] = fmax(0.0, lo[p, i, g] - prm.t2_s)
            ah[p, i, g] = new
            # Every application counts, even one that leaves AH unchanged: formula 1 at
            # AH = N must re-grant the balancing time of a group that still lags.
            counts[p, i, formula] += 1
            _book(st, p, i, g, formula, old, new, dv)
    subtracted = n > 0
    for g in range(n):
        if not ah[p, i, g] > 0.0:
            subtracted = False
    if subtracted:
        low = ah[p, i, 0]
        for g in range(1, n):
            low = fmin(low, ah[p, i, g])
        for g in range(n):
            old = ah[p, i, g]
            new = old - low
            ah[p, i, g] = new
            _book(st, p, i, g, SUBTRACT_MIN, old, new, dvs[p, i, g])
        counts[p, i, SUBTRACT_MIN] += 1
    owed, granted = st.owed_ah, st.ledger_granted_ah
    for g in range(n):
        if upd[p, g]:
            # S43: the balancing time follows AH_g from now on, so the group is owed exactly
            # AH_g: raised by formula 1 (what one update period could not deliver is still in
            # it: AH only grows while the lag persists), lowered when formula 2 halves AH or
            # the subtraction resets it (issue #24: the charge still to deliver falls with AH).
            # ``granted`` books the change either way (granted = delivered + owed).
            a = ah[p, i, g]
            granted[p, i, g] += a - owed[p, i, g]
            owed[p, i, g] = a
    return subtracted


@kernel
def _pack(
    prm: EqParams, st: EqState, groups: I64, group_v: F64, n_groups: I64, current: F64,
    reported: B1, present: B1, p: int, dt: float, status: F64, s0: int,
) -> None:  # fmt: skip
    """Every string of pack ``p`` for one step of ``dt``: input checks (hold and a recorded
    ``Fault`` / ``FaultCleared``), the sample when due, the equalizer currents (owed Ah
    delivered, ledger booked) and the status channels."""
    ah, hi, lo, rem, dvs, cur = (
        st.ah, st.hi_timer_s, st.lo_timer_s, st.remaining_s, st.dv_v, st.current_a
    )  # fmt: skip
    since, faulted, owed = st.since_sample_s, st.faulted, st.owed_ah
    rec_n, rec_code, rec_val = st.rec_n, st.rec_code, st.rec_val
    l_time, l_gross, l_net, buf = (
        st.ledger_time_s, st.ledger_gross_ah, st.ledger_net_ah, st.sort_buf
    )  # fmt: skip
    cap_rec = rec_code.shape[1]
    for i in range(since.shape[1]):
        n = int(groups[i])
        # Only what the method uses is checked (group voltages and string current): a NaN
        # temperature must not stop it.
        code = -1
        x1 = 0.0
        x2 = np.nan
        if reported[p, i] and present[p, i]:
            got = int(n_groups[p, i])
            if got != n:
                code, x1, x2 = FAULT_GROUP_COUNT, float(n), float(got)
            else:
                for g in range(n):
                    v = group_v[p, i, g]
                    if not math.isfinite(v) or v <= 0.0:
                        code, x1, x2 = FAULT_GROUP_VOLTAGE, float(g), v
                        break
            if code < 0 and not math.isfinite(current[p, i]):
                code, x1 = FAULT_CURRENT, current[p, i]
            ok = code < 0
        else:
            ok = False  # absent: idle silently
        fault = code >= 0
        if fault and not faulted[p, i]:
            e = rec_n[p]
            if e < cap_rec:
                rec_code[p, e, 0] = code
                rec_code[p, e, 1] = i
                rec_val[p, e, 0] = 0.0  # the "source" label
                rec_val[p, e, 1] = x1
                rec_val[p, e, 2] = x2
                rec_val[p, e, 3] = np.nan
                rec_val[p, e, 4] = np.nan
            rec_n[p] = e + 1
        if fault:
            faulted[p, i] = True
        if not ok:
            # Hold: forget persistence; AH (learned), the owed Ah (granted, not yet delivered:
            # carried, never dropped) and the fault flag are kept; the equalizers idle.
            for g in range(hi.shape[2]):
                hi[p, i, g] = 0.0
                lo[p, i, g] = 0.0
                dvs[p, i, g] = np.nan
                cur[p, i, g] = 0.0
            since[p, i] = 0.0
        else:
            if faulted[p, i]:
                faulted[p, i] = False
                e = rec_n[p]
                if e < cap_rec:
                    rec_code[p, e, 0] = FAULT_CLEARED
                    rec_code[p, e, 1] = i
                    rec_val[p, e, 0] = 0.0
                    for j in range(1, 5):
                        rec_val[p, e, j] = np.nan
                rec_n[p] = e + 1
            cur_a = current[p, i]
            since[p, i] += dt
            if n > 0 and since[p, i] >= prm.sample_period_s * (1.0 - SAMPLE_TOL):
                ts = since[p, i]
                since[p, i] = 0.0
                sample_string(prm, st, group_v, p, i, n, ts, cur_a)
            # Equalizer currents for the next dt: each group's owed Ah is delivered at i_eq,
            # the last partial step prorated so that the charge is exactly what was owed.
            i_eq = equalizer_current(prm, cur_a)
            for g in range(n):
                cur[p, i, g] = 0.0
            if i_eq > 0.0 and dt > 0.0:
                step_ah = i_eq * dt / 3600.0
                for g in range(n):
                    q = owed[p, i, g]
                    # A group at or above the average (ΔV_g <= 0 at its last sample) is not
                    # behind: charging it would widen the spread. What it is owed waits (and
                    # falls with its AH at the next formula-2 update) until it lags again.
                    if q <= 0.0 or not dvs[p, i, g] > 0.0:
                        continue
                    if q >= step_ah:
                        cur[p, i, g] = i_eq
                        owed[p, i, g] = q - step_ah
                        l_time[p, i, g] += dt
                        l_gross[p, i, g] += step_ah
                    else:
                        cur[p, i, g] = q * 3600.0 / dt
                        owed[p, i, g] = 0.0
                        l_time[p, i, g] += q * 3600.0 / i_eq
                        l_gross[p, i, g] += q
            i_ref = i_eq if i_eq > 0.0 else nominal_current(prm)
            for g in range(n):
                rem[p, i, g] = 3600.0 * owed[p, i, g] / i_ref
            if prm.bidirectional and n > 1:
                shift = lower_median(cur[p, i], n, buf[p])
                for g in range(n):
                    cur[p, i, g] = cur[p, i, g] - shift
            for g in range(n):
                l_net[p, i, g] += cur[p, i, g] * dt / 3600.0
        status[p, i, s0 + ST_FAULT] = 1.0 if fault else 0.0
        for k in range(prm.status_groups):
            c = s0 + 1 + PER_GROUP * k
            if k < n:
                status[p, i, c + ST_DV_MV] = dvs[p, i, k] * 1000.0
                status[p, i, c + ST_AH] = ah[p, i, k]
                status[p, i, c + ST_TIME] = rem[p, i, k]
                status[p, i, c + ST_I] = cur[p, i, k]
                status[p, i, c + ST_OWED] = owed[p, i, k]
            else:  # this battery has no group k (None to a reader)
                status[p, i, c + ST_DV_MV] = np.nan
                status[p, i, c + ST_AH] = np.nan
                status[p, i, c + ST_TIME] = np.nan
                status[p, i, c + ST_I] = np.nan
                status[p, i, c + ST_OWED] = np.nan


@kernel
def _emit_recorded(st: EqState, ev: EventBuf, p: int, src: int, t_s: float) -> None:
    """The events the rules recorded, in order (those beyond the record's room are counted
    as dropped, as a full event buffer does)."""
    n = st.rec_n[p]
    cap = st.rec_code.shape[1]
    for e in range(min(n, cap)):
        k = emit(ev, p, src, st.rec_code[p, e, 0], st.rec_code[p, e, 1], t_s)
        for j in range(5):
            ev.val[k, j] = st.rec_val[p, e, j]
    if n > cap:
        ev.dropped[0] += n - cap
    st.rec_n[p] = 0


@kernel
def _put_balancers(cmd: CmdArrays, groups: I64, current: F64, p: int) -> None:
    claim_balancer(cmd, p)
    for i in range(groups.shape[0]):
        for g in range(groups[i]):
            put_balancer(cmd, p, i, g, current[p, i, g])


@kernel
def step_pack(
    prm: EqParams, st: EqState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One step of pack ``p``: every string's equalizer currents (an opinion only where the
    pack has balancers), events, and the status channels."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    bat = m.bat
    st.rec_n[p] = 0
    _pack(
        prm, st, tp.groups, bat.group_v, bat.n_groups, bat.current_a, bat.reported,
        bat.present, p, dt, status, s0,
    )  # fmt: skip
    if st.rec_n[p] > 0:
        _emit_recorded(st, ev, p, src, m.t_s[p])
    if tp.has_balancers:
        _put_balancers(cmd, tp.groups, st.current_a, p)


@kernel
def step_packs(
    prm: EqParams, st: EqState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
