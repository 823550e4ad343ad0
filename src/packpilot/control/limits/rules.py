"""Absolute safety limits, compiled: warn / derate / trip rows with debounce, delay,
hysteresis and latch, and the published current limits.

A row is violated while its quantity is strictly beyond ``threshold``. It becomes active once
``debounce`` consecutive samples violated it *and* the violation then persisted ``delay_s``
more seconds (the debounce rejects single-sample glitches, the delay sets the time scale).
It clears when the quantity is back at or past ``reset`` (hysteresis) and it has been active
for at least ``latch_s``; a manual row (``latch_s = None``) clears only by :func:`reset_trips`
(an operator or supervisor decision), whose ``LimitReset`` events come with the next step. A
non-finite value neither counts nor clears (sensor plausibility is another layer's job); this
layer holds its state. Outside its context (``when``) a row counts nothing and may clear.

A trip opens its path (``chg_on`` / ``dsg_on`` off) while active, and the charger is switched
off while docked with any charge-path trip. The published current limits (charge and
discharge, per battery and for the pack) are the minimum of three piecewise-linear C-rate
tables over cell voltage, temperature and SOC, scaled by the battery's capacity; a derate row
of a path scales that path's limit by ``derate_fraction`` (once), a trip makes it 0. For
parallel batteries the pack limit is N x the smallest limit of the N batteries that can conduct
in that direction (current shares roughly equally, so the weakest battery sets everyone's
share); NaN when one of them is unknown.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.battery import capacity_ah, conducts
from packpilot.control.commands import emit, fmax, fmin, put_charger_off, put_chg, put_dsg
from packpilot.jit import kernel

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

EPS = 1e-9
"""Time comparisons tolerate float round-off of summed ``dt_s`` (10 x 0.1 s = 0.9999999)."""

# Quantities (``config.limits.QUANTITIES`` order).
Q_CELL_V_MAX = 0
Q_CELL_V_MIN = 1
Q_CHG_C_RATE = 2
Q_DSG_C_RATE = 3
Q_TEMP_MAX_C = 4
Q_TEMP_MIN_C = 5
N_QUANTITIES = 6

# Contexts (``config.limits.CONTEXTS`` order).
W_ALWAYS = 0
W_CHARGING = 1
W_DISCHARGING = 2

# Tiers (``config.limits.TIERS`` order; the status shows 1 + tier, 0 = ok).
T_WARN = 0
T_DERATE = 1
T_TRIP = 2

# Derating curves (rows of ``curve_x`` / ``curve_y``).
C_CHG_V = 0
C_CHG_T = 1
C_CHG_SOC = 2
C_DSG_V = 3
C_DSG_T = 4
C_DSG_SOC = 5
N_CURVES = 6

# Reason codes (rows of the reason table in controller.py): entering a tier is code = tier.
WARNED = 0
DERATED = 1
TRIPPED = 2
CLEARED = 3
RESET = 4
"""Cleared by :func:`reset_trips` (emitted with the next step)."""

# Event slots.
S_ROW = 0
S_LIMIT = 1
S_TIER = 2
S_QUANTITY = 3
S_PATH = 4
S_VALUE = 5
S_THRESHOLD = 6
S_RESET = 7
S_MANUAL = 8
S_PACK_CHG = 9
S_PACK_DSG = 10
S_OP = 11

# Status channels after the ``n_ladders`` tier channels ``lim_<name>``, in order.
ST_LIMIT_CHG = 0
ST_LIMIT_DSG = 1
ST_PACK_CHG = 2
ST_PACK_DSG = 3


class LimitsParams(NamedTuple):
    quantity: I64
    """(R,) per row: ``Q_*``."""
    above: B1
    """(R,) violated above the threshold (else below)."""
    charge_path: B1
    """(R,) the row's path is charge (else discharge)."""
    when: I64
    """(R,) ``W_*``."""
    tier: I64
    """(R,) ``T_*``."""
    ladder: I64
    """(R,) index of the row's limit among the limits, in order of first appearance."""
    threshold: F64
    reset: F64
    debounce: I64
    delay_s: F64
    latch_s: F64
    """(R,) NaN where ``manual``."""
    manual: B1
    """(R,) ``latch_s = None``: only :func:`reset_trips` clears the row."""
    n_ladders: int
    curve_x: F64
    """(N_CURVES, K) input points, the first ``curve_n`` of each row valid."""
    curve_y: F64
    """(N_CURVES, K) C-rates."""
    curve_n: I64
    curve_min: F64
    """(N_CURVES,) smallest C-rate of each table (for a non-finite input)."""
    derate_fraction: float
    context_current_c: float


class LimitsState(NamedTuple):
    seen: I64
    """(P, B, R) consecutive violating samples (up to ``debounce``)."""
    held_s: F64
    """(P, B, R) time the violation persisted after the debounce."""
    active: B1
    active_s: F64
    clear_ok: B1
    """(P, B, R) the last sample allows clearing (past the reset value, or out of context)."""
    value: F64
    """(P, B, R) the row's quantity at the last step."""
    limit_chg_a: F64
    """(P, B) published charge current limit."""
    limit_dsg_a: F64
    pack_chg_a: F64
    """(P,) N x the smallest charge limit of the N batteries that can take charge."""
    pack_dsg_a: F64
    t_s: F64
    """(P,) time of the last step (NaN before the first)."""
    pending: I64
    """(P, B * R) rows cleared by :func:`reset_trips` since the last step, ``i * R + k``, in
    order; their events come with the next step."""
    n_pending: I64
    """(P,)."""
    values: F64
    """(P, N_QUANTITIES) scratch: the quantities of the battery being evaluated."""
    ctx: B1
    """(P, 3) scratch: its contexts."""


# ------------------------------------------------------------------------------ tables


@kernel
def curve_at(prm: LimitsParams, c: int, x: float) -> float:
    """Table ``c`` at ``x``, held constant beyond its end points; a non-finite input gets the
    table's smallest (safest) value."""
    if not math.isfinite(x):
        return float(prm.curve_min[c])
    # Indexed [c, j] through prm: a row slice or a local alias costs a reference count per call.
    last = prm.curve_n[c] - 1
    if x <= prm.curve_x[c, 0]:
        return float(prm.curve_y[c, 0])
    if x >= prm.curve_x[c, last]:
        return float(prm.curve_y[c, last])
    k = 1
    while prm.curve_x[c, k] <= x:  # bisect_right: the first point above x
        k += 1
    x0, x1 = prm.curve_x[c, k - 1], prm.curve_x[c, k]
    y0, y1 = prm.curve_y[c, k - 1], prm.curve_y[c, k]
    return float(y0 + (y1 - y0) * (x - x0) / (x1 - x0))


@kernel
def _temp_lookup(prm: LimitsParams, c: int, m: MeasArrays, p: int, i: int) -> float:
    """Hottest and coldest cell both limit (a table is low at both ends)."""
    hot = curve_at(prm, c, m.bat.temp_c[p, i])
    coldest = m.bat.min_temp_c[p, i]
    if math.isfinite(coldest):
        return fmin(hot, curve_at(prm, c, coldest))
    return hot


@kernel
def charge_c(prm: LimitsParams, m: MeasArrays, p: int, i: int) -> float:
    """Charge limit in C: the smallest of the cell-voltage, temperature and SOC tables."""
    a = curve_at(prm, C_CHG_V, m.bat.max_cell_v[p, i])
    b = _temp_lookup(prm, C_CHG_T, m, p, i)
    return fmin(fmin(a, b), curve_at(prm, C_CHG_SOC, m.bat.soc[p, i]))


@kernel
def discharge_c(prm: LimitsParams, m: MeasArrays, p: int, i: int) -> float:
    a = curve_at(prm, C_DSG_V, m.bat.min_cell_v[p, i])
    b = _temp_lookup(prm, C_DSG_T, m, p, i)
    return fmin(fmin(a, b), curve_at(prm, C_DSG_SOC, m.bat.soc[p, i]))


# ------------------------------------------------------------------------------ queries


@kernel
def tiers_into(prm: LimitsParams, st: LimitsState, p: int, i: int, out: F64, o0: int) -> None:
    """Highest active tier of every limit of battery ``i`` into ``out[p, i, o0 + ladder]``:
    0 ok, 1 + ``T_*`` otherwise."""
    for j in range(prm.n_ladders):
        out[p, i, o0 + j] = 0.0
    for k in range(prm.tier.shape[0]):
        if st.active[p, i, k] and prm.tier[k] + 1 > out[p, i, o0 + prm.ladder[k]]:
            out[p, i, o0 + prm.ladder[k]] = prm.tier[k] + 1


@kernel
def path_tiers(prm: LimitsParams, st: LimitsState, p: int, i: int) -> tuple[bool, bool, bool, bool]:
    """(charge tripped, discharge tripped, charge derated, discharge derated) for battery ``i``:
    some row of that tier and path is active."""
    trip_chg = trip_dsg = der_chg = der_dsg = False
    for k in range(prm.tier.shape[0]):
        if st.active[p, i, k]:
            if prm.tier[k] == T_TRIP:
                if prm.charge_path[k]:
                    trip_chg = True
                else:
                    trip_dsg = True
            elif prm.tier[k] == T_DERATE:
                if prm.charge_path[k]:
                    der_chg = True
                else:
                    der_dsg = True
    return trip_chg, trip_dsg, der_chg, der_dsg


# ------------------------------------------------------------------------------ events


@kernel
def _known(x: float) -> float:
    """An event's optional number: NaN (shown as None) unless finite."""
    return x if math.isfinite(x) else math.nan


@kernel
def _emit_row(
    prm: LimitsParams, ev: EventBuf, p: int, src: int, code: int, i: int, k: int, t_s: float,
    value: float,
) -> int:  # fmt: skip
    """Emit ``code`` for row ``k`` of battery ``i`` with the row's fields (the caller adds
    ``manual`` and the pack limits)."""
    e = emit(ev, p, src, code, i, t_s)
    ev.val[e, S_ROW] = k
    ev.val[e, S_LIMIT] = prm.ladder[k]
    ev.val[e, S_TIER] = prm.tier[k]
    ev.val[e, S_QUANTITY] = prm.quantity[k]
    ev.val[e, S_PATH] = 0 if prm.charge_path[k] else 1
    ev.val[e, S_VALUE] = _known(value)
    ev.val[e, S_THRESHOLD] = prm.threshold[k]
    ev.val[e, S_RESET] = prm.reset[k]
    ev.val[e, S_OP] = 0 if prm.above[k] else 1
    return e


@kernel
def _deactivate(st: LimitsState, p: int, i: int, k: int) -> None:
    st.active[p, i, k] = False
    st.active_s[p, i, k] = 0.0
    st.seen[p, i, k] = 0
    st.held_s[p, i, k] = 0.0


@kernel
def reset_trips(prm: LimitsParams, st: LimitsState, p: int, battery: int) -> int:
    """Explicit reset of pack ``p``: clear the active rows (any latch) of ``battery`` (every
    battery if negative) whose quantity is past its reset value. Returns how many rows cleared;
    their ``LimitReset`` events come with the next step."""
    n_bat, n_rows = st.active.shape[1], st.active.shape[2]
    lo, hi = (0, n_bat) if battery < 0 else (battery, min(battery + 1, n_bat))
    n = 0
    for i in range(lo, hi):
        for k in range(n_rows):
            if st.active[p, i, k] and st.clear_ok[p, i, k]:
                _deactivate(st, p, i, k)
                q = st.n_pending[p]
                if q < st.pending.shape[1]:  # always: a row is pending at most once
                    st.pending[p, q] = i * n_rows + k
                    st.n_pending[p] = q + 1
                n += 1
    return n


# ------------------------------------------------------------------------------ the step


@kernel
def _pack_limits(prm: LimitsParams, st: LimitsState, tp: PackArrays, m: MeasArrays, p: int) -> None:
    """Per-battery limits from the tables and the active tiers; the pack limits."""
    n_chg = 0
    n_dsg = 0
    min_chg = 0.0
    min_dsg = 0.0
    bad_chg = False
    bad_dsg = False
    for i in range(st.limit_chg_a.shape[1]):
        if not (m.bat.reported[p, i] and m.bat.present[p, i]):
            st.limit_chg_a[p, i] = 0.0
            st.limit_dsg_a[p, i] = 0.0
            continue
        cap = capacity_ah(tp, m, p, i)
        lim_chg = charge_c(prm, m, p, i) * cap
        lim_dsg = discharge_c(prm, m, p, i) * cap
        chg_trip, dsg_trip, chg_der, dsg_der = path_tiers(prm, st, p, i)
        if chg_trip:
            lim_chg = 0.0
        elif chg_der:
            lim_chg *= prm.derate_fraction  # once per path, however many derate rows
        if dsg_trip:
            lim_dsg = 0.0
        elif dsg_der:
            lim_dsg *= prm.derate_fraction
        st.limit_chg_a[p, i] = lim_chg
        st.limit_dsg_a[p, i] = lim_dsg
        if not chg_trip and conducts(tp, m, p, i, True):
            min_chg = lim_chg if n_chg == 0 else fmin(min_chg, lim_chg)
            bad_chg = bad_chg or not math.isfinite(lim_chg)
            n_chg += 1
        if not dsg_trip and conducts(tp, m, p, i, False):
            min_dsg = lim_dsg if n_dsg == 0 else fmin(min_dsg, lim_dsg)
            bad_dsg = bad_dsg or not math.isfinite(lim_dsg)
            n_dsg += 1
    st.pack_chg_a[p] = 0.0 if n_chg == 0 else (math.nan if bad_chg else float(n_chg) * min_chg)
    st.pack_dsg_a[p] = 0.0 if n_dsg == 0 else (math.nan if bad_dsg else float(n_dsg) * min_dsg)


@kernel
def step_pack(
    prm: LimitsParams, st: LimitsState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One tick of pack ``p``: rows, limits, opinions (trips open paths), status."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    n_bat, n_rows = st.active.shape[1], st.active.shape[2]
    for q in range(st.n_pending[p]):  # explicit resets since the last step, at its time
        i = st.pending[p, q] // n_rows
        k = st.pending[p, q] % n_rows
        e = _emit_row(prm, ev, p, src, RESET, i, k, st.t_s[p], st.value[p, i, k])
        ev.val[e, S_MANUAL] = 1.0
    st.n_pending[p] = 0
    st.t_s[p] = m.t_s[p]
    first = ev.n[0]
    docked = bool(m.docked[p])
    for i in range(n_bat):  # every row of battery i: count, time, activate or clear
        st.ctx[p, W_ALWAYS] = True
        if not (m.bat.reported[p, i] and m.bat.present[p, i]):
            for q in range(N_QUANTITIES):
                st.values[p, q] = math.nan
            st.ctx[p, W_CHARGING] = docked
            st.ctx[p, W_DISCHARGING] = False
        else:
            cap = capacity_ah(tp, m, p, i)
            cur = float(m.bat.current_a[p, i])  # without the JIT: no NumPy overflow warning
            temp = m.bat.temp_c[p, i]
            cold = m.bat.min_temp_c[p, i]
            st.values[p, Q_CELL_V_MAX] = m.bat.max_cell_v[p, i]
            st.values[p, Q_CELL_V_MIN] = m.bat.min_cell_v[p, i]
            if math.isfinite(cur):
                st.values[p, Q_CHG_C_RATE] = fmax(0.0, -cur) / cap
                st.values[p, Q_DSG_C_RATE] = fmax(0.0, cur) / cap
            else:
                st.values[p, Q_CHG_C_RATE] = math.nan
                st.values[p, Q_DSG_C_RATE] = math.nan
            st.values[p, Q_TEMP_MAX_C] = temp
            st.values[p, Q_TEMP_MIN_C] = cold if math.isfinite(cold) else temp
            band = prm.context_current_c * cap if math.isfinite(cap) else 0.0
            st.ctx[p, W_CHARGING] = docked or (math.isfinite(cur) and cur < -band)
            st.ctx[p, W_DISCHARGING] = math.isfinite(cur) and cur > band and not docked
        for k in range(prm.tier.shape[0]):
            v = st.values[p, prm.quantity[k]]
            st.value[p, i, k] = v
            violating = False
            if not st.ctx[p, prm.when[k]]:
                st.seen[p, i, k] = 0
                st.held_s[p, i, k] = 0.0
                st.clear_ok[p, i, k] = True
            elif not math.isfinite(v):
                st.clear_ok[p, i, k] = False  # unknown: hold counters and the active state
            else:
                if prm.above[k]:
                    violating = v > prm.threshold[k]
                    st.clear_ok[p, i, k] = v <= prm.reset[k]
                else:
                    violating = v < prm.threshold[k]
                    st.clear_ok[p, i, k] = v >= prm.reset[k]
                if violating:
                    if st.seen[p, i, k] >= prm.debounce[k]:
                        st.held_s[p, i, k] += dt
                    else:
                        st.seen[p, i, k] += 1
                        st.held_s[p, i, k] = 0.0
                else:
                    st.seen[p, i, k] = 0
                    st.held_s[p, i, k] = 0.0
            if st.active[p, i, k]:
                st.active_s[p, i, k] += dt
                if (
                    st.clear_ok[p, i, k]
                    and not prm.manual[k]
                    and st.active_s[p, i, k] >= prm.latch_s[k] - EPS
                ):
                    _deactivate(st, p, i, k)
                    e = _emit_row(prm, ev, p, src, CLEARED, i, k, m.t_s[p], v)
                    ev.val[e, S_MANUAL] = 0.0
            elif (
                violating
                and st.seen[p, i, k] >= prm.debounce[k]
                and st.held_s[p, i, k] >= prm.delay_s[k] - EPS
            ):
                st.active[p, i, k] = True
                st.active_s[p, i, k] = 0.0
                _emit_row(prm, ev, p, src, prm.tier[k], i, k, m.t_s[p], v)
    _pack_limits(prm, st, tp, m, p)
    for e in range(first, ev.n[0]):  # the pack limits after this tick, in this tick's events
        ev.val[e, S_PACK_CHG] = _known(st.pack_chg_a[p])
        ev.val[e, S_PACK_DSG] = _known(st.pack_dsg_a[p])
    any_chg_trip = False
    n_lad = prm.n_ladders
    for i in range(n_bat):
        chg_trip, dsg_trip, _, _ = path_tiers(prm, st, p, i)
        if chg_trip:
            put_chg(cmd, p, i, False)
            any_chg_trip = True
        if dsg_trip:
            put_dsg(cmd, p, i, False)
        tiers_into(prm, st, p, i, status, s0)
        status[p, i, s0 + n_lad + ST_LIMIT_CHG] = st.limit_chg_a[p, i]
        status[p, i, s0 + n_lad + ST_LIMIT_DSG] = st.limit_dsg_a[p, i]
        status[p, i, s0 + n_lad + ST_PACK_CHG] = st.pack_chg_a[p]
        status[p, i, s0 + n_lad + ST_PACK_DSG] = st.pack_dsg_a[p]
    if docked and any_chg_trip:
        put_charger_off(cmd, p)


@kernel
def step_packs(
    prm: LimitsParams, st: LimitsState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)
