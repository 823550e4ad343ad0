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
from packpilot.jit import kernel

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
    "isolate",
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


@kernel
def _out(x: float, lo: float, hi: float) -> bool:
    return math.isfinite(x) and not (lo <= x and x <= hi)


@kernel
def _ok() -> Finding:
    return (OK, F_NONE, math.nan, V_FLOAT)


@kernel
def _none() -> Finding:
    return (NONE, F_NONE, math.nan, V_FLOAT)


@kernel
def _groups_seen(st: PlausibilityState, m: MeasArrays, p: int, i: int) -> int:
    """Group voltages of battery ``i`` the arrays hold (all of them, unless a misbehaving
    monitor reported more than the arrays have room for)."""
    return int(min(m.bat.n_groups[p, i], m.bat.group_v.shape[2], st.last.shape[2] - T_GROUP0))


# ------------------------------------------------------------------------------ detections


@kernel
def _nonfinite(st: PlausibilityState, m: MeasArrays, p: int, i: int) -> Finding:
    b = m.bat
    x = b.voltage_v[p, i]
    if not math.isfinite(x):
        return (BAD, F_VOLTAGE, x, V_SHOW)
    x = b.current_a[p, i]
    if not math.isfinite(x):
        return (BAD, F_CURRENT, x, V_SHOW)
    x = b.temp_c[p, i]
    if not math.isfinite(x):
        return (BAD, F_TEMP, x, V_SHOW)
    x = b.min_cell_v[p, i]
    if not math.isfinite(x):
        return (BAD, F_MIN_CELL, x, V_SHOW)
    x = b.max_cell_v[p, i]
    if not math.isfinite(x):
        return (BAD, F_MAX_CELL, x, V_SHOW)
    x = b.soc[p, i]
    if not math.isfinite(x):
        return (BAD, F_SOC, x, V_SHOW)
    x = b.min_temp_c[p, i]
    if math.isinf(x):
        return (BAD, F_MIN_TEMP, x, V_SHOW)  # NaN = not measured
    for g in range(_groups_seen(st, m, p, i)):
        x = b.group_v[p, i, g]
        if not math.isfinite(x):
            return (BAD, F_GROUP0 + g, x, V_SHOW)
    return _ok()


@kernel
def _range(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    i: int, cap: float,
) -> Finding:  # fmt: skip
    b = m.bat
    lo_v, hi_v = prm.cell_lo, prm.cell_hi
    x = b.min_cell_v[p, i]
    if _out(x, lo_v, hi_v):
        return (BAD, F_MIN_CELL, x, V_SHOW)
    x = b.max_cell_v[p, i]
    if _out(x, lo_v, hi_v):
        return (BAD, F_MAX_CELL, x, V_SHOW)
    x = b.temp_c[p, i]
    if _out(x, prm.temp_lo, prm.temp_hi):
        return (BAD, F_TEMP, x, V_SHOW)
    x = b.min_temp_c[p, i]
    if _out(x, prm.temp_lo, prm.temp_hi):
        return (BAD, F_MIN_TEMP, x, V_SHOW)
    x = b.soc[p, i]
    if _out(x, prm.soc_lo, prm.soc_hi):
        return (BAD, F_SOC, x, V_SHOW)
    groups, per_group = tp.groups[i], tp.cells_per_group[i]
    if groups != 0 and per_group != 0:
        s = groups * per_group
        x = b.voltage_v[p, i]
        if _out(x, lo_v * s, hi_v * s):
            return (BAD, F_VOLTAGE, x, V_SHOW)
        for g in range(_groups_seen(st, m, p, i)):
            x = b.group_v[p, i, g]
            if _out(x, lo_v * per_group, hi_v * per_group):
                return (BAD, F_GROUP0 + g, x, V_SHOW)
    cur = b.current_a[p, i]
    if math.isfinite(cap) and math.isfinite(cur):
        x = cur / cap
        if _out(x, prm.cur_lo, prm.cur_hi):
            return (BAD, F_CURRENT, x, V_SHOW)
    lo, hi = b.min_cell_v[p, i], b.max_cell_v[p, i]
    if math.isfinite(lo) and math.isfinite(hi) and lo > hi:
        return (BAD, F_MINMAX, lo - hi, V_SHOW)
    return _ok()


@kernel
def _track(
    st: PlausibilityState, p: int, i: int, j: int, x: float, loaded: bool, dt: float
) -> float:
    """Advance stuck-sensor track ``j``; returns how long its value has not changed."""
    if x != st.last[p, i, j]:  # a change (or NaN) proves nothing is frozen
        st.last[p, i, j] = x
        st.unchanged_s[p, i, j] = 0.0
    elif loaded:
        st.unchanged_s[p, i, j] += dt
    return float(st.unchanged_s[p, i, j])


@kernel
def _stuck(
    prm: PlausibilityParams, st: PlausibilityState, m: MeasArrays, p: int, i: int, cap: float,
    dt: float,
) -> Finding:  # fmt: skip
    b = m.bat
    scale = cap if math.isfinite(cap) else 1.0
    cur = b.current_a[p, i]
    loaded = math.isfinite(cur) and abs(cur) >= prm.stuck_current_c * scale
    hit = False
    field = F_NONE
    value = math.nan
    if prm.stuck_on:
        limit = prm.stuck_time_s
        for j in range(3):
            if j == T_VOLTAGE:
                x, f = b.voltage_v[p, i], F_VOLTAGE
            elif j == T_MIN_CELL:
                x, f = b.min_cell_v[p, i], F_MIN_CELL
            else:
                x, f = b.max_cell_v[p, i], F_MAX_CELL
            if _track(st, p, i, j, x, loaded, dt) >= limit - EPS and not hit:
                hit, field, value = True, f, x
    if prm.stuck_temp_on:
        x = b.temp_c[p, i]
        if _track(st, p, i, T_TEMP, x, loaded, dt) >= prm.stuck_temp_time_s - EPS and not hit:
            hit, field, value = True, F_TEMP, x
    if prm.stuck_on:
        limit = prm.stuck_time_s
        for g in range(_groups_seen(st, m, p, i)):
            x = b.group_v[p, i, g]
            if _track(st, p, i, T_GROUP0 + g, x, loaded, dt) >= limit - EPS and not hit:
                hit, field, value = True, F_GROUP0 + g, x
    if hit:
        return (BAD, field, value, V_SHOW)
    return _ok()


@kernel
def _stale(prm: PlausibilityParams, m: MeasArrays, p: int, i: int) -> Finding:
    age = m.bat.sample_age_s[p, i]
    if math.isnan(age):
        return _none()  # not reported (NaN means "unknown", not "stale")
    if not math.isfinite(age) or age > prm.max_sample_age_s:
        return (BAD, F_SAMPLE_AGE, age, V_SHOW)
    return _ok()


@kernel
def _group_count(tp: PackArrays, m: MeasArrays, p: int, i: int) -> Finding:
    groups = tp.groups[i]
    k = m.bat.n_groups[p, i]
    if groups != 0 and k != 0 and k != groups:
        return (BAD, F_GROUPS, float(k), V_INT)
    return _ok()


@kernel
def _sum(prm: PlausibilityParams, tp: PackArrays, m: MeasArrays, p: int, i: int) -> Finding:
    groups = tp.groups[i]
    if groups == 0 or m.bat.n_groups[p, i] != groups:
        return _none()
    v = m.bat.voltage_v[p, i]
    if not math.isfinite(v):
        return _none()
    for g in range(groups):
        if not math.isfinite(m.bat.group_v[p, i, g]):
            return _none()
    total = 0.0
    for g in range(groups):
        total += m.bat.group_v[p, i, g]
    diff = v - total
    if abs(diff) > prm.sum_tolerance_v_per_group * groups:
        return (BAD, F_SUM, diff, V_FLOAT)
    return _ok()


@kernel
def _switch(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, i: int, k: int
) -> Finding:
    """Switch detector ``k`` of battery ``i``: feedback against the last merged command."""
    chg, dsg = st.cmd_chg[p, i], st.cmd_dsg[p, i]
    fb_chg, fb_dsg = m.bat.sw_chg[p, i], m.bat.sw_dsg[p, i]
    if tp.relay[i]:
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


@kernel
def _pack_finding(m: MeasArrays, p: int) -> Finding:
    x = m.bus_v[p]
    if not math.isfinite(x):
        return (BAD, F_BUS, x, V_SHOW)
    x = m.load_current_a[p]
    if not math.isfinite(x):
        return (BAD, F_LOAD, x, V_SHOW)
    return _ok()


# ------------------------------------------------------------------------------ reactions


@kernel
def _sensor_bad(st: PlausibilityState, p: int, i: int) -> bool:
    for k in range(N_SENSOR_KINDS):  # noqa: SIM110 - no generators in a kernel
        if st.latched[p, i, k]:
            return True
    return False


@kernel
def _other_source(st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, i: int) -> bool:
    """Another battery with trusted sensors can carry the load now (switch feedback)."""
    for j in range(st.cmd_chg.shape[1]):
        if j == i or not (m.bat.reported[p, j] and m.bat.present[p, j]) or _sensor_bad(st, p, j):
            continue
        if conducts(tp, m, p, j, False):
            return True
    return False


@kernel
def _reaction(st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, i: int, k: int) -> int:
    """What the commands will do about a new fault (for the event; see ``_output``)."""
    if i < 0:
        return R_CHARGER_OFF
    if k < N_SENSOR_KINDS:
        if st.latched[p, i, K_RELAY_WELDED]:
            return R_WELDED_NO_ISOLATE
        if m.docked[p]:
            return R_ISOLATE_DOCKED
        if _other_source(st, tp, m, p, i):
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


@kernel
def _nonfinite_code(x: float) -> float:
    """Label index of the text of a non-finite value (:data:`NONFINITE_TEXT`)."""
    if math.isnan(x):
        return 0.0
    return 1.0 if x > 0.0 else 2.0


@kernel
def _emit_fault(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, i: int, k: int,
    f: Finding, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    reaction = _reaction(st, tp, m, p, i, k)
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


@kernel
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


@kernel
def _reset(st: PlausibilityState, p: int, row: int, k: int) -> None:
    st.latched[p, row, k] = False
    st.bad_s[p, row, k] = 0.0
    st.ok_s[p, row, k] = 0.0
    st.was_bad[p, row, k] = False
    st.field[p, row, k] = F_NONE


@kernel
def _advance(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    row: int, k: int, f: Finding, delay: float, auto_clear: bool, dt: float, ev: EventBuf,
    src: int,
) -> None:  # fmt: skip
    """Persistence timer and latch of detector ``k`` of battery ``row`` (B: the pack)."""
    if f[0] == NONE:
        return  # not judgeable now: hold every timer
    i = row if row < st.cmd_chg.shape[1] else -1
    if f[0] == BAD:
        st.bad_s[p, row, k] = st.bad_s[p, row, k] + dt if st.was_bad[p, row, k] else 0.0
        st.was_bad[p, row, k] = True
        st.ok_s[p, row, k] = 0.0
        if not st.latched[p, row, k] and st.bad_s[p, row, k] >= delay - EPS:
            st.latched[p, row, k] = True
            st.field[p, row, k] = f[1]
            _emit_fault(st, tp, m, p, i, k, f, ev, src)
        return
    st.ok_s[p, row, k] = st.ok_s[p, row, k] + dt if not st.was_bad[p, row, k] else 0.0
    st.was_bad[p, row, k] = False
    st.bad_s[p, row, k] = 0.0
    if st.latched[p, row, k] and auto_clear and st.ok_s[p, row, k] >= prm.clear_after_s - EPS:
        _emit_cleared(ev, p, src, i, k, int(st.field[p, row, k]), False, m.t_s[p])
        _reset(st, p, row, k)


# ------------------------------------------------------------------------------ the step


@kernel
def _battery(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    i: int, dt: float, ev: EventBuf, src: int,
) -> None:  # fmt: skip
    if not (m.bat.reported[p, i] and m.bat.present[p, i]):
        return  # absent: nothing can be judged, every timer holds
    cap = capacity_ah(tp, m, p, i)
    _advance(prm, st, tp, m, p, i, K_NONFINITE, _nonfinite(st, m, p, i),
             prm.nonfinite_delay_s, True, dt, ev, src)  # fmt: skip
    _advance(prm, st, tp, m, p, i, K_RANGE, _range(prm, st, tp, m, p, i, cap),
             prm.range_delay_s, True, dt, ev, src)  # fmt: skip
    _advance(prm, st, tp, m, p, i, K_STUCK, _stuck(prm, st, m, p, i, cap, dt),
             0.0, True, dt, ev, src)  # fmt: skip
    _advance(prm, st, tp, m, p, i, K_STALE, _stale(prm, m, p, i), 0.0, True, dt, ev, src)
    _advance(prm, st, tp, m, p, i, K_SUM, _sum(prm, tp, m, p, i),
             prm.sum_delay_s, True, dt, ev, src)  # fmt: skip
    _advance(prm, st, tp, m, p, i, K_COUNT, _group_count(tp, m, p, i), 0.0, True, dt, ev, src)
    for k in range(N_SENSOR_KINDS, N_KINDS):
        _advance(prm, st, tp, m, p, i, k, _switch(st, tp, m, p, i, k),
                 prm.switch_delay_s, False, dt, ev, src)  # fmt: skip


@kernel
def _output(
    st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int, cmd: CmdArrays, status: F64,
    s0: int,
) -> None:  # fmt: skip
    """The fail-safe commands of every latched fault, and the status channels."""
    n = st.cmd_chg.shape[1]
    charger_off = bool(st.latched[p, n, K_NONFINITE])
    docked = m.docked[p]
    for i in range(n):
        lat = st.latched[p, i]
        welded = lat[K_RELAY_WELDED]
        chg_off = False
        dsg_off = False
        isolated = False
        if lat[K_RELAY_STUCK_OPEN]:
            chg_off = dsg_off = True
        if lat[K_CHG_STUCK_OPEN]:
            chg_off = True
        if lat[K_DSG_STUCK_OPEN]:
            dsg_off = True
        sensor_bad = _sensor_bad(st, p, i)
        if sensor_bad and not welded:
            if docked or _other_source(st, tp, m, p, i):
                chg_off = dsg_off = True
                isolated = True
            elif not tp.relay[i]:
                chg_off = True  # discharge still flows through the charge FET's body diode
        can_take_charge = (
            m.bat.reported[p, i] and m.bat.present[p, i] and conducts(tp, m, p, i, True)
        )
        if (sensor_bad or welded or lat[K_CHG_SHORTED]) and can_take_charge:
            charger_off = True  # never charge into a battery we cannot see or cannot block
        if chg_off:
            put_chg(cmd, p, i, False)
        if dsg_off:
            put_dsg(cmd, p, i, False)
        st.isolated[p, i] = isolated
        mask = 0
        for k in range(N_KINDS):
            if lat[k]:
                mask |= 1 << k
        status[p, i, s0 + ST_FAULTS] = mask
        status[p, i, s0 + ST_ISOLATED] = 1.0 if isolated else 0.0
    if charger_off:
        put_charger_off(cmd, p)


@kernel
def step_pack(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, p: int,
    dt_s: float, cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One step of pack ``p``: pending service resets, every detector, the pack's bus and load
    readings, then the reactions as commands and the status channels."""
    dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
    st.t_s[p] = m.t_s[p]
    for q in range(st.pend_n[p]):
        _emit_cleared(ev, p, src, int(st.pend_bat[p, q]), int(st.pend_kind[p, q]),
                      int(st.pend_field[p, q]), True, st.pend_t[p, q])  # fmt: skip
    st.pend_n[p] = 0
    n = st.cmd_chg.shape[1]
    for i in range(n):
        _battery(prm, st, tp, m, p, i, dt, ev, src)
    _advance(prm, st, tp, m, p, n, K_NONFINITE, _pack_finding(m, p),
             prm.nonfinite_delay_s, True, dt, ev, src)  # fmt: skip
    _output(st, tp, m, p, cmd, status, s0)


@kernel
def step_packs(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)


# ------------------------------------------------------------------------------ outside the step


@kernel
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


@kernel
def note_commands_packs(
    prm: PlausibilityParams, st: PlausibilityState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays
) -> None:
    for p in range(cmd.chg_on.shape[0]):
        note_commands_pack(prm, st, tp, m, p, cmd)


@kernel
def _push_cleared(st: PlausibilityState, p: int, row: int, k: int) -> None:
    q = st.pend_n[p]
    st.pend_bat[p, q] = row if row < st.cmd_chg.shape[1] else -1
    st.pend_kind[p, q] = k
    st.pend_field[p, q] = st.field[p, row, k]
    st.pend_t[p, q] = st.t_s[p]
    st.pend_n[p] = q + 1
    _reset(st, p, row, k)


@kernel
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
