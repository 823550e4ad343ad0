"""The supervisor's rules, compiled: the mode machine, the mode's own commands, and the relay
join limit, applied after every method and safety layer has written its opinion.

Modes: init → idle → discharge / charge → fault → shutdown. Methods keep running in every mode
(their timers and accumulators need continuous time); the mode decides what the supervisor
adds: charger off outside CHARGE and in FAULT, every path open in SHUTDOWN. The supervisor
learns trips, resets and faults from the events the other parts emitted in the same step
(their class comes from each part's reason table, ``SupParams.ev_class``).

The join limit refuses any command that would close a relay between batteries more than
``join_limit_v`` apart (the cross-charging current of two batteries a few volts apart behind
milliohms is hundreds of amperes) and logs the refusal once per episode.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import NO_OPINION, CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import emit, put_charger_off, put_chg, put_dsg
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

INIT, IDLE, DISCHARGE, CHARGE, FAULT, SHUTDOWN = 0, 1, 2, 3, 4, 5
MODES = ("init", "idle", "discharge", "charge", "fault", "shutdown")

# Event classes the supervisor reacts to (bits of SupParams.ev_class).
CLS_FAULT = 1
CLS_TRIP = 2
CLS_RESET = 4
FOREIGN_SRC = 15
"""Source id of events from a scalar (Python) part; their class travels in ``val[k, 0]``."""

# Reason codes.
MODE_CHANGED = 0
COMMAND_REFUSED = 1

ST_MODE = 0


class SupParams(NamedTuple):
    init_time_s: float
    discharge_current_a: float
    idle_after_s: float
    join_limit_v: float
    fault_hold_s: float
    shutdown_when_all_tripped: bool
    ev_class: I64
    """(sources, codes) class bits of every reason of every part."""


class SupState(NamedTuple):
    mode: I64
    """(P,)."""
    t_in_mode_s: F64
    quiet_s: F64
    since_fault_s: F64
    tripped: B1
    """(P, B)."""
    refused: B1
    accepted: I64
    """(P, B) scratch: batteries on the bus group, in the order they were accepted."""
    order: I64
    """(P, B) scratch: closing candidates sorted by voltage."""


FAULT_KINDS = frozenset({"Fault", "LimitTripped"})
TRIP_KINDS = frozenset({"ProtectionTripped", "LimitTripped"})
RESET_KINDS = frozenset({"ProtectionReset", "LimitReset"})


def event_class(kind: str) -> int:
    """Class bits of an event kind, as the supervisor reacts to it (built into ``ev_class``)."""
    return (
        (CLS_FAULT if kind in FAULT_KINDS else 0)
        | (CLS_TRIP if kind in TRIP_KINDS else 0)
        | (CLS_RESET if kind in RESET_KINDS else 0)
    )


@kernel_inline
def _class_of(prm: SupParams, ev: EventBuf, k: int) -> int:
    src = ev.src[k]
    if src == FOREIGN_SRC:
        return int(ev.val[k, 0])
    if src < prm.ev_class.shape[0] and ev.code[k] < prm.ev_class.shape[1]:
        return int(prm.ev_class[src, ev.code[k]])
    return 0


@kernel_inline
def _note_events(prm: SupParams, st: SupState, ev: EventBuf, p: int, k0: int) -> None:
    """React to the events this step's parts emitted for pack ``p`` (from row ``k0``)."""
    n_b = st.tripped.shape[1]
    for k in range(k0, ev.n[0]):
        if ev.pack[k] != p:
            continue
        cls = _class_of(prm, ev, k)
        b = ev.battery[k]
        if cls & CLS_FAULT:
            st.since_fault_s[p] = 0.0
        if cls & CLS_TRIP and 0 <= b < n_b:
            st.tripped[p, b] = True
        if cls & CLS_RESET and 0 <= b < n_b:
            st.tripped[p, b] = False


@kernel_inline
def _reported(m: MeasArrays, p: int) -> int:
    n = 0
    while n < m.bat.reported.shape[1] and m.bat.reported[p, n]:
        n += 1
    return n


@kernel_inline
def _next_mode(prm: SupParams, st: SupState, m: MeasArrays, p: int, dt_s: float) -> int:
    st.since_fault_s[p] += dt_s
    pack_a = 0.0
    for i in range(_reported(m, p)):
        cur = m.bat.current_a[p, i]
        if m.bat.present[p, i] and math.isfinite(cur):
            pack_a += cur
    if pack_a > prm.discharge_current_a:
        st.quiet_s[p] = 0.0
    else:
        st.quiet_s[p] += dt_s
    mode = st.mode[p]
    if mode == INIT:
        if st.t_in_mode_s[p] + dt_s < prm.init_time_s:
            return INIT
        mode = IDLE
    if st.since_fault_s[p] < prm.fault_hold_s:
        return FAULT
    n_b = st.tripped.shape[1]
    all_tripped = n_b > 0 and st.tripped[p].sum() >= n_b
    if m.docked[p]:
        return CHARGE
    if all_tripped and prm.shutdown_when_all_tripped:
        return SHUTDOWN
    if pack_a > prm.discharge_current_a:
        return DISCHARGE
    if mode == DISCHARGE and st.quiet_s[p] < prm.idle_after_s:
        return DISCHARGE
    return IDLE


@kernel_inline
def _will_close(tp: PackArrays, m: MeasArrays, cmd: CmdArrays, p: int, i: int) -> bool:
    c = m.bat.sw_chg[p, i] if cmd.chg_on[p, i] == NO_OPINION else cmd.chg_on[p, i] == 1
    d = m.bat.sw_dsg[p, i] if cmd.dsg_on[p, i] == NO_OPINION else cmd.dsg_on[p, i] == 1
    return bool(tp.relay[i] and c and d and m.bat.present[p, i])


@kernel_inline
def _closed_now(tp: PackArrays, m: MeasArrays, p: int, i: int) -> bool:
    return bool(tp.relay[i] and m.bat.sw_chg[p, i] and m.bat.sw_dsg[p, i])


@kernel_inline
def _is_accepted(st: SupState, p: int, na: int, i: int) -> bool:
    for k in range(na):  # noqa: SIM110 - compiled: a plain loop
        if st.accepted[p, k] == i:
            return True
    return False


@kernel_inline
def _seed_group(prm: SupParams, st: SupState, m: MeasArrays, p: int, nc: int) -> int:
    """Nothing on the bus yet: the largest set of candidates within the limit (ties: the
    lowest voltages, where staged charging starts). Returns its size (into ``accepted``)."""
    v = m.bat.voltage_v
    best_a, best_n = 0, 0
    for a in range(nc):
        lo = v[p, st.order[p, a]]
        n = 0
        for b in range(a, nc):
            if v[p, st.order[p, b]] - lo <= prm.join_limit_v:
                n += 1
        if n > best_n:
            best_a, best_n = a, n
    na = 0
    lo = v[p, st.order[p, best_a]]
    for b in range(best_a, nc):
        j = st.order[p, b]
        if v[p, j] - lo <= prm.join_limit_v:
            st.accepted[p, na] = j
            na += 1
    return na


@kernel_inline
def _join_limit(
    prm: SupParams, st: SupState, tp: PackArrays, m: MeasArrays, p: int, cmd: CmdArrays,
    ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """Refuse closing a relay onto batteries more than ``join_limit_v`` away."""
    n = min(st.refused.shape[1], _reported(m, p))
    v = m.bat.voltage_v
    any_closing = False
    for i in range(n):
        if _will_close(tp, m, cmd, p, i) and not _closed_now(tp, m, p, i):
            any_closing = True
    if not any_closing:
        st.refused[p].fill(False)
        return
    na = 0
    for i in range(n):
        if _closed_now(tp, m, p, i) and _will_close(tp, m, cmd, p, i):
            st.accepted[p, na] = i
            na += 1
    nc = 0  # closing candidates with a finite voltage, stably sorted by voltage
    for i in range(n):
        closing = _will_close(tp, m, cmd, p, i) and not _closed_now(tp, m, p, i)
        if closing and math.isfinite(v[p, i]):
            k = nc
            while k > 0 and v[p, st.order[p, k - 1]] > v[p, i]:
                st.order[p, k] = st.order[p, k - 1]
                k -= 1
            st.order[p, k] = i
            nc += 1
    if na == 0 and nc > 0:
        na = _seed_group(prm, st, m, p, nc)
    limit = prm.join_limit_v
    for i in range(n):
        if not (_will_close(tp, m, cmd, p, i) and not _closed_now(tp, m, p, i)):
            continue
        if _is_accepted(st, p, na, i):
            st.refused[p, i] = False
            continue
        vi = v[p, i]
        spread = 0.0
        hi = lo = vi
        if na > 0:
            first = v[p, st.accepted[p, 0]]
            spread = abs(vi - first)
            hi = lo = first
            for k in range(1, na):
                o = v[p, st.accepted[p, k]]
                d = abs(vi - o)
                if d > spread:
                    spread = d
                if o > hi:
                    hi = o
                if o < lo:
                    lo = o
            if vi > hi:
                hi = vi
            if vi < lo:
                lo = vi
        if math.isfinite(vi) and hi - lo <= limit:
            st.accepted[p, na] = i
            na += 1
            st.refused[p, i] = False
            continue
        cmd.chg_on[p, i] = 0
        cmd.dsg_on[p, i] = 0
        if not st.refused[p, i]:
            k = emit(ev, p, src, COMMAND_REFUSED, i, m.t_s[p])
            ev.val[k, 0] = vi
            ev.val[k, 1] = spread
            ev.val[k, 2] = limit
        st.refused[p, i] = True


@kernel_inline
def supervise_pack(
    prm: SupParams, st: SupState, tp: PackArrays, m: MeasArrays, p: int, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, k0: int, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """The supervisor's step for pack ``p``, after the parts wrote rows ``k0..`` of ``ev``."""
    _note_events(prm, st, ev, p, k0)
    new = _next_mode(prm, st, m, p, dt_s)
    old = st.mode[p]
    if new != old:
        k = emit(ev, p, src, MODE_CHANGED, -1, m.t_s[p])
        ev.val[k, 0] = old
        ev.val[k, 1] = new
        st.mode[p] = new
        st.t_in_mode_s[p] = 0.0
    else:
        st.t_in_mode_s[p] += dt_s
    mode = st.mode[p]
    n_b = st.tripped.shape[1]
    if mode == SHUTDOWN:
        for i in range(n_b):
            put_chg(cmd, p, i, False)
            put_dsg(cmd, p, i, False)
    if mode != CHARGE:
        put_charger_off(cmd, p)
    _join_limit(prm, st, tp, m, p, cmd, ev, src)
    for i in range(n_b):
        status[p, i, s0 + ST_MODE] = mode


@kernel
def supervise_packs(
    prm: SupParams, st: SupState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, k0: int, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        supervise_pack(prm, st, tp, m, p, dt_s, cmd, ev, k0, src, status, s0)
