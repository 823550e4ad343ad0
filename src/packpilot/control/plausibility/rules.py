"""Sensor and switch plausibility rules, compiled: detect lying measurements and failed
switches, fail safe.

Limits and method controllers trust the numbers they get; this monitor decides whether those
numbers (and the switches) can be trusted. Per battery it detects

- ``nonfinite``: NaN / inf in a field a controller relies on;
- ``out_of_range``: a value outside its physical range (cell, group and battery voltage,
  temperature, current in C, SOC), or min cell above max cell;
- ``stuck``: a voltage (or temperature) that has not changed *at all* for a configured time
  while the battery carries current (a frozen ADC or a dead CAN source repeating its last
  frame); ``stale``: a per-battery ``sample_age_s`` above a limit (NaN = not reported);
- ``voltage_sum``: battery voltage disagreeing with the sum of its group voltages;
  ``group_count``: a group-voltage tuple of the wrong length;
- switch feedback disagreeing with the last command for longer than a delay: a welded or
  stuck-open relay, a shorted or stuck-open charge / discharge FET.

Each detection latches one ``Fault`` event (data: battery, kind, field, value, reaction) and a
fail-safe reaction expressed as commands; see ``docs/safety.md`` for the table. Sensor faults
clear by themselves after ``clear_after_s`` of plausible data; switch faults only through
:func:`clear_faults_pack` (a service action, whose ``FaultCleared`` events come with the next
step). The last command is learnt through :func:`note_commands_pack`, which the supervisor
calls with the *merged* commands after every step.

A detector's *finding* each step is a tuple ``(state, field, value, value_kind)``: state
``NONE`` (cannot be judged: hold every timer), ``OK`` or ``BAD``; ``field`` a label index
(:data:`FIELDS`, then ``group_voltages_v[g]`` from :data:`F_GROUP0`); ``value_kind`` how the
value is shown (the scalar monitor's ``_show``: a finite number as a float, NaN / inf as text).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import NO_OPINION, CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.battery import capacity_ah, conducts
from packpilot.control.commands import emit, put_charger_off, put_chg, put_dsg
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I8 = NDArray[np.int8]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

EPS = 1e-9

# Detector kinds (their order is the order they are judged and their events are emitted).
SENSOR_KINDS: tuple[str, ...] = (
    "nonfinite",
    "out_of_range",
    "stuck",
    "stale",
    "voltage_sum",
    "group_count",
)
SWITCH_KINDS: tuple[str, ...] = (
    "relay_welded",
    "relay_stuck_open",
    "chg_fet_shorted",
    "dsg_fet_shorted",
    "chg_fet_stuck_open",
    "dsg_fet_stuck_open",
)
KINDS = SENSOR_KINDS + SWITCH_KINDS
K_NONFINITE = 0
K_RANGE = 1
K_STUCK = 2
K_STALE = 3
K_SUM = 4
K_COUNT = 5
K_RELAY_WELDED = 6
K_RELAY_STUCK_OPEN = 7
K_CHG_SHORTED = 8
K_DSG_SHORTED = 9
K_CHG_STUCK_OPEN = 10
K_DSG_STUCK_OPEN = 11
N_KINDS = 12
N_SENSOR_KINDS = 6

# Field labels (the quantity a finding is about).
FIELDS: tuple[str, ...] = (
    "",
    "voltage_v",
    "current_a",
    "temp_c",
    "min_cell_v",
    "max_cell_v",
    "soc",
    "min_temp_c",
    "sample_age_s",
    "group_voltages_v",
    "voltage_v-sum(group_voltages_v)",
    "min_cell_v>max_cell_v",
    "switch",
    "switch.chg_on",
    "switch.dsg_on",
    "bus_v",
    "load_current_a",
)
F_NONE = 0
F_VOLTAGE = 1
F_CURRENT = 2
F_TEMP = 3
F_MIN_CELL = 4
F_MAX_CELL = 5
F_SOC = 6
F_MIN_TEMP = 7
F_SAMPLE_AGE = 8
F_GROUPS = 9
F_SUM = 10
F_MINMAX = 11
F_SWITCH = 12
F_SW_CHG = 13
F_SW_DSG = 14
F_BUS = 15
F_LOAD = 16
F_GROUP0 = 17
"""``group_voltages_v[g]`` is label ``F_GROUP0 + g``."""

# How a finding's value reads in the event.
V_FLOAT = 0
"""A float as it is (also when not finite)."""
V_SHOW = 1
"""A float if finite, else its text (``"nan"``, ``"inf"``, ``"-inf"``)."""
V_BOOL = 2
V_INT = 3
NONFINITE_TEXT: tuple[str, ...] = ("nan", "inf", "-inf")

# Finding states.
NONE = -1
OK = 0
BAD = 1

# Reactions (labels of a Fault event).
REACTIONS: tuple[str, ...] = (
    "charger_off",
    "charger_off (welded relay: cannot isolate)",
    "isolate (kept as reserve)",
    "isolate + charger_off until open",
    "keep_supplying (last source in flight)",
    "open_charge_path, keep_supplying (last source in flight)",
    "charger_off; relay never used to isolate",
    "command_open",
    "flag_only (discharge cannot be interrupted)",
    "command_chg_off",
    "command_dsg_off",
)
R_CHARGER_OFF = 0
R_WELDED_NO_ISOLATE = 1
R_ISOLATE = 2
R_ISOLATE_DOCKED = 3
R_KEEP_SUPPLYING = 4
R_OPEN_CHARGE_KEEP = 5
R_RELAY_WELDED = 6
R_COMMAND_OPEN = 7
R_FLAG_ONLY = 8
R_COMMAND_CHG_OFF = 9
R_COMMAND_DSG_OFF = 10

# Reason codes (rows of the reason table in controller.py).
FAULT_FLOAT = 0
FAULT_TEXT = 1
FAULT_BOOL = 2
FAULT_INT = 3
PACK_FAULT = 4
CLEARED = 5
CLEARED_MANUAL = 6
PACK_CLEARED = 7
PACK_CLEARED_MANUAL = 8
RESERVE_ENGAGED = 9

# Event value slots.
SLOT_BATTERY = 0
SLOT_KIND = 1
SLOT_FIELD = 2
SLOT_VALUE = 3
SLOT_REACTION = 4
SLOT_MANUAL = 3

# Status channels, in order.
ST_FAULTS = 0
ST_ISOLATED = 1

# Stuck-sensor tracks: these four, then one per group voltage.
T_VOLTAGE = 0
T_MIN_CELL = 1
T_MAX_CELL = 2
T_TEMP = 3
T_GROUP0 = 4


class PlausibilityParams(NamedTuple):
    cell_lo: float
    cell_hi: float
    temp_lo: float
    temp_hi: float
    cur_lo: float
    cur_hi: float
    soc_lo: float
    soc_hi: float
    nonfinite_delay_s: float
    range_delay_s: float
    stuck_on: bool
    stuck_time_s: float
    stuck_temp_on: bool
    stuck_temp_time_s: float
    stuck_current_c: float
    max_sample_age_s: float
    sum_tolerance_v_per_group: float
    sum_delay_s: float
    switch_delay_s: float
    clear_after_s: float
    max_groups: int
    """Series groups of the largest battery (how many ``group_voltages_v[g]`` labels)."""


class PlausibilityState(NamedTuple):
    bad_s: F64
    """(P, B + 1, N_KINDS) persistence timer of each detector; row B is the pack's."""
    ok_s: F64
    was_bad: B1
    latched: B1
    field: I64
    """Field label of a latched detector (F_NONE otherwise)."""
    last: F64
    """(P, B, T_GROUP0 + groups) last value of each stuck-sensor track (NaN: none yet)."""
    unchanged_s: F64
    cmd_chg: I8
    """(P, B) last merged command: NO_OPINION (none yet), 0 or 1."""
    cmd_dsg: I8
    isolated: B1
    """(P, B) isolated by the last step's reaction."""
    t_s: F64
    """(P,) time of the last step (service-reset events carry it)."""
    pend_n: I64
    """(P,) service resets waiting for the next step's events ..."""
    pend_bat: I64
    """... (P, Q): battery (-1: the pack), ..."""
    pend_kind: I64
    pend_field: I64
    pend_t: F64


Finding = tuple[int, int, float, int]


@kernel_inline
def _out(x: float, lo: float, hi: float) -> bool:
    return math.isfinite(x) and not (lo <= x and x <= hi)


@kernel_inline
def _ok() -> Finding:
    return (OK, F_NONE, math.nan, V_FLOAT)


@kernel_inline
def _none() -> Finding:
    return (NONE, F_NONE, math.nan, V_FLOAT)


# ------------------------------------------------------------------------------ detections
#
# The detections are functions of the battery's readings as numbers (and of its group-voltage
# row ``gv[p, i, :ng]``), not of the named tuples: a helper with branches that holds a tuple of
# arrays pays a reference-count pair for every array of it on every call (microseconds).


@kernel_inline
def _nonfinite(
    v: float, cur: float, temp: float, vmin: float, vmax: float, soc: float, tmin: float,
    gv: F64, p: int, i: int, ng: int,
) -> Finding:  # fmt: skip
    if not math.isfinite(v):
        return (BAD, F_VOLTAGE, v, V_SHOW)
    if not math.isfinite(cur):
        return (BAD, F_CURRENT, cur, V_SHOW)
    if not math.isfinite(temp):
        return (BAD, F_TEMP, temp, V_SHOW)
    if not math.isfinite(vmin):
        return (BAD, F_MIN_CELL, vmin, V_SHOW)
    if not math.isfinite(vmax):
        return (BAD, F_MAX_CELL, vmax, V_SHOW)
    if not math.isfinite(soc):
        return (BAD, F_SOC, soc, V_SHOW)
    if math.isinf(tmin):
        return (BAD, F_MIN_TEMP, tmin, V_SHOW)  # NaN = not measured
    for g in range(ng):
        x = gv[p, i, g]
        if not math.isfinite(x):
            return (BAD, F_GROUP0 + g, x, V_SHOW)
    return _ok()


@kernel_inline
def _range(
    prm: PlausibilityParams, groups: int, per_group: int, v: float, cur: float, temp: float,
    tmin: float, vmin: float, vmax: float, soc: float, gv: F64, p: int, i: int, ng: int,
    cap: float,
) -> Finding:  # fmt: skip
    lo_v, hi_v = prm.cell_lo, prm.cell_hi
    if _out(vmin, lo_v, hi_v):
        return (BAD, F_MIN_CELL, vmin, V_SHOW)
    if _out(vmax, lo_v, hi_v):
        return (BAD, F_MAX_CELL, vmax, V_SHOW)
    if _out(temp, prm.temp_lo, prm.temp_hi):
        return (BAD, F_TEMP, temp, V_SHOW)
    if _out(tmin, prm.temp_lo, prm.temp_hi):
        return (BAD, F_MIN_TEMP, tmin, V_SHOW)
    if _out(soc, prm.soc_lo, prm.soc_hi):
        return (BAD, F_SOC, soc, V_SHOW)
    if groups != 0 and per_group != 0:
        s = groups * per_group
        if _out(v, lo_v * s, hi_v * s):
            return (BAD, F_VOLTAGE, v, V_SHOW)
        for g in range(ng):
            x = gv[p, i, g]
            if _out(x, lo_v * per_group, hi_v * per_group):
                return (BAD, F_GROUP0 + g, x, V_SHOW)
    if math.isfinite(cap) and math.isfinite(cur):
        x = cur / cap
        if _out(x, prm.cur_lo, prm.cur_hi):
            return (BAD, F_CURRENT, x, V_SHOW)
    if math.isfinite(vmin) and math.isfinite(vmax) and vmin > vmax:
        return (BAD, F_MINMAX, vmin - vmax, V_SHOW)
    return _ok()


@kernel_inline
def _track(
    last: F64, unchanged: F64, p: int, i: int, j: int, x: float, loaded: bool, dt: float
) -> float:
    """Advance stuck-sensor track ``j``; returns how long its value has not changed."""
    u = unchanged[p, i, j]
    if x != last[p, i, j]:  # a change (or NaN) proves nothing is frozen
        last[p, i, j] = x
        u = 0.0
    elif loaded:
        u += dt
    unchanged[p, i, j] = u
    return float(u)


@kernel_inline
def _stuck(
    prm: PlausibilityParams, last: F64, unchanged: F64, p: int, i: int, v: float, vmin: float,
    vmax: float, temp: float, gv: F64, ng: int, cur: float, cap: float, dt: float,
) -> Finding:  # fmt: skip
    scale = cap if math.isfinite(cap) else 1.0
    loaded = math.isfinite(cur) and abs(cur) >= prm.stuck_current_c * scale
    hit = False
    field = F_NONE
    value = math.nan
    for j in range(T_GROUP0 + ng):
        if j == T_TEMP:
            if not prm.stuck_temp_on:
                continue
            limit = prm.stuck_temp_time_s - EPS
        else:
            if not prm.stuck_on:
                continue
            limit = prm.stuck_time_s - EPS
        if j == T_VOLTAGE:
            x, f = v, F_VOLTAGE
        elif j == T_MIN_CELL:
            x, f = vmin, F_MIN_CELL
        elif j == T_MAX_CELL:
            x, f = vmax, F_MAX_CELL
        elif j == T_TEMP:
            x, f = temp, F_TEMP
        else:
            x, f = gv[p, i, j - T_GROUP0], F_GROUP0 + j - T_GROUP0
        if _track(last, unchanged, p, i, j, x, loaded, dt) >= limit and not hit:
            hit, field, value = True, f, x
    if hit:
        return (BAD, field, value, V_SHOW)
    return _ok()


@kernel_inline
def _stale(prm: PlausibilityParams, age: float) -> Finding:
    if math.isnan(age):
        return _none()  # not reported (NaN means "unknown", not "stale")
    if not math.isfinite(age) or age > prm.max_sample_age_s:
        return (BAD, F_SAMPLE_AGE, age, V_SHOW)
    return _ok()


@kernel_inline
def _group_count(groups: int, n_groups: int) -> Finding:
    if groups != 0 and n_groups != 0 and n_groups != groups:
        return (BAD, F_GROUPS, float(n_groups), V_INT)
    return _ok()


@kernel_inline
def _sum(
    prm: PlausibilityParams, groups: int, n_groups: int, v: float, gv: F64, p: int, i: int
) -> Finding:
    if groups == 0 or n_groups != groups:
        return _none()
    if not math.isfinite(v):
        return _none()
    for g in range(groups):
        if not math.isfinite(gv[p, i, g]):
            return _none()
    total = 0.0
    for g in range(groups):
        total += gv[p, i, g]
    diff = v - total
    if abs(diff) > prm.sum_tolerance_v_per_group * groups:
        return (BAD, F_SUM, diff, V_FLOAT)
    return _ok()


@kernel_inline
def _switch(relay: bool, chg: int, dsg: int, fb_chg: bool, fb_dsg: bool, k: int) -> Finding:
    """Switch detector ``k``: feedback against the last merged command."""
    if relay:
        if k > K_RELAY_STUCK_OPEN or chg == NO_OPINION or dsg == NO_OPINION:
            return _none()
        want = chg == 1 and dsg == 1
        closed = fb_chg and fb_dsg
        bad = (not want and closed) if k == K_RELAY_WELDED else (want and not closed)
        return (BAD if bad else OK, F_SWITCH, 1.0 if closed else 0.0, V_BOOL)
    if k in (K_CHG_SHORTED, K_CHG_STUCK_OPEN):
        cmd, got, f = chg, fb_chg, F_SW_CHG
    elif k in (K_DSG_SHORTED, K_DSG_STUCK_OPEN):
        cmd, got, f = dsg, fb_dsg, F_SW_DSG
    else:
        return _none()
    if cmd == NO_OPINION:
        return _none()
    shorted = k in (K_CHG_SHORTED, K_DSG_SHORTED)
    bad = (cmd == 0 and got) if shorted else (cmd == 1 and not got)
    return (BAD if bad else OK, f, 1.0 if got else 0.0, V_BOOL)


@kernel_inline
def _pack_finding(bus_v: float, load_a: float) -> Finding:
    if not math.isfinite(bus_v):
        return (BAD, F_BUS, bus_v, V_SHOW)
    if not math.isfinite(load_a):
        return (BAD, F_LOAD, load_a, V_SHOW)
    return _ok()


# ------------------------------------------------------------------------------ reactions


@kernel_inline
def _sensor_bad(latched: B1, p: int, i: int) -> bool:
    for k in range(N_SENSOR_KINDS):  # noqa: SIM110 - no generators in a kernel
        if latched[p, i, k]:
            return True
    return False


@kernel_inline
def _stays_on(tp: PackArrays, cmd: CmdArrays, p: int, j: int) -> bool:
    """No layer before this one opened battery ``j``'s discharge path in this step (a relay
    opens when either of its commands is off)."""
    if cmd.dsg_on[p, j] == 0:
        return False
    return not (tp.relay[j] and cmd.chg_on[p, j] == 0)


@kernel_inline
def _other_source(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays, p: int, i: int
) -> bool:  # fmt: skip
    """Another battery with trusted sensors carries the load now (switch feedback) and keeps
    carrying it after this step (no layer opened it this step).

    The second half is what makes the hand-over to a reserve make-before-break: this layer runs
    after the methods and the limits, so when protection trips the last trusted source in this
    step, the reserve's isolation is lifted in the same step its path opens."""
    for j in range(st.cmd_chg.shape[1]):
        if j == i or not (m.bat.reported[p, j] and m.bat.present[p, j]):
            continue
        if _sensor_bad(st.latched, p, j):
            continue
        if conducts(tp, m, p, j, False) and _stays_on(tp, cmd, p, j):
            return True
    return False


@kernel_inline
def _reaction(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays, p: int, i: int, k: int
) -> int:  # fmt: skip
    """What the commands will do about a new fault (for the event; see ``_output``)."""
    if i < 0:
        return R_CHARGER_OFF
    if k < N_SENSOR_KINDS:
        if st.latched[p, i, K_RELAY_WELDED]:
            return R_WELDED_NO_ISOLATE
        if m.docked[p]:
            return R_ISOLATE_DOCKED
        if _other_source(st, tp, m, cmd, p, i):
            return R_ISOLATE
        if tp.relay[i]:
            return R_KEEP_SUPPLYING
        return R_OPEN_CHARGE_KEEP
    if k == K_RELAY_WELDED:
        return R_RELAY_WELDED
    if k == K_RELAY_STUCK_OPEN:
        return R_COMMAND_OPEN
    if k == K_CHG_SHORTED:
        return R_CHARGER_OFF
    if k == K_DSG_SHORTED:
        return R_FLAG_ONLY
    if k == K_CHG_STUCK_OPEN:
        return R_COMMAND_CHG_OFF
    return R_COMMAND_DSG_OFF


# ------------------------------------------------------------------------------ latching

HOLD = 0
LATCH = 1
CLEAR = 2


@kernel_inline
def _advance(
    state: int, bad_s: float, ok_s: float, was_bad: bool, latched: bool, delay: float,
    auto_clear: bool, dt: float, clear_after_s: float,
) -> tuple[int, float, float, bool]:  # fmt: skip
    """Persistence timer and latch of one detector given its finding's state: returns (what to
    do: HOLD, LATCH or CLEAR; the new bad_s, ok_s and was_bad)."""
    if state == NONE:
        return (HOLD, bad_s, ok_s, was_bad)  # not judgeable now: hold every timer
    if state == BAD:
        bad_s = bad_s + dt if was_bad else 0.0
        if not latched and bad_s >= delay - EPS:
            return (LATCH, bad_s, 0.0, True)
        return (HOLD, bad_s, 0.0, True)
    ok_s = ok_s + dt if not was_bad else 0.0
    if latched and auto_clear and ok_s >= clear_after_s - EPS:
        return (CLEAR, 0.0, ok_s, False)
    return (HOLD, 0.0, ok_s, False)


@kernel_inline
def _nonfinite_code(x: float) -> float:
    """Label index of the text of a non-finite value (:data:`NONFINITE_TEXT`)."""
    if math.isnan(x):
        return 0.0
    return 1.0 if x > 0.0 else 2.0


@kernel_inline
def _emit_fault(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays, p: int, i: int,
    k: int, f: Finding, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    reaction = _reaction(st, tp, m, cmd, p, i, k)
    value, vk = f[2], f[3]
    if i < 0:
        code = PACK_FAULT
    elif vk == V_BOOL:
        code = FAULT_BOOL
    elif vk == V_INT:
        code = FAULT_INT
    elif vk == V_SHOW and not math.isfinite(value):
        code = FAULT_TEXT
    else:
        code = FAULT_FLOAT
    e = emit(ev, p, src, code, i, m.t_s[p])
    ev.val[e, SLOT_BATTERY] = float(i) if i >= 0 else math.nan
    ev.val[e, SLOT_KIND] = k
    ev.val[e, SLOT_FIELD] = f[1]
    text = code in (FAULT_TEXT, PACK_FAULT)
    ev.val[e, SLOT_VALUE] = _nonfinite_code(value) if text else value
    ev.val[e, SLOT_REACTION] = reaction


@kernel_inline
def _emit_cleared(
    ev: EventBuf, p: int, src: int, battery: int, kind: int, field: int, manual: bool,
    t_s: float,
) -> None:  # fmt: skip
    if battery < 0:
        code = PACK_CLEARED_MANUAL if manual else PACK_CLEARED
    else:
        code = CLEARED_MANUAL if manual else CLEARED
    e = emit(ev, p, src, code, battery, t_s)
    ev.val[e, SLOT_BATTERY] = float(battery) if battery >= 0 else math.nan
    ev.val[e, SLOT_KIND] = kind
    ev.val[e, SLOT_FIELD] = field
    ev.val[e, SLOT_MANUAL] = 1.0 if manual else 0.0


@kernel_inline
def _reset(st: PlausibilityState, p: int, row: int, k: int) -> None:
    st.latched[p, row, k] = False
    st.bad_s[p, row, k] = 0.0
    st.ok_s[p, row, k] = 0.0
    st.was_bad[p, row, k] = False
    st.field[p, row, k] = F_NONE


@kernel_inline
def _act(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays, p: int, row: int,
    k: int, f: Finding, action: int, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """Latch detector ``k`` of battery ``row`` (B: the pack) with a ``Fault`` event, or clear it
    with a ``FaultCleared`` event (the rare path, kept out of the per-detector loop)."""
    i = row if row < st.cmd_chg.shape[1] else -1
    if action == LATCH:
        st.latched[p, row, k] = True
        st.field[p, row, k] = f[1]
        _emit_fault(st, tp, m, cmd, p, i, k, f, ev, src)
    else:
        _emit_cleared(ev, p, src, i, k, int(st.field[p, row, k]), False, m.t_s[p])
        _reset(st, p, row, k)


@kernel_inline
def _flush_resets(st: PlausibilityState, p: int, ev: EventBuf, src: int) -> None:
    """The ``FaultCleared`` events of the service resets since the previous step."""
    for q in range(st.pend_n[p]):
        _emit_cleared(ev, p, src, int(st.pend_bat[p, q]), int(st.pend_kind[p, q]),
                      int(st.pend_field[p, q]), True, st.pend_t[p, q])  # fmt: skip
    st.pend_n[p] = 0


@kernel_inline
def _output(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, cmd: CmdArrays, status: F64,
    s0: int, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    """The fail-safe commands of every latched fault, and the status channels.

    Degraded mode in flight (docs/fault_injection.md): a battery with a failed sensor is a
    *reserve*, isolated while a trusted battery carries the load and brought in (charge path
    still off: nothing may charge a battery we cannot see) in the step the last trusted source
    stops, with a ``ReserveEngaged`` event that tells the platform."""
    n = st.cmd_chg.shape[1]
    lat = st.latched
    charger_off = bool(lat[p, n, K_NONFINITE])
    docked = m.docked[p]
    for i in range(n):
        welded = lat[p, i, K_RELAY_WELDED]
        chg_off = False
        dsg_off = False
        isolated = False
        if lat[p, i, K_RELAY_STUCK_OPEN]:
            chg_off = dsg_off = True
        if lat[p, i, K_CHG_STUCK_OPEN]:
            chg_off = True
        if lat[p, i, K_DSG_STUCK_OPEN]:
            dsg_off = True
        sensor_bad = _sensor_bad(lat, p, i)
        if sensor_bad and not welded:
            if docked or _other_source(st, tp, m, cmd, p, i):
                chg_off = dsg_off = True
                isolated = True
            elif not tp.relay[i]:
                chg_off = True  # discharge still flows through the charge FET's body diode
        unsafe = sensor_bad or welded or lat[p, i, K_CHG_SHORTED]
        can_take_charge = m.bat.reported[p, i] and m.bat.present[p, i]
        if unsafe and can_take_charge and conducts(tp, m, p, i, True):
            charger_off = True  # never charge into a battery we cannot see or cannot block
        if chg_off:
            put_chg(cmd, p, i, False)
        if dsg_off:
            put_dsg(cmd, p, i, False)
        if st.isolated[p, i] and not isolated and sensor_bad and not docked:
            e = emit(ev, p, src, RESERVE_ENGAGED, i, m.t_s[p])
            ev.val[e, SLOT_BATTERY] = float(i)
        st.isolated[p, i] = isolated
        mask = 0
        for k in range(N_KINDS):
            if lat[p, i, k]:
                mask |= 1 << k
        status[p, i, s0 + ST_FAULTS] = mask
        status[p, i, s0 + ST_ISOLATED] = 1.0 if isolated else 0.0
    if charger_off:
        put_charger_off(cmd, p)


@kernel_inline
def step_pack(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    dt_s: float, cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One step of pack ``p``: pending service resets, every detector of every battery (in the
    order of :data:`KINDS`), the pack's bus and load readings, then the reactions as commands
    and the status channels.

    One function on purpose: the named tuples are handed on only on the rare paths (a latch, a
    clear), so their reference counts are paid once per pack-step, not once per detector.
    """
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    st.t_s[p] = m.t_s[p]
    if st.pend_n[p] > 0:
        _flush_resets(st, p, ev, src)
    n = st.cmd_chg.shape[1]
    gv = m.bat.group_v
    for i in range(n):
        if not (m.bat.reported[p, i] and m.bat.present[p, i]):
            continue  # absent: nothing can be judged, every timer holds
        cap = capacity_ah(tp, m, p, i)
        v = m.bat.voltage_v[p, i]
        cur = m.bat.current_a[p, i]
        temp = m.bat.temp_c[p, i]
        tmin = m.bat.min_temp_c[p, i]
        vmin = m.bat.min_cell_v[p, i]
        vmax = m.bat.max_cell_v[p, i]
        soc = m.bat.soc[p, i]
        n_groups = int(m.bat.n_groups[p, i])
        # the group voltages the arrays hold (all of them, unless a misbehaving monitor
        # reported more than the arrays have room for)
        ng = min(n_groups, gv.shape[2], st.last.shape[2] - T_GROUP0)
        groups, per_group = int(tp.groups[i]), int(tp.cells_per_group[i])
        for k in range(N_KINDS):
            if k == K_NONFINITE:
                f = _nonfinite(v, cur, temp, vmin, vmax, soc, tmin, gv, p, i, ng)
                delay = prm.nonfinite_delay_s
            elif k == K_RANGE:
                f = _range(prm, groups, per_group, v, cur, temp, tmin, vmin, vmax, soc, gv, p,
                           i, ng, cap)  # fmt: skip
                delay = prm.range_delay_s
            elif k == K_STUCK:
                f = _stuck(prm, st.last, st.unchanged_s, p, i, v, vmin, vmax, temp, gv, ng,
                           cur, cap, dt)  # fmt: skip
                delay = 0.0
            elif k == K_STALE:
                f = _stale(prm, m.bat.sample_age_s[p, i])
                delay = 0.0
            elif k == K_SUM:
                f = _sum(prm, groups, n_groups, v, gv, p, i)
                delay = prm.sum_delay_s
            elif k == K_COUNT:
                f = _group_count(groups, n_groups)
                delay = 0.0
            elif _stale(prm, m.bat.sample_age_s[p, i])[0] == BAD:
                f = _none()  # a stale sample's feedback says nothing about the switch now
                delay = prm.switch_delay_s
            elif m.bat.sw_explained[p, i]:
                f = _none()  # the node opened on its timeout / has not heard us yet (#26)
                delay = prm.switch_delay_s
            else:
                f = _switch(tp.relay[i], int(st.cmd_chg[p, i]), int(st.cmd_dsg[p, i]),
                            m.bat.sw_chg[p, i], m.bat.sw_dsg[p, i], k)  # fmt: skip
                delay = prm.switch_delay_s
            action, bad_s, ok_s, was_bad = _advance(
                f[0], st.bad_s[p, i, k], st.ok_s[p, i, k], st.was_bad[p, i, k],
                st.latched[p, i, k], delay, k < N_SENSOR_KINDS, dt, prm.clear_after_s,
            )  # fmt: skip
            st.bad_s[p, i, k] = bad_s
            st.ok_s[p, i, k] = ok_s
            st.was_bad[p, i, k] = was_bad
            if action != HOLD:
                _act(st, tp, m, cmd, p, i, k, f, action, ev, src)
    f = _pack_finding(m.bus_v[p], m.load_current_a[p])
    action, bad_s, ok_s, was_bad = _advance(
        f[0], st.bad_s[p, n, K_NONFINITE], st.ok_s[p, n, K_NONFINITE],
        st.was_bad[p, n, K_NONFINITE], st.latched[p, n, K_NONFINITE], prm.nonfinite_delay_s,
        True, dt, prm.clear_after_s,
    )  # fmt: skip
    st.bad_s[p, n, K_NONFINITE] = bad_s
    st.ok_s[p, n, K_NONFINITE] = ok_s
    st.was_bad[p, n, K_NONFINITE] = was_bad
    if action != HOLD:
        _act(st, tp, m, cmd, p, n, K_NONFINITE, f, action, ev, src)
    _output(st, tp, m, p, cmd, status, s0, ev, src)


@kernel
def step_packs(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)


# ------------------------------------------------------------------------------ outside the step


@kernel_inline
def note_commands_pack(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    cmd: CmdArrays,
) -> None:  # fmt: skip
    """Record the merged commands of pack ``p`` that were applied (NO_OPINION keeps the previous
    state, as the hardware does). The supervisor calls this after every step."""
    for i in range(st.cmd_chg.shape[1]):
        c = cmd.chg_on[p, i]
        if c != NO_OPINION:
            st.cmd_chg[p, i] = 1 if c != 0 else 0
        d = cmd.dsg_on[p, i]
        if d != NO_OPINION:
            st.cmd_dsg[p, i] = 1 if d != 0 else 0


@kernel_inline
def note_commands_packs(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays
) -> None:
    for p in range(cmd.chg_on.shape[0]):
        note_commands_pack(prm, st, tp, m, p, cmd)


@kernel_inline
def _push_cleared(st: PlausibilityState, p: int, row: int, k: int) -> None:
    q = st.pend_n[p]
    st.pend_bat[p, q] = row if row < st.cmd_chg.shape[1] else -1
    st.pend_kind[p, q] = k
    st.pend_field[p, q] = st.field[p, row, k]
    st.pend_t[p, q] = st.t_s[p]
    st.pend_n[p] = q + 1
    _reset(st, p, row, k)


@kernel_inline
def clear_faults_pack(
    st: PlausibilityState, p: int, every_battery: bool, battery: int, kinds: int
) -> int:
    """Service reset of pack ``p``: unlatch the faults of ``battery`` (or of every battery and
    the pack's own) whose kind bit is set in ``kinds``. The only way to clear a switch fault;
    a condition still present re-latches after its delay. Returns how many faults were cleared;
    their ``FaultCleared`` events come with the next step."""
    n = st.cmd_chg.shape[1]
    cleared = 0
    lo, hi = (0, n) if every_battery else (battery, battery + 1)
    for i in range(lo, hi):
        if not 0 <= i < n:
            continue
        for k in range(N_KINDS):
            if kinds >> k & 1 and st.latched[p, i, k]:
                _push_cleared(st, p, i, k)
                cleared += 1
    if every_battery and kinds & 1 and st.latched[p, n, K_NONFINITE]:
        _push_cleared(st, p, n, K_NONFINITE)
        cleared += 1
    return cleared


__all__ = [
    "FIELDS",
    "KINDS",
    "NONFINITE_TEXT",
    "REACTIONS",
    "SENSOR_KINDS",
    "SWITCH_KINDS",
    "PlausibilityParams",
    "PlausibilityState",
    "clear_faults_pack",
    "note_commands_pack",
    "note_commands_packs",
    "step_pack",
    "step_packs",
]
