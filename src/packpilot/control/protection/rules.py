"""Condition-dependent discharge protection rules, compiled (US10868343B2;
``spec/discharge_protection.md``).

A fixed "cut-off voltage + longest sustainable time" wastes capacity when the load is heavy or
the battery is cold (the voltage sags under load while plenty of charge is left) and is too lax
when the load is light. Here the protection parameter (cut-off, t_max) is looked up every tick
from the battery's status (current, temperature, optionally SOH) in an N-dimensional range
table, and the time spent at or below the *active* cut-off is accumulated with the weight
``n = m / t_max`` (``m`` = LCM of all t_max). The battery's discharge path is opened, and stays
open until the next discharge cycle, once the weighted sum reaches ``m``; this is the same as
``sum(t_k / t_max_k) >= 1``: each second under parameter k uses up ``1 / t_max_k`` of the
allowance.

Exactness: the sum is kept as an exact fraction in weighted milliseconds, a pair of int64
(numerator, denominator) reduced by their gcd (``n`` is an integer because ``m`` is the LCM of
whole-millisecond durations), so the spec's worked examples trip exactly at 5 s, 15 s and 10 s
and never one tick late from float round-off. A tick's duration enters as
``Fraction(dt_s * 1000).limit_denominator(1000)`` (:func:`dt_ms`, CPython's continued-fraction
algorithm on the float's exact value: 0.1 s -> 100 ms, 1/3 s -> 1000/3 ms).

Bounds (``build`` guarantees ``m <= 2**43`` ms): the pair is kept with numerator <= 2**53 and
denominator * m <= 2**53, so every comparison is exact and ``n / d`` as floats is the correctly
rounded value Python's ``float(Fraction)`` gives. Outside those bounds the rules fail safe
instead of overflowing: a tick whose weighted numerator alone exceeds 2**53 (a dt of roughly
10**9 s or more; ``dt * 1000`` at or above 2**62 or infinite) *saturates* the sum at 2**53
weighted ms, which trips; a sum whose exact denominator would grow past the bound (many ticks
with different, coprime fractional durations) is rounded *up* to whole weighted microseconds
(a trip can only come earlier, by at most two weighted microseconds per such tick). Neither
happens with the durations a simulation or a log produces; the scalar reference kept a Python
big-integer ``Fraction`` there (and raised ``OverflowError`` for an infinite ``dt * 1000``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import emit, fmin, put_dsg
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

# Axis codes: the index of the axis name in ``packpilot.config.protection.AXES``.
AX_CURRENT = 0
AX_TEMP = 1
AX_SOH = 2
AX_RES = 3
AX_CYCLES = 4
N_AXES = 5
FIELD_MIN_CELL = N_AXES
"""Fault fields: the axis codes, then the check voltage."""
N_FIELDS = N_AXES + 1

# Sources of the check voltage (label list ``vsources``).
VS_MIN_CELL = 0
VS_GROUPS = 1
VS_MEAN = 2
VS_NONE = 3

# New-cycle reasons (label list ``resets``).
RESET_REINSERTED = 0
RESET_CHARGE = 1

# Reason codes (rows of the reason table in controller.py).
FAULT_CURRENT = 0
FAULT_AXIS = 1
FAULT_V_GROUPS = 2
FAULT_V_MEAN = 3
FAULT_V_NONE = 4
RESET = 5
TRIPPED = 6
WARNING = 7
EVENTS_PER_BATTERY = 2 + N_FIELDS + 2
"""At most one reset each for re-insertion and charge, one fault per field, one warning, one
trip."""

# Status channels, in order.
ST_PARAM = 0
ST_CUTOFF = 1
ST_TMAX = 2
ST_FRACTION = 3
ST_TRIPPED = 4
ST_TIME_TO_TRIP = 5
ST_TIME_TO_EMPTY = 6

LIM = 2**53
"""Largest numerator (and denominator * m) of the weighted sum: exact as a float."""
M_MAX = 2**43
"""Largest m (ms) ``build`` accepts: ``1000 * m <= LIM`` for the microsecond fallback."""
FALLBACK_DEN = 1000
"""Denominator of the rounded-up sum when the exact one would not fit (weighted µs)."""
MAX_DEN_MS = 1000
"""``limit_denominator(1000)`` of a tick's milliseconds."""


class ProtectionParams(NamedTuple):
    axis_code: I64
    """(A,) code of each table axis (``AX_*``), in the table's axis order."""
    row_param: I64
    """(R,) parameter index of each table row."""
    row_lo: F64
    """(R, A) lower edge of each row's range per axis (-inf = unbounded) ..."""
    row_hi: F64
    """(R, A) ... upper edge ..."""
    row_lo_closed: B1
    """(R, A) ... lower edge included ..."""
    row_hi_closed: B1
    """(R, A) ... upper edge included."""
    cutoff_v: F64
    """(K,) cut-off of each parameter the table uses (order of first appearance)."""
    t_max_s: F64
    """(K,) longest sustainable time."""
    weight: I64
    """(K,) n = m / t_max (exact integers)."""
    m_ms: int
    band: F64
    """(A,) hysteresis band per axis (0 = none)."""
    use_hysteresis: bool
    tau_s: F64
    """(A,) filter time constant per axis ..."""
    has_filter: B1
    """(A,) ... and whether that axis is filtered."""
    voltage_le: bool
    """Accumulate when the check voltage is <= the cut-off (else <)."""
    trip_ge: bool
    """Trip when the sum is >= m (else >)."""
    discharge_threshold_a: float
    charge_threshold_a: float
    charge_detect_s: float
    reset_on_recovery: bool
    reset_on_reinsert: bool
    warn_share: float
    """Share of the allowance at which ``ProtectionWarning`` fires (0 < share <= 1)."""
    predict_tau_s: float
    """Time constant of the check voltage's slope filter (time-to-trip prediction)."""
    res_step_a: float
    """Smallest current step that updates the resistance estimate ..."""
    res_gain: float
    """... and the weight of a new step in it."""
    name_len: I64
    """(K,) UTF-8 byte length of each parameter name ..."""
    name_utf8: I64
    """... and the names' bytes concatenated (the label list; never read by the rules)."""


class ProtectionState(NamedTuple):
    acc_num: I64
    """(P, B) weighted sum in weight x milliseconds: numerator ..."""
    acc_den: I64
    """(P, B) ... and denominator (>= 1, coprime with the numerator)."""
    tripped: B1
    row: I64
    """(P, B) active table row (-1 before the first tick)."""
    discharging: B1
    """(P, B) last known discharge state (held while the current is not finite)."""
    charge_s: F64
    charge_cycle_started: B1
    absent: B1
    filtered: F64
    """(P, B, A) filtered axis value ..."""
    filtered_set: B1
    """(P, B, A) ... once the axis has had a finite reading."""
    faults: B1
    """(P, B, N_FIELDS) field currently not finite (one Fault event per episode)."""
    values: F64
    """(P, B, A) scratch: this tick's axis values (NaN = unknown)."""
    warned: B1
    """(P, B) ProtectionWarning given in this episode (re-armed below the share)."""
    v_prev: F64
    """(P, B) last finite check voltage (NaN before one) ..."""
    dvdt: F64
    """(P, B) ... and its filtered slope in V/s (NaN before two)."""
    r_est: F64
    """(P, B) cell-level internal resistance estimated from current steps (NaN before one) ..."""
    r_i: F64
    """(P, B) ... the current and ..."""
    r_v: F64
    """(P, B) ... check voltage of the last tick with both finite (NaN before one)."""


# ------------------------------------------------------------------------- exact fractions


@kernel_inline
def _gcd(a: int, b: int) -> int:
    while b != 0:
        a, b = b, a % b
    return a


@kernel_inline
def dt_ms(dt: float) -> tuple[int, int]:
    """``Fraction(dt * 1000.0).limit_denominator(1000)`` as (numerator, denominator) for a
    finite ``dt >= 0``; (-1, 1) when the numerator would not fit (2**62 ms or more).

    Float noise snaps (0.1 s -> 100 ms, 1/3 s -> 1000/3 ms): CPython's continued-fraction
    algorithm, run on the exact binary value ``x = n / 2**e`` of ``dt * 1000``.
    """
    x = dt * 1000.0
    if not (x > 0.0):
        return 0, 1
    if not (x < 4611686018427387904.0):  # 2**62 (or inf / NaN)
        return -1, 1
    mant, ex = math.frexp(x)  # x = mant * 2**ex, 0.5 <= mant < 1
    n = int(mant * 9007199254740992.0)  # mant * 2**53: an integer
    e = 53 - ex
    while n % 2 == 0 and e > 0:
        n //= 2
        e -= 1
    if e <= 0:
        return n << (-e), 1  # an integer number of ms, < 2**62
    if e >= 63:
        # x < 2**-10 < 1/1000: the candidates are 0/1 and 1/1000; CPython keeps 0/1 when
        # 2 * n * 1000 <= 2**e, i.e. 125 * n <= 2**(e - 4) (125 * n < 2**60).
        if e - 4 >= 61 or 125 * n <= (1 << (e - 4)):
            return 0, 1
        return 1, MAX_DEN_MS
    den = 1 << e
    if den <= MAX_DEN_MS:
        return n, den
    p0, q0, p1, q1 = 0, 1, 1, 0
    nn, dd = n, den
    while True:
        a = nn // dd
        if q1 > 0 and a > MAX_DEN_MS:
            break  # q0 + a * q1 > max_denominator (and no overflow)
        q2 = q0 + a * q1
        if q2 > MAX_DEN_MS:
            break
        p0, q0, p1, q1 = p1, q1, p0 + a * p1, q2
        nn, dd = dd, nn - a * dd
    k = (MAX_DEN_MS - q0) // q1
    qk = q0 + k * q1
    # |p1/q1 - x| <= |bound1 - x|  <=>  2 * dd * qk <= den  <=>  2 * qk <= den // dd
    if 2 * qk <= den // dd:
        return p1, q1
    return p0 + k * p1, qk


@kernel_inline
def acc_add(num: I64, den: I64, p: int, i: int, w: int, a: int, b: int, m: int) -> None:
    """``acc += w * a / b`` exactly for the sum ``num[p, i] / den[p, i]`` (``a >= 0`` or -1 =
    huge, ``1 <= b <= 1000``), within the bounds of the module docstring (saturate / round up
    beyond them)."""
    if a == 0:
        return
    if a < 0 or a > LIM // w:
        num[p, i] = LIM  # w * a / b > LIM / 1000 > M_MAX >= m: saturate (trips)
        den[p, i] = 1
        return
    inc = w * a
    g = _gcd(inc, b)
    inc //= g
    b //= g
    an = num[p, i]
    ad = den[p, i]
    g = _gcd(ad, b)
    ad_g = ad // g
    b_g = b // g
    if ad_g > (LIM // m) // b:
        # The exact denominator would not fit: round the sum up to whole weighted µs.
        v = (float(an) / float(ad) + float(inc) / float(b)) * float(FALLBACK_DEN)
        if not (v < float(LIM - 2)):
            num[p, i] = LIM
            den[p, i] = 1
            return
        n_up = math.ceil(v) + 1
        g = _gcd(n_up, FALLBACK_DEN)
        num[p, i] = n_up // g
        den[p, i] = FALLBACK_DEN // g
        return
    if an > LIM // b_g or inc > LIM // ad_g:
        num[p, i] = LIM  # numerator > LIM with den * m <= LIM: the sum is above m
        den[p, i] = 1
        return
    t1 = an * b_g
    t2 = inc * ad_g
    if t1 > LIM - t2:
        num[p, i] = LIM
        den[p, i] = 1
        return
    n_new = t1 + t2
    d_new = ad_g * b
    g = _gcd(n_new, d_new)
    num[p, i] = n_new // g
    den[p, i] = d_new // g


@kernel_inline
def acc_fraction(num: I64, den: I64, p: int, i: int, m: int) -> float:
    """``float(acc / m)``: correctly rounded (numerator and denominator * m <= 2**53)."""
    return float(num[p, i]) / float(den[p, i] * m)


# ------------------------------------------------------------------------------- the table


@kernel_inline
def contains(
    lo: float, hi: float, lo_closed: bool, hi_closed: bool, x: float, band: float
) -> bool:  # fmt: skip
    """``x`` in the range widened by ``band`` on both sides (a NaN ``x`` reads as inside, as
    in the scalar reference; the callers never pass one where it matters)."""
    lo_b = lo - band
    hi_b = hi + band
    if x < lo_b or (x == lo_b and not lo_closed):
        return False
    return not (x > hi_b or (x == hi_b and not hi_closed))


@kernel_inline
def lookup(
    row_lo: F64, row_hi: F64, row_lo_closed: B1, row_hi_closed: B1, values: F64, p: int, i: int
) -> int:  # fmt: skip
    """First row containing every value ``values[p, i, :]`` (fully known; -1 if none)."""
    for k in range(row_lo.shape[0]):
        ok = True
        for a in range(row_lo.shape[1]):
            if not contains(
                row_lo[k, a], row_hi[k, a], row_lo_closed[k, a], row_hi_closed[k, a],
                values[p, i, a], 0.0,
            ):  # fmt: skip
                ok = False
                break
        if ok:
            return k
    return -1


@kernel_inline
def most_conservative(
    row_lo: F64, row_hi: F64, row_lo_closed: B1, row_hi_closed: B1, row_param: I64,
    cutoff_v: F64, t_max_s: F64, values: F64, p: int, i: int,
) -> int:  # fmt: skip
    """Among rows consistent with the finite values ``values[p, i, :]`` (NaN = unknown), the
    highest cut-off; ties to the shortest t_max, then to the first row (-1 if none): when a
    sensor fails the battery is protected as if the unknown status were the worst the table
    allows."""
    best = -1
    best_cut = 0.0
    best_neg_t = 0.0
    for k in range(row_lo.shape[0]):
        ok = True
        for a in range(row_lo.shape[1]):
            x = values[p, i, a]
            if not math.isnan(x) and not contains(
                row_lo[k, a], row_hi[k, a], row_lo_closed[k, a], row_hi_closed[k, a], x, 0.0
            ):
                ok = False
                break
        if not ok:
            continue
        q = row_param[k]
        cut = cutoff_v[q]
        neg_t = -t_max_s[q]
        if best < 0 or cut > best_cut or (cut == best_cut and neg_t > best_neg_t):
            best = k
            best_cut = cut
            best_neg_t = neg_t
    return best


@kernel_inline
def _in_band(
    row_lo: F64, row_hi: F64, row_lo_closed: B1, row_hi_closed: B1, band: F64, row: int,
    values: F64, p: int, i: int,
) -> bool:  # fmt: skip
    """The values are still inside ``row`` widened by the hysteresis bands."""
    for a in range(row_lo.shape[1]):
        if not contains(
            row_lo[row, a], row_hi[row, a], row_lo_closed[row, a], row_hi_closed[row, a],
            values[p, i, a], band[a],
        ):  # fmt: skip
            return False
    return True


# ------------------------------------------------------------------------------- the rules
# Per-battery helpers are inlined or take arrays and numbers, not the named tuples: a call
# that is not inlined pays a reference-count update for every array of every tuple it receives
# (the helpers that do take tuples run only when they emit an event).


@kernel_inline
def _fault_edge(faults: B1, p: int, i: int, field: int, ok: bool) -> bool:
    """Track a field's non-finite episode; True at its start (one ``Fault`` per episode)."""
    if ok:
        faults[p, i, field] = False
        return False
    if faults[p, i, field]:
        return False
    faults[p, i, field] = True
    return True


@kernel_inline
def _emit_fault(ev: EventBuf, p: int, src: int, code: int, i: int, t_s: float, field: int) -> None:
    k = emit(ev, p, src, code, i, t_s)
    ev.val[k, 0] = 0.0  # source: "protection"
    ev.val[k, 1] = field


@kernel_inline
def _new_cycle(
    st: ProtectionState, p: int, i: int, reason: int, t_s: float, ev: EventBuf, src: int
) -> None:  # fmt: skip
    if st.acc_num[p, i] != 0 or st.tripped[p, i]:
        k = emit(ev, p, src, RESET, i, t_s)
        ev.val[k, 0] = reason
        ev.val[k, 1] = 1.0 if st.tripped[p, i] else 0.0
        ev.val[k, 2] = float(st.acc_num[p, i]) / float(st.acc_den[p, i]) / 1000.0
    st.acc_num[p, i] = 0
    st.acc_den[p, i] = 1
    st.tripped[p, i] = False


@kernel_inline
def fallback_voltage(
    group_v: F64, n_groups: I64, voltage_v: F64, cells_per_group: I64, groups: I64, p: int,
    i: int,
) -> tuple[float, int]:  # fmt: skip
    """Without a finite min cell voltage: the weakest group's mean cell; else the mean cell;
    else NaN. A group is ``cells_per_group`` cells in series, so ``group_v / cells_per_group``
    is that group's mean cell voltage (>= its minimum: the fallbacks under-count, never
    over-trip)."""
    per_group = cells_per_group[i] if i < cells_per_group.shape[0] else 0
    n_series = groups[i] if i < groups.shape[0] else 0
    ng = min(n_groups[p, i], group_v.shape[2])
    if per_group > 0 and ng > 0:
        ok = True
        g_min = group_v[p, i, 0]
        for g in range(ng):
            x = group_v[p, i, g]
            if not math.isfinite(x):
                ok = False
                break
            g_min = fmin(g_min, x)
        if ok:
            return g_min / per_group, VS_GROUPS
    vb = voltage_v[p, i]
    if per_group > 0 and n_series > 0 and math.isfinite(vb):
        return vb / (n_series * per_group), VS_MEAN
    return math.nan, VS_NONE


@kernel_inline
def _trip_event(
    prm: ProtectionParams, st: ProtectionState, m: MeasArrays, p: int, i: int, q: int,
    v_chk: float, source: int, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    k = emit(ev, p, src, TRIPPED, i, m.t_s[p])
    val = ev.val[k]
    val[0] = q
    val[1] = prm.cutoff_v[q]
    val[2] = prm.t_max_s[q]
    val[3] = prm.weight[q]
    val[4] = float(st.acc_num[p, i]) / float(st.acc_den[p, i]) / 1000.0
    val[5] = prm.m_ms / 1000.0
    val[6] = acc_fraction(st.acc_num, st.acc_den, p, i, prm.m_ms)
    val[7] = v_chk
    val[8] = source
    val[9] = m.bat.min_cell_v[p, i]
    val[10] = m.bat.voltage_v[p, i]
    val[11] = m.bat.current_a[p, i]
    val[12] = m.bat.temp_c[p, i]
    val[13] = m.bat.soc[p, i]
    val[14] = m.bat.remaining_capacity_ah[p, i]
    val[15] = m.bat.full_capacity_ah[p, i]


@kernel_inline
def _warning_event(
    prm: ProtectionParams, st: ProtectionState, m: MeasArrays, p: int, i: int, q: int,
    v_chk: float, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    k = emit(ev, p, src, WARNING, i, m.t_s[p])
    val = ev.val[k]
    val[0] = q
    val[1] = prm.cutoff_v[q]
    val[2] = prm.t_max_s[q]
    val[3] = acc_fraction(st.acc_num, st.acc_den, p, i, prm.m_ms)
    val[4] = prm.warn_share
    val[5] = remaining_s(st.acc_num, st.acc_den, p, i, prm.m_ms, prm.weight[q])
    val[6] = v_chk
    val[7] = m.bat.current_a[p, i]
    val[8] = m.bat.temp_c[p, i]
    val[9] = m.bat.soc[p, i]


@kernel_inline
def remaining_s(num: I64, den: I64, p: int, i: int, m: int, w: int) -> float:
    """Seconds at or below the cut-off left before the trip if parameter weight ``w`` stays
    active: ``(m - acc) / w`` weighted ms, as seconds (0 once the sum reached m)."""
    left = float(m * den[p, i] - num[p, i]) / float(den[p, i])
    if left <= 0.0:
        return 0.0
    return left / float(w) / 1000.0



@kernel_inline
def _below(prm: ProtectionParams, v_chk: float, cut: float) -> bool:
    """The voltage is below the active cut-off (at it counts as below under ``voltage_le``):
    one test for the trip rule and the time-to-trip prediction."""
    return v_chk <= cut if prm.voltage_le else v_chk < cut

@kernel_inline
def time_to_trip(
    prm: ProtectionParams, st: ProtectionState, p: int, i: int, q: int, v_chk: float,
    cur: float,
) -> float:  # fmt: skip
    """Predicted seconds to the trip if the present load and temperature (so the active
    parameter ``q``) hold: 0 when tripped; NaN when not discharging or the check voltage is
    unknown; at or below the cut-off the allowance left at ``q``'s weight; above it, the time
    the voltage needs to reach the cut-off at its filtered slope plus that allowance, NaN if
    the voltage is not falling."""
    if st.tripped[p, i]:
        return 0.0
    if q < 0 or not (math.isfinite(cur) and st.discharging[p, i]) or math.isnan(v_chk):
        return math.nan
    left = remaining_s(st.acc_num, st.acc_den, p, i, prm.m_ms, prm.weight[q])
    cut = float(prm.cutoff_v[q])
    below = _below(prm, v_chk, cut)
    if below:
        return left
    slope = float(st.dvdt[p, i])
    if not (slope < 0.0):
        return math.nan
    return (v_chk - cut) / -slope + left


@kernel_inline
def time_to_empty(m: MeasArrays, p: int, i: int, discharge_threshold_a: float) -> float:
    """Seconds until the remaining capacity is used up at the present discharge current (NaN
    when not discharging or unknown): remaining_capacity_ah, else soc x full_capacity_ah."""
    cur = m.bat.current_a[p, i]
    if not (math.isfinite(cur) and cur > discharge_threshold_a and cur > 0.0):
        return math.nan
    ah = m.bat.remaining_capacity_ah[p, i]
    if not math.isfinite(ah):
        ah = m.bat.soc[p, i] * m.bat.full_capacity_ah[p, i]
    if not math.isfinite(ah):
        return math.nan
    if ah <= 0.0:
        return 0.0
    return float(ah * 3600.0 / cur)


@kernel_inline
def step_pack(
    prm: ProtectionParams, st: ProtectionState, tp: PackArrays, m: MeasArrays, p: int,
    dt_s: float, cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One tick of pack ``p``: the discharge path of a tripped battery off, else no opinion.

    Tick semantics: each sample is taken to hold for ``dt_s``; the trip fires on the tick whose
    ``dt_s`` makes the weighted sum reach ``m``. A ``dt_s`` that is not a finite number > 0
    counts as 0.
    """
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    a_ms, b_ms = dt_ms(dt)
    t_s = m.t_s[p]
    bat = m.bat
    n_axes = prm.axis_code.shape[0]
    for i in range(st.tripped.shape[1]):
        ttt = math.nan
        if not (bat.reported[p, i] and bat.present[p, i]):
            st.absent[p, i] = True
            st.charge_s[p, i] = 0.0
            st.v_prev[p, i] = math.nan
            st.dvdt[p, i] = math.nan
            st.r_est[p, i] = math.nan  # whatever comes back is estimated afresh
            st.r_i[p, i] = math.nan
            st.r_v[p, i] = math.nan
        else:
            if st.absent[p, i]:
                st.absent[p, i] = False
                if prm.reset_on_reinsert:
                    _new_cycle(st, p, i, RESET_REINSERTED, t_s, ev, src)

            cur = bat.current_a[p, i]
            cur_ok = math.isfinite(cur)
            if _fault_edge(st.faults, p, i, AX_CURRENT, cur_ok):
                _emit_fault(ev, p, src, FAULT_CURRENT, i, t_s, AX_CURRENT)
            # New discharge cycle: sustained charging (spec §7/§10.4).
            if cur_ok and cur < -prm.charge_threshold_a:
                st.charge_s[p, i] += dt
                if st.charge_s[p, i] >= prm.charge_detect_s and not st.charge_cycle_started[p, i]:
                    st.charge_cycle_started[p, i] = True
                    _new_cycle(st, p, i, RESET_CHARGE, t_s, ev, src)
            else:
                st.charge_s[p, i] = 0.0
                st.charge_cycle_started[p, i] = False
            if cur_ok:
                st.discharging[p, i] = cur > prm.discharge_threshold_a

            # Status values of the table's axes (NaN = unknown), filtered where configured.
            known = True
            for a in range(n_axes):
                code = prm.axis_code[a]
                if code == AX_CURRENT:
                    x = cur  # its fault is reported above
                else:
                    if code == AX_TEMP:
                        x = bat.temp_c[p, i]
                    elif code == AX_RES:
                        x = st.r_est[p, i]  # an estimate, not a sensor: unknown is no Fault
                    elif code == AX_CYCLES:
                        x = bat.cycle_count[p, i]
                    else:  # AX_SOH: full / nominal capacity; unknown without a nominal value
                        cap = tp.capacity_ah[p, i]
                        x = bat.full_capacity_ah[p, i] / cap if cap > 0.0 else math.nan
                    if code != AX_RES and _fault_edge(st.faults, p, i, code, math.isfinite(x)):
                        _emit_fault(ev, p, src, FAULT_AXIS, i, t_s, code)
                if not math.isfinite(x):
                    st.values[p, i, a] = math.nan
                    known = False
                    continue
                if prm.has_filter[a]:
                    if st.filtered_set[p, i, a]:
                        prev = st.filtered[p, i, a]
                        x = prev + (1.0 - math.exp(-dt / prm.tau_s[a])) * (x - prev)
                    st.filtered[p, i, a] = x
                    st.filtered_set[p, i, a] = True
                if math.isnan(x):
                    known = False
                st.values[p, i, a] = x
            row = st.row[p, i]
            if not known:
                row = most_conservative(
                    prm.row_lo, prm.row_hi, prm.row_lo_closed, prm.row_hi_closed, prm.row_param,
                    prm.cutoff_v, prm.t_max_s, st.values, p, i,
                )  # fmt: skip
            elif not (
                prm.use_hysteresis
                and row >= 0
                and _in_band(
                    prm.row_lo, prm.row_hi, prm.row_lo_closed, prm.row_hi_closed, prm.band, row,
                    st.values, p, i,
                )
            ):  # fmt: skip
                row = lookup(
                    prm.row_lo, prm.row_hi, prm.row_lo_closed, prm.row_hi_closed, st.values, p, i
                )
            st.row[p, i] = row
            q = prm.row_param[row]  # row -1 (never: the table covers everything) reads the last

            # The check voltage: the min cell voltage, else a fallback.
            v_chk = bat.min_cell_v[p, i]
            source = VS_MIN_CELL
            if not math.isfinite(v_chk):
                v_chk, source = fallback_voltage(
                    bat.group_v, bat.n_groups, bat.voltage_v, tp.cells_per_group, tp.groups, p, i
                )
            if _fault_edge(st.faults, p, i, FIELD_MIN_CELL, source == VS_MIN_CELL):
                if source == VS_GROUPS:
                    code = FAULT_V_GROUPS
                elif source == VS_MEAN:
                    code = FAULT_V_MEAN
                else:
                    code = FAULT_V_NONE
                _emit_fault(ev, p, src, code, i, t_s, FIELD_MIN_CELL)

            # Internal resistance from current steps: R = -dV / dI of the check voltage between
            # two ticks whose currents differ by at least res_step_a (the same cell's reading).
            if cur_ok and source == VS_MIN_CELL:
                di = cur - st.r_i[p, i]
                if math.isfinite(di) and abs(di) >= prm.res_step_a:
                    r_new = -(v_chk - st.r_v[p, i]) / di
                    if r_new > 0.0 and math.isfinite(r_new):
                        if math.isnan(st.r_est[p, i]):
                            st.r_est[p, i] = r_new
                        else:
                            r_old = st.r_est[p, i]
                            st.r_est[p, i] = r_old + prm.res_gain * (r_new - r_old)
                st.r_i[p, i] = cur
                st.r_v[p, i] = v_chk

            # The check voltage's slope, low-pass filtered (time-to-trip prediction).
            if math.isfinite(v_chk) and dt > 0.0:
                if math.isfinite(st.v_prev[p, i]):
                    raw = (v_chk - st.v_prev[p, i]) / dt
                    if math.isnan(st.dvdt[p, i]):
                        st.dvdt[p, i] = raw
                    else:
                        prev_s = st.dvdt[p, i]
                        st.dvdt[p, i] = prev_s + (1.0 - math.exp(-dt / prm.predict_tau_s)) * (
                            raw - prev_s
                        )
                st.v_prev[p, i] = v_chk

            if not (st.tripped[p, i] or math.isnan(v_chk)):
                cut = prm.cutoff_v[q]
                below = _below(prm, v_chk, cut)
                if below and st.discharging[p, i]:
                    acc_add(st.acc_num, st.acc_den, p, i, prm.weight[q], a_ms, b_ms, prm.m_ms)
                elif not below and prm.reset_on_recovery:
                    st.acc_num[p, i] = 0
                    st.acc_den[p, i] = 1
                m_den = prm.m_ms * st.acc_den[p, i]
                an = st.acc_num[p, i]
                if an > m_den or (prm.trip_ge and an == m_den):
                    st.tripped[p, i] = True
                    _trip_event(prm, st, m, p, i, q, v_chk, source, ev, src)
                elif not st.warned[p, i] and (
                    acc_fraction(st.acc_num, st.acc_den, p, i, prm.m_ms) >= prm.warn_share
                ):
                    # The platform is told once per episode, before the trip (a tick that
                    # trips outright reports the trip alone).
                    st.warned[p, i] = True
                    _warning_event(prm, st, m, p, i, q, v_chk, ev, src)
            if acc_fraction(st.acc_num, st.acc_den, p, i, prm.m_ms) < prm.warn_share:
                st.warned[p, i] = False  # re-armed: the share fell back (a new cycle)
            ttt = time_to_trip(prm, st, p, i, q, v_chk, cur)

        if st.tripped[p, i]:
            put_dsg(cmd, p, i, False)
        row = st.row[p, i]
        if row < 0:
            status[p, i, s0 + ST_PARAM] = -1.0
            status[p, i, s0 + ST_CUTOFF] = math.nan
            status[p, i, s0 + ST_TMAX] = math.nan
        else:
            q = prm.row_param[row]
            status[p, i, s0 + ST_PARAM] = q
            status[p, i, s0 + ST_CUTOFF] = prm.cutoff_v[q]
            status[p, i, s0 + ST_TMAX] = prm.t_max_s[q]
        status[p, i, s0 + ST_FRACTION] = float(st.acc_num[p, i]) / float(
            st.acc_den[p, i] * prm.m_ms
        )
        status[p, i, s0 + ST_TRIPPED] = 1.0 if st.tripped[p, i] else 0.0
        status[p, i, s0 + ST_TIME_TO_TRIP] = ttt
        status[p, i, s0 + ST_TIME_TO_EMPTY] = time_to_empty(m, p, i, prm.discharge_threshold_a)


@kernel
def step_packs(
    prm: ProtectionParams, st: ProtectionState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
