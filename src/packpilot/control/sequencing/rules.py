"""Discharge sequencing of parallel batteries behind charge/discharge MOSFET pairs, compiled.

Spec: ``spec/parallel_discharge.md`` (DJI CN 201680002560.8), generalised to N >= 2 batteries.
Each battery sits behind a charge FET (its body diode conducts when the battery *discharges*)
in series with a discharge FET (its diode conducts when the battery is *charged*). The point of
the method is that a battery whose charge FET is off can feed the bus through the diode but can
never be charged by a higher sibling, so directly paralleled batteries at different voltages do
not push tens of amperes into each other.

States (per battery) and the FET pattern each one commands:

* ``DISCHARGING`` - admitted to discharge: discharge FET on; charge FET on once *engaged*.
  Engagement follows R3 (diode conduction seen -> FET on within ``t_on``) or the *level rule*
  (the battery's voltage has reached the bus reference, so closing the FET cannot charge it).
* ``STANDBY`` - discharge FET on, charge FET off (the charge diode blocks any charging); both
  off while the battery is isolated by source isolation ([REC]).
* ``CHARGING`` - charge FET on; discharge FET on once charging current is seen through its
  diode (R4).
* ``OFF`` - both FETs off: the battery is not present.

Rules applied every control period in discharge mode (see ``docs/parallel_discharge.md``):

* R1 at (re)initialisation (power-up, fault recovery, return from charge mode, empty
  discharging set): batteries within ``v_th`` of the highest discharge, the others stand by.
  A hot-inserted battery that is ``v_th`` or more above the bus reference takes over (R1
  re-applied to it); any other inserted battery starts in STANDBY.
* Reverse current: an engaged discharging battery taking more than ``i_rev`` of charge from a
  sibling has its charge FET opened (-> STANDBY).
* R2: a standby battery ``v_co`` or more above the bus reference (the highest discharging
  battery's terminal voltage) joins. At rest (no current anywhere) it takes over instead of
  co-discharging, because rest voltages are open-circuit voltages and co-discharge would push
  about (V_k - V_ref) / R_loop into the others.
* Rest merge ([REC], not in the source text): when every battery has carried at most
  ``i_det`` for ``t_rest``, a standby (or admitted, not yet engaged) battery whose voltage is
  within ``v_merge = i_merge * r_loop_ohm`` of every engaged battery rejoins with its charge FET
  on, like R1 admitting batteries within ``v_th`` at power-up, but with a window sized so the
  circulating current it can cause stays at or below ``i_merge <= i_rev``.
* Load merge ([REC]): under load, a standby or admitted battery whose *fast voltage*
  ``V + I*R`` (R estimated online from current steps) matches the engaged ones' closes its
  charge FET; the level rule (which completes R2) closes one only under the same check.
* R3: a battery with discharge FET on and charge FET off that sources more than ``i_det``
  (its charge diode conducts) gets its charge FET on after a debounce, no later than ``t_on``.
  Only current measured over a period in which the controller held that FET off counts.
* Cross-current guard ([REC]): a sampled controller cannot stop the current that flows between
  co-discharging batteries in the period in which the load falls, so every period it predicts
  that current at zero load from the fast voltages and opens (-> STANDBY) any battery that
  would take more than ``i_guard``, unless R3 needs it closed or the bus needs it above cut-off
  (then ``CrossCurrentRisk``).
* Source isolation ([REC], ``isolate_source``): when the guard predicts more than ``i_guard``
  into a battery that R3 closed at the present load (opening it would only make its diode
  conduct again: the R3 conflict), the battery pushing that current is *isolated* - STANDBY
  with the discharge FET off too (``seq_isolated``) - if the rest carry the load with
  pessimistic resistances. It comes back by take-over, merge, plain STANDBY or, near
  cut-off, forced (:func:`_release_isolated`), after at least ``t_iso_hold``.

Invalid measurements (a battery missing from the sample; non-finite or negative voltage,
non-finite current, time or period) put the pack in a fail-safe: every charge FET off, every
present battery's discharge FET on (the pack can discharge only through the charge diodes,
nothing can be charged), with one ``Fault`` event. When measurements are valid again the
controller re-initialises with R1.

Deterministic: the only clock is the sample time ``m.t_s[p]`` (for timers) and ``dt_s`` (the
control period, used to predict whether waiting one more period would miss the ``t_on``
deadline). The kernels keep the decisions of the scalar controller they replaced (checked
step by step until that controller was deleted): "none" is NaN (floats) or -1 (indices), a
ranking is a stable insertion sort, a maximum the first maximum, sums from 0 left to right.
Arrays are bound to local names once per function (a tuple attribute read in a loop costs a
reference-count round trip in numba).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import emit, put_chg, put_dsg
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

EPS_S = 1e-9
"""Tolerance for comparing accumulated times, so 0.1 + 0.1 + 0.1 counts as 0.3 s."""

# Battery states (the order of ``SeqState``).
DISCHARGING = 0
STANDBY = 1
CHARGING = 2
OFF = 3

# Pack modes (the order of ``SeqMode``).
MODE_DISCHARGE = 0
MODE_CHARGE = 1
MODE_FAULT = 2

# Fail-safe reasons (``State.fault[p, 0]``; the text is built by the controller's labels).
FAULT_NONE = 0
FAULT_COUNT = 1
"""A battery is missing from the sample: ``fault[p, 1]`` = how many were reported."""
FAULT_T = 2
"""``fault[p, 2]`` = the non-finite time."""
FAULT_DT = 3
"""``fault[p, 2]`` = the period."""
FAULT_BACKWARDS = 4
"""``fault[p, 2]`` = the last valid time, ``fault[p, 3]`` = this sample's."""
FAULT_VOLTAGE = 5
"""``fault[p, 1]`` = battery, ``fault[p, 2]`` = its voltage."""
FAULT_CURRENT = 6
"""``fault[p, 1]`` = battery, ``fault[p, 2]`` = its current."""
N_FAULT = 4

# Reason codes (rows of the reason table in controller.py).
SET = 0
"""A state change without data (StateChanged)."""
SET_R1 = 1
REVERSE = 2
INSERTED_ABOVE = 3
JOIN_R2 = 4
JOIN_REST = 5
JOIN_LOAD = 6
JOIN_R3 = 7
GUARD = 8
ISOLATED = 9
JOIN_ISO_MERGE = 10
JOIN_TAKE_OVER = 11
RELEASED = 12
DIODE = 13
REVERSE_DSG = 14
RISK = 15
MODE = 16
MODE_NO_BATTERY = 17
"""ModeChanged with no battery present: the scalar pack current was the integer 0."""
FAULT = 18
FAULT_CLEARED = 19

# Slots of a state-change event: from, to, reason, battery (message only), then the data.
V_FROM = 0
V_TO = 1
V_REASON = 2
V_BATTERY = 3
V_DATA = 4

# Reason labels (``controller.REASON_LABELS``); then "R1 battery {k} inserted" for each k,
# then "would charge battery {k}, which R3 closed at this load" for each k.
R_NONE = 0
R_FAIL_SAFE = 1
R_REMOVED = 2
R_INSERTED = 3
R_CHARGE_MODE = 4
R_INSERTED_CHARGING = 5
R_R1_INIT = 6
R_R1_EMPTY = 7
R_REVERSE = 8
R_INSERTED_ABOVE = 9
R_R2 = 10
R_REST_MERGE = 11
R_LOAD_MERGE = 12
R_R3 = 13
R_GUARD = 14
R_ISO_MERGE = 15
R_ISO_ENDED = 16
R_ISO_FORCED = 17
R_TAKE_OVER = 18
N_FIXED_REASONS = 19

PATH_CHG = 0
PATH_DSG = 1

# Status channels, in order.
ST_STATE = 0
ST_CHG = 1
ST_DSG = 2
ST_MODE = 3
ST_V_REF = 4
ST_ZERO_LOAD = 5
ST_AT_RISK = 6
ST_ISOLATED = 7
ST_DIODE = 8


class SequencingParams(NamedTuple):
    v_th: float
    v_co: float
    i_det: float
    t_on: float
    t_debounce: float
    i_rev: float
    t_mode: float
    i_merge: float
    v_merge: float
    """i_merge * r_loop_ohm."""
    t_rest: float
    i_guard: float
    r_batt_ohm: float
    i_step: float
    v_diode: float
    v_cut: float
    """Pack cut-off voltage: v_cutoff_cell_v times the most cells in series of a group."""
    v_reserve: float
    isolate_source: bool
    t_iso_hold: float
    v_iso_margin: float
    n_batteries: int
    fault_text: F64
    """The State's ``fault`` array itself: the event renderer formats the fail-safe reason
    (a data string with numbers in it) from it, as the scalar controller did."""


class SequencingState(NamedTuple):
    """Everything the controller remembers between periods, (P, B) or (P,)."""

    state: I64
    """Battery state (DISCHARGING, STANDBY, CHARGING, OFF)."""
    chg_on: B1
    """Charge FET command last issued."""
    dsg_on: B1
    conduct_since_s: F64
    """Time of the first sample of the current diode-conduction episode (R3/R4); NaN = none."""
    r_ohm: F64
    """Ohmic resistance estimate (-dV/dI of the last current step >= i_step); NaN = none yet."""
    last_v_v: F64
    last_i_a: F64
    """The previous sample's battery-side voltage and current (resistance estimate)."""
    hold_load_a: F64
    """Pack current at which R3 last had to close this battery's charge FET: the guard leaves
    it engaged while the pack current stays above 0.9 of that (its diode would conduct)."""
    guard_opened: B1
    """The guard opened this battery's charge FET and no rule has closed it since."""
    at_risk: B1
    """The guard predicts more than i_guard into this battery but may not open it."""
    isolated_since_s: F64
    """Source isolation: time both FETs were opened (state STANDBY); NaN = not isolated."""
    released_at_s: F64
    """Source isolation: time this battery last left isolation by a take-over, the standby
    release or a forced release; not isolated again within t_iso_hold of that."""
    zero_load_into_a: F64
    """Guard prediction of the last discharge period (valid where ``zero_load_valid``)."""
    mode: I64
    """(P,) MODE_DISCHARGE, MODE_CHARGE or MODE_FAULT."""
    initialized: B1
    last_t_s: F64
    """(P,) time of the last valid sample; NaN = none yet."""
    mode_evidence_since_s: F64
    """(P,) first sample of the current run of evidence for leaving the mode."""
    v_ref_v: F64
    """(P,) bus reference of the last period (highest discharging terminal voltage)."""
    rest_since_s: F64
    """(P,) first sample of the current run with every battery at or below i_det."""
    zero_load_valid: B1
    """(P,)."""
    fault: F64
    """(P, N_FAULT) the last fail-safe reason: code (FAULT_*), then its numbers; kept after
    the fault clears (the FaultCleared event names it)."""
    # Scratch, (B,): values of the pack being stepped, nothing carried between steps (packs
    # are stepped one after the other; a State is never stepped by two threads at once).
    ef: F64
    """Fast voltage V + I*R of each battery."""
    g: F64
    """1 / R estimate."""
    gp: F64
    """1 / pessimistic R."""
    pred: F64
    pred2: F64
    grp: I64
    grp2: I64
    order: I64
    ready: I64
    diodes: I64
    iso: I64
    demoted: B1
    keep: B1
    held: B1
    dheld: B1
    ing: B1
    inserted: B1
    rest: B1
    was_c: B1
    was_d: B1


class Switches(NamedTuple):
    """The arrays a state change writes (built once per kernel from the State)."""

    state: I64
    chg_on: B1
    dsg_on: B1
    isolated_since_s: F64


# ------------------------------------------------------------------------------ helpers


@kernel_inline
def _set(
    sw: Switches, ev: EventBuf, src: int, p: int, k: int, new: int, engaged: bool, t: float,
    code: int, reason: int,
) -> int:  # fmt: skip
    """Move battery k to ``new`` with its FET pattern (``engaged``: the R3/R4-controlled FET
    of that state) and emit one event if its state changed; returns the event row (data from
    slot ``V_DATA``) or -1."""
    state = sw.state
    old = state[p, k]
    state[p, k] = new
    if new == DISCHARGING:
        c = engaged
        d = True
    elif new == STANDBY:
        c = False
        d = True
    elif new == CHARGING:
        c = True
        d = engaged
    else:
        c = False
        d = False
    sw.chg_on[p, k] = c
    sw.dsg_on[p, k] = d
    sw.isolated_since_s[p, k] = np.nan
    if old == new:
        return -1
    r = emit(ev, p, src, code, k, t)
    ev.val[r, V_FROM] = old
    ev.val[r, V_TO] = new
    ev.val[r, V_REASON] = reason
    ev.val[r, V_BATTERY] = k
    return r


@kernel_inline
def _sort_desc(idx: I64, m: int, key: F64) -> None:
    """Stable sort of ``idx[:m]`` by ``-key`` (``sorted(idx, key=lambda j: -key[j])``)."""
    for i in range(1, m):
        x = idx[i]
        kx = key[x]
        j = i - 1
        while j >= 0 and key[idx[j]] < kx:
            idx[j + 1] = idx[j]
            j -= 1
        idx[j + 1] = x


@kernel_inline
def _engaged(state: I64, chg_on: B1, p: int, grp: I64, extra: int) -> int:
    """Indices (ascending) of the engaged batteries (DISCHARGING, charge FET on) into
    ``grp``, plus ``extra`` (>= 0) if given; returns how many."""
    m = 0
    for k in range(state.shape[1]):
        if (state[p, k] == DISCHARGING and chg_on[p, k]) or k == extra:
            grp[m] = k
            m += 1
    return m


@kernel_inline
def _zero_load(grp: I64, m: int, ef: F64, g: F64, out: F64) -> None:
    """Current (A, > 0 = charging) into each battery of ``grp[:m]`` if the load vanished now.

    The engaged batteries then form a loop of voltage sources behind their resistances; the
    lowest ones are charged by the others. Zero load is the worst case: any load current
    only lowers the current into every battery. FET on-resistances are left out, which
    overestimates the current (the safe side).
    """
    if m < 2:
        for i in range(m):
            out[grp[i]] = 0.0
        return
    num = 0.0
    for i in range(m):
        k = grp[i]
        num += ef[k] * g[k]
    den = 0.0
    for i in range(m):
        den += g[grp[i]]
    v0 = num / den
    for i in range(m):
        k = grp[i]
        out[k] = (v0 - ef[k]) * g[k]


@kernel_inline
def _max_over(grp: I64, m: int, x: F64) -> float:
    best: float = x[grp[0]]
    for i in range(1, m):
        if x[grp[i]] > best:
            best = x[grp[i]]
    return best


@kernel_inline
def _v_ref(state: I64, p: int, volt: F64) -> float:
    """Bus reference for R2: highest terminal voltage of the DISCHARGING batteries (NaN: none).

    Admitted batteries whose charge FET is still open count too, so a standby battery joins
    only above every battery already admitted to discharge (joins go in voltage order).
    """
    have = False
    v = np.nan
    for k in range(state.shape[1]):
        if state[p, k] == DISCHARGING and (not have or volt[k] > v):
            v = volt[k]
            have = True
    return v


@kernel_inline
def _load(pres: B1, cur: F64) -> float:
    """Pack current: the sum of the present batteries' currents."""
    tot = 0.0
    for k in range(pres.shape[0]):
        if pres[k]:
            tot += cur[k]
    return tot


@kernel_inline
def _r_est(prm: SequencingParams, st: SequencingState, p: int, k: int) -> float:
    r = st.r_ohm[p, k]
    return prm.r_batt_ohm if math.isnan(r) else r


@kernel_inline
def _r1(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, volt: F64,
    pres: B1, t: float, reason: int,
) -> None:  # fmt: skip
    """R1: within ``v_th`` of the highest -> DISCHARGING (not yet engaged), else STANDBY."""
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    isolated_since_s = st.isolated_since_s
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    have = False
    v_max = 0.0
    for k in range(n):
        if pres[k] and (not have or volt[k] > v_max):
            v_max = volt[k]
            have = True
    if not have:
        return
    for k in range(n):
        if not pres[k]:
            continue
        new = DISCHARGING if v_max - volt[k] < prm.v_th else STANDBY
        r = _set(sw, ev, src, p, k, new, False, t, SET_R1, reason)
        if r >= 0:
            ev.val[r, V_DATA] = volt[k]
            ev.val[r, V_DATA + 1] = v_max
        conduct_since_s[p, k] = np.nan


@kernel_inline
def _diode_rule(
    prm: SequencingParams, state: I64, conduct_since_s: F64, ev: EventBuf, src: int, p: int,
    k: int, conducting: bool, t: float, dt: float,
) -> bool:  # fmt: skip
    """R3/R4 timer for battery k. Returns True when the FET must be switched on now.

    Switches once conduction has lasted ``t_debounce``, or earlier if waiting one more
    period (``dt``) would overrun ``t_on``.
    """
    if not conducting:
        conduct_since_s[p, k] = np.nan
        return False
    if math.isnan(conduct_since_s[p, k]):
        conduct_since_s[p, k] = t
    elapsed = t - conduct_since_s[p, k]
    due: bool = elapsed + EPS_S >= prm.t_debounce or elapsed + dt > prm.t_on + EPS_S
    if due:
        conduct_since_s[p, k] = np.nan
        r = emit(ev, p, src, DIODE, k, t)
        ev.val[r, 0] = PATH_CHG if state[p, k] != CHARGING else PATH_DSG
        ev.val[r, 1] = elapsed
        ev.val[r, 2] = k
    return due


# ------------------------------------------------------------------------------ source isolation


@kernel_inline
def _bus_held(
    prm: SequencingParams, st: SequencingState, p: int, pres: B1, iso: int, grp: I64, m: int,
    load_a: float,
) -> float:  # fmt: skip
    """Pessimistic bus voltage (V) if battery ``iso`` stopped and the rest of ``grp[:m]``
    (engaged) plus every other battery with its discharge FET on (through its diode) carried
    ``load_a``.

    Resistances are inflated: 1.25 x the estimate (polarisation builds up once the load has
    moved to the rest), 2 x the prior for a battery that has not yet seen a current step.
    Diodes drop ``v_diode + v_iso_margin``, the pessimistic end of the 0.5-0.7 V range.
    """
    state = st.state
    dsg_on = st.dsg_on
    ef = st.ef
    gp = st.gp
    diodes = st.diodes
    rest = st.rest
    n = state.shape[1]
    for j in range(n):
        rest[j] = False
    cnt = 0
    num = 0.0
    for i in range(m):
        j = grp[i]
        if j != iso:
            rest[j] = True
            cnt += 1
            num += ef[j] * gp[j]
    if cnt == 0:
        return -np.inf
    den = 0.0
    for i in range(m):
        j = grp[i]
        if j != iso:
            den += gp[j]
    v_rest = (num - load_a) / den
    nd = 0
    for j in range(n):
        if j != iso and not rest[j] and pres[j] and dsg_on[p, j]:
            diodes[nd] = j
            nd += 1
    _sort_desc(diodes, nd, ef)
    v_drop = prm.v_diode + prm.v_iso_margin
    for i in range(nd):
        j = diodes[i]
        e_j = ef[j] - v_drop
        if v_rest >= e_j:
            break
        num += e_j * gp[j]
        den += gp[j]
        v_rest = (num - load_a) / den
    return v_rest


@kernel_inline
def _isolate_source(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, pres: B1,
    victim: int, grp: I64, m: int, pred: F64, load_a: float, t: float,
) -> bool:  # fmt: skip
    """Source isolation [REC]: open *both* FETs of the battery that would charge ``victim``.

    The guard cannot open the victim: its charge diode would conduct and R3 would close it
    again (diode stress). So the battery with the highest fast voltage among its siblings
    (the one pushing the current) is isolated instead: STANDBY with the discharge FET off
    too, because with only its charge FET off it would still discharge through its charge
    diode. Only if the rest (the victim included) hold the bus ``v_reserve`` +
    ``v_iso_margin`` above cut-off at the present load, with pessimistic resistances
    (:func:`_bus_held`), and not within ``t_iso_hold`` of its last release (no chatter).
    Isolating the victim instead (both its FETs off) was tried: it leaves the high battery
    carrying a heavy load alone, which drags the bus under the next battery's diode, and
    did worse in the closed-loop sweeps. Returns whether a battery was isolated.
    """
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    isolated_since_s = st.isolated_since_s
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    if not prm.isolate_source:
        return False
    ef = st.ef
    s = -1
    for i in range(m):
        j = grp[i]
        if j != victim and pred[j] < 0.0 and (s < 0 or ef[j] > ef[s]):
            s = j
    if s < 0:
        return False
    rel = st.released_at_s[p, s]
    if not math.isnan(rel) and t - rel + EPS_S < prm.t_iso_hold:
        return False
    v_rest = _bus_held(prm, st, p, pres, s, grp, m, load_a)
    if v_rest < prm.v_cut + prm.v_reserve + prm.v_iso_margin:
        return False
    n = state.shape[1]
    reason = N_FIXED_REASONS + n + victim
    r = _set(sw, ev, src, p, s, STANDBY, False, t, ISOLATED, reason)
    if r >= 0:
        ev.val[r, V_DATA] = victim
        ev.val[r, V_DATA + 1] = pred[victim]
        ev.val[r, V_DATA + 2] = ef[s]
        ev.val[r, V_DATA + 3] = v_rest
    dsg_on[p, s] = False
    isolated_since_s[p, s] = t
    st.conduct_since_s[p, s] = np.nan
    st.guard_opened[p, s] = False
    st.hold_load_a[p, s] = np.nan
    return True


@kernel_inline
def _guard(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, pres: B1,
    cur: F64, t: float,
) -> None:  # fmt: skip
    """Open, before the load can fall, the charge FET of any engaged battery that would take
    more than ``i_guard`` from its siblings at zero load (worst victim first).

    A sampled controller cannot react within the period in which the load falls; between
    that step and the next sample the plant pushes (E_a - E_b) / (R_a + R_b) into the lower
    battery. Batteries co-discharging on one bus have equal terminal voltages, so their
    fast voltages E = V + I*R differ by their I*R difference (16 vs 30 mOhm at 10 A: 0.14 V,
    3 A). Not opened: a battery in ``keep`` (closed by R3 this period), the last engaged
    one, one whose diode would conduct at the present load (R3 would re-close it), and one
    without which the others would hold the bus less than ``v_reserve`` above cut-off.
    Source isolation [REC] applies to the R3 conflict only: a victim that R3 closed this
    period, or closed earlier at (0.9 of) the present load, cannot be opened (its diode
    would conduct and R3 close it again), so the battery that would push the current is
    isolated instead, if the rest can carry the load (:func:`_isolate_source`). A victim kept
    for any other reason (last engaged, cut-off reserve, a diode that would conduct only
    once opened) stays engaged and is flagged (``CrossCurrentRisk``, once per episode).
    """
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    hold_load_a = st.hold_load_a
    guard_opened = st.guard_opened
    at_risk = st.at_risk
    isolated_since_s = st.isolated_since_s
    zero_load_into_a = st.zero_load_into_a
    zero_load_valid = st.zero_load_valid
    ef = st.ef
    g = st.g
    pred = st.pred
    grp = st.grp
    keep = st.keep
    held = st.held
    dheld = st.dheld
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    load_a = _load(pres, cur)
    v_cut = prm.v_cut
    for k in range(n):
        held[k] = False
        dheld[k] = keep[k]
    for k in range(n):
        if state[p, k] != DISCHARGING or not chg_on[p, k]:
            hold_load_a[p, k] = np.nan
            continue
        if not keep[k]:
            guard_opened[p, k] = False
        if not math.isnan(hold_load_a[p, k]):
            if load_a >= 0.9 * hold_load_a[p, k]:
                dheld[k] = True
            else:
                hold_load_a[p, k] = np.nan
    while True:
        m = _engaged(state, chg_on, p, grp, -1)
        _zero_load(grp, m, ef, g, pred)
        k = -1
        for i in range(m):
            j = grp[i]
            if pred[j] > prm.i_guard and not held[j] and (k < 0 or pred[j] > pred[k]):
                k = j
        if k < 0:
            break
        if m > 1:
            num = 0.0
            for i in range(m):
                j = grp[i]
                if j != k:
                    num += ef[j] * g[j]
            den = 0.0
            for i in range(m):
                j = grp[i]
                if j != k:
                    den += g[j]
            v_bus = (num - load_a) / den
        else:
            v_bus = -np.inf
        if m == 1 or v_bus < v_cut + prm.v_reserve:
            held[k] = True
            continue
        if dheld[k]:
            # R3 conflict: R3 closed it because its diode conducted at this load, so opening
            # it would only make the diode conduct again. Take the source away instead.
            if not _isolate_source(prm, st, ev, src, p, pres, k, grp, m, pred, load_a, t):
                held[k] = True
            continue
        if ef[k] - prm.v_diode >= v_bus:
            held[k] = True
            continue
        r = _set(sw, ev, src, p, k, STANDBY, False, t, GUARD, R_GUARD)
        if r >= 0:
            ev.val[r, V_DATA] = pred[k]
            ev.val[r, V_DATA + 1] = prm.i_guard
            ev.val[r, V_DATA + 2] = ef[k]
            ev.val[r, V_DATA + 3] = _r_est(prm, st, p, k)
        conduct_since_s[p, k] = np.nan
        guard_opened[p, k] = True
    # What is left above i_guard the controller knowingly keeps (R3, cut-off reserve, last
    # battery): flagged once per episode, so the risk is visible in the event log.
    m = _engaged(state, chg_on, p, grp, -1)
    for k in range(n):
        pred[k] = 0.0
    _zero_load(grp, m, ef, g, pred)
    for k in range(n):
        risk = pred[k] > prm.i_guard
        if risk and not at_risk[p, k]:
            r = emit(ev, p, src, RISK, k, t)
            ev.val[r, 0] = pred[k]
            ev.val[r, 1] = prm.i_guard
            ev.val[r, 2] = k
        at_risk[p, k] = risk
        zero_load_into_a[p, k] = pred[k]
    zero_load_valid[p] = True


@kernel_inline
def _take_over(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, pres: B1,
    iso: I64, ni: int, load_a: float, t: float,
) -> bool:  # fmt: skip
    """Isolation take-over: the isolated batteries (highest fast voltage first, the fewest
    that suffice) discharge and everybody else stands by, when that is safe.

    A set ``T`` of isolated batteries held at least ``t_iso_hold`` qualifies when, carrying
    the present load alone with pessimistic resistances, it holds the bus ``v_iso_margin``
    above every other battery's fast voltage minus ``v_diode`` (no charge diode outside ``T``
    conducts, so R3 cannot pull a lower battery back in under it) and ``v_reserve`` above
    cut-off, and the batteries of ``T`` would not push more than ``v_co`` apart (fast
    voltages). The discharging batteries outside ``T`` go to plain STANDBY; the other
    isolated ones stay isolated until they merge with ``T`` (or their diodes would stay off,
    or the load forces them back). This is R1 applied to the isolated set; without it a
    higher isolated battery would wait while the lower ones drain, and be left with its
    energy at the end.
    """
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    isolated_since_s = st.isolated_since_s
    released_at_s = st.released_at_s
    ef = st.ef
    gp = st.gp
    ready = st.ready
    ing = st.ing
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    r = 0
    for i in range(ni):
        k = iso[i]
        since = isolated_since_s[p, k]
        if not math.isnan(since) and t - since + EPS_S >= prm.t_iso_hold:
            ready[r] = k
            r += 1
    _sort_desc(ready, r, ef)
    for j in range(n):
        ing[j] = False
    load0 = 0.0 if load_a < 0.0 else load_a  # max(load_a, 0.0): load_a unless 0.0 > it
    for m in range(1, r + 1):
        ing[ready[m - 1]] = True
        num = 0.0
        for i in range(m):
            j = ready[i]
            num += ef[j] * gp[j]
        den = 0.0
        for i in range(m):
            den += gp[ready[i]]
        v_alone = (num - load0) / den
        e_rest = -np.inf
        for j in range(n):
            if pres[j] and not ing[j] and math.isnan(isolated_since_s[p, j]) and ef[j] > e_rest:
                e_rest = ef[j]
        e_max = ef[ready[0]]
        e_min = ef[ready[0]]
        for i in range(1, m):
            x = ef[ready[i]]
            if x > e_max:
                e_max = x
            if x < e_min:
                e_min = x
        if e_max - e_min > prm.v_co:
            break
        if v_alone < e_rest - prm.v_diode + prm.v_iso_margin:
            continue
        if v_alone < prm.v_cut + prm.v_reserve:
            continue
        for j in range(n):
            if ing[j] or not pres[j]:
                continue
            if state[p, j] == DISCHARGING:
                _set(sw, ev, src, p, j, STANDBY, False, t, SET, R_TAKE_OVER)
        for i in range(m):
            j = ready[i]
            since = isolated_since_s[p, j]
            row = _set(sw, ev, src, p, j, DISCHARGING, True, t, JOIN_TAKE_OVER, R_TAKE_OVER)
            if row >= 0:
                ev.val[row, V_DATA] = v_alone
                ev.val[row, V_DATA + 1] = e_rest
                ev.val[row, V_DATA + 2] = t - (t if math.isnan(since) else since)
            conduct_since_s[p, j] = np.nan
            released_at_s[p, j] = t
        return True
    return False


@kernel_inline
def _release_isolated(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, volt: F64,
    cur: F64, pres: B1, t: float,
) -> None:  # fmt: skip
    """Bring an isolated battery back when that is safe, or when the load needs it.

    Not before ``t_iso_hold`` (unless forced), then the first that applies:

    * take-over (:func:`_take_over`, not while a charge diode conducts: R3 would then act on
      a current the take-over has just changed);
    * merge: with it engaged, the zero-load prediction puts at most ``i_merge`` into it and
      at most ``i_guard`` into anyone (the load merge's test), or at least no more than
      now into anyone (a battery between the engaged ones' fast voltages narrows a risk
      the guard could not open, and then lets the guard open the victim);
    * standby: at the present bus its charge diode stays off with ``v_iso_margin`` to
      spare, so plain STANDBY (diode-OR) is safe and R2 / load merge take it from there;
    * forced: the engaged batteries hold the bus less than ``v_reserve`` above cut-off (or
      none is engaged): plain STANDBY whatever the risk (it feeds the bus through its
      diode and R3 closes it): the load must stay supplied.
    """
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    isolated_since_s = st.isolated_since_s
    released_at_s = st.released_at_s
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    iso = st.iso
    ni = 0
    for k in range(n):
        if not math.isnan(isolated_since_s[p, k]):
            iso[ni] = k
            ni += 1
    if ni == 0:
        return
    ef = st.ef
    g = st.g
    pred = st.pred
    pred2 = st.pred2
    grp = st.grp
    grp2 = st.grp2
    load_a = _load(pres, cur)
    # A diode conducting now (R3 pending) was driven by the present bus; a take-over would
    # leave R3 acting on stale current. Wait until R3 has closed it.
    diode_on = False
    for j in range(n):
        if pres[j] and dsg_on[p, j] and not chg_on[p, j] and cur[j] > prm.i_det:
            diode_on = True
            break
    if not diode_on and _take_over(prm, st, ev, src, p, pres, iso, ni, load_a, t):
        return
    _sort_desc(iso, ni, ef)
    v_floor = prm.v_cut + prm.v_reserve
    for i in range(ni):
        k = iso[i]
        since = isolated_since_s[p, k]
        if math.isnan(since):
            continue
        m = _engaged(state, chg_on, p, grp, -1)
        # Bus estimate: the lowest engaged battery; with none engaged (R1 has just admitted
        # batteries with their charge FETs open) the highest admitted one less a diode drop;
        # with nobody admitted, nothing supplies the load but the diodes: forced.
        have_adm = False
        adm_max = 0.0
        for j in range(n):
            if pres[j] and state[p, j] == DISCHARGING and (not have_adm or volt[j] > adm_max):
                adm_max = volt[j]
                have_adm = True
        if m > 0:
            bus_v = volt[grp[0]]
            for q in range(1, m):
                if volt[grp[q]] < bus_v:
                    bus_v = volt[grp[q]]
        elif have_adm:
            bus_v = adm_max - prm.v_diode
        else:
            bus_v = -np.inf
        forced = bus_v < v_floor
        if not forced and t - since + EPS_S < prm.t_iso_hold:
            continue
        if m > 0:
            m2 = _engaged(state, chg_on, p, grp2, k)
            _zero_load(grp2, m2, ef, g, pred)
            _zero_load(grp, m, ef, g, pred2)
            worst = _max_over(grp, m, pred2)
            lim = worst if worst > prm.i_guard else prm.i_guard
            if pred[k] <= prm.i_merge and _max_over(grp2, m2, pred) <= lim:
                r = _set(sw, ev, src, p, k, DISCHARGING, True, t, JOIN_ISO_MERGE, R_ISO_MERGE)
                if r >= 0:
                    ev.val[r, V_DATA] = pred[k]
                    ev.val[r, V_DATA + 1] = t - since
                continue
        e_k = ef[k]
        quiet = bus_v >= e_k - prm.v_diode + prm.v_iso_margin
        if not (quiet or forced):
            continue
        _set(sw, ev, src, p, k, STANDBY, False, t, SET, R_NONE)
        released_at_s[p, k] = t
        r = emit(ev, p, src, RELEASED, k, t)
        ev.val[r, V_FROM] = STANDBY
        ev.val[r, V_TO] = STANDBY
        ev.val[r, V_REASON] = R_ISO_ENDED if quiet else R_ISO_FORCED
        ev.val[r, V_BATTERY] = k


# ------------------------------------------------------------------------------ the modes


@kernel_inline
def _discharge_tick(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, volt: F64,
    cur: F64, pres: B1, t: float, dt: float, n_inserted: int,
) -> None:  # fmt: skip
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    hold_load_a = st.hold_load_a
    guard_opened = st.guard_opened
    isolated_since_s = st.isolated_since_s
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    rest_since_s = st.rest_since_s
    ef = st.ef
    g = st.g
    pred = st.pred
    grp = st.grp
    order = st.order
    demoted = st.demoted
    keep = st.keep
    inserted = st.inserted
    was_c = st.was_c
    was_d = st.was_d
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    i_det = prm.i_det

    if not initialized[p]:
        _r1(prm, st, ev, src, p, volt, pres, t, R_R1_INIT)
        initialized[p] = True
        n_inserted = 0

    # Reverse current: a sibling is charging an engaged discharging battery. Only when some
    # other battery sources current; otherwise the charge comes from outside (mode logic).
    for k in range(n):
        demoted[k] = False
    for k in range(n):
        if state[p, k] == DISCHARGING and chg_on[p, k] and cur[k] < -prm.i_rev:
            feeder = False
            for j in range(n):
                if j != k and pres[j] and cur[j] > i_det:
                    feeder = True
                    break
            if feeder:
                r = _set(sw, ev, src, p, k, STANDBY, False, t, REVERSE, R_REVERSE)
                if r >= 0:
                    ev.val[r, V_DATA] = cur[k]
                    ev.val[r, V_DATA + 1] = prm.i_rev
                conduct_since_s[p, k] = np.nan
                demoted[k] = True

    # Hot insertion (R1 re-applied to the newcomer): a battery v_th above the bus takes over
    # and the batteries v_th below it stand by in the same period, so none is charged.
    if n_inserted > 0:
        for k in range(n):
            if not inserted[k]:
                continue
            v_ref = _v_ref(state, p, volt)
            if math.isnan(v_ref) or volt[k] - v_ref < prm.v_th:
                continue
            for j in range(n):
                if state[p, j] == DISCHARGING and volt[k] - volt[j] >= prm.v_th:
                    _set(sw, ev, src, p, j, STANDBY, False, t, SET, N_FIXED_REASONS + k)
            r = _set(sw, ev, src, p, k, DISCHARGING, False, t, INSERTED_ABOVE, R_INSERTED_ABOVE)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = v_ref

    # Source isolation [REC]: an isolated battery merges, takes over or is forced back.
    for k in range(n):
        if not math.isnan(isolated_since_s[p, k]):
            _release_isolated(prm, st, ev, src, p, volt, cur, pres, t)
            break

    # Nobody admitted to discharge and no diode conducting: start over with R1.
    any_d = False
    for k in range(n):
        if state[p, k] == DISCHARGING:
            any_d = True
            break
    if not any_d:
        diode = False
        for k in range(n):
            if pres[k] and cur[k] > i_det:
                diode = True
                break
        if not diode:
            _r1(prm, st, ev, src, p, volt, pres, t, R_R1_EMPTY)

    # R2: a standby battery v_co above the bus reference joins. Not one demoted for reverse
    # current this period: its terminal voltage still carries the charging I*R rise.
    # At rest (no battery carries more than i_det) terminal voltages are open-circuit
    # voltages, so a joiner v_co above the engaged batteries would push about
    # (V_k - V_ref) / R_loop into them: it takes over instead, and they stay admitted with
    # their charge FETs open until the load brings the bus down to them (level rule).
    v_ref = _v_ref(state, p, volt)
    idle = True
    for k in range(n):
        if pres[k] and not abs(cur[k]) <= i_det:
            idle = False
            break
    if not math.isnan(v_ref):
        m = 0
        for k in range(n):
            if state[p, k] == STANDBY and math.isnan(isolated_since_s[p, k]):
                order[m] = k
                m += 1
        _sort_desc(order, m, volt)
        for i in range(m):
            k = order[i]
            if demoted[k] or volt[k] - v_ref < prm.v_co:
                continue
            if idle:
                for j in range(n):
                    if state[p, j] == DISCHARGING:
                        chg_on[p, j] = False
            r = _set(sw, ev, src, p, k, DISCHARGING, idle, t, JOIN_R2, R_R2)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = v_ref
                ev.val[r, V_DATA + 2] = volt[k] - v_ref
                ev.val[r, V_DATA + 3] = 1.0 if idle else 0.0
            if idle:
                v_ref = volt[k]

    # Rest merge [REC]: at rest (every battery at or below i_det for t_rest), a standby or
    # admitted battery whose voltage is within v_merge = i_merge * r_loop_ohm of every
    # engaged battery rejoins with its charge FET on, as R1 admits batteries within v_th at
    # power-up: closing it pushes at most about i_merge between them. Without it a battery
    # demoted by reverse current when the load stopped can only come back by R2 (it is
    # lower, so never) or R3 (its diode needs the bus 0.6 V below it, which the remaining
    # batteries alone may not reach before the load's own under-voltage lock-out cuts it).
    if idle:
        if math.isnan(rest_since_s[p]):
            rest_since_s[p] = t
    else:
        rest_since_s[p] = np.nan
    rest = rest_since_s[p]
    rested = not math.isnan(rest) and t - rest + EPS_S >= prm.t_rest
    have_eng = False
    lo = 0.0
    hi = 0.0
    for k in range(n):
        if state[p, k] == DISCHARGING and chg_on[p, k]:
            v = volt[k]
            if not have_eng:
                lo = v
                hi = v
                have_eng = True
            else:
                if v < lo:
                    lo = v
                if v > hi:
                    hi = v
    if rested and have_eng:
        m = 0
        for k in range(n):
            if (
                not demoted[k]
                and not chg_on[p, k]
                and math.isnan(isolated_since_s[p, k])
                and (state[p, k] == STANDBY or state[p, k] == DISCHARGING)
            ):
                order[m] = k
                m += 1
        _sort_desc(order, m, volt)
        for i in range(m):
            k = order[i]
            new_lo = volt[k] if volt[k] < lo else lo
            new_hi = volt[k] if volt[k] > hi else hi
            if new_hi - new_lo > prm.v_merge:
                continue
            r = _set(sw, ev, src, p, k, DISCHARGING, True, t, JOIN_REST, R_REST_MERGE)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = lo
                ev.val[r, V_DATA + 2] = hi
                ev.val[r, V_DATA + 3] = prm.v_merge
            conduct_since_s[p, k] = np.nan
            lo = new_lo
            hi = new_hi

    # Load merge [REC]: under load, a standby (or admitted, not engaged) battery whose fast
    # voltage matches the engaged ones' (zero-load current into any of them <= i_merge and
    # none pushed past i_guard) closes its charge FET: it sources at once and the guard
    # would not open anybody. This is the rest merge with IR-compensated voltages; it brings
    # back a battery the guard opened as soon as the others have come down to it, before
    # R2 (v_co above the loaded bus) or R3 (a diode drop below it) would.
    if not idle and _engaged(state, chg_on, p, grp, -1) > 0:
        m = 0
        for k in range(n):
            if (
                not demoted[k]
                and pres[k]
                and not chg_on[p, k]
                and math.isnan(isolated_since_s[p, k])
                and (state[p, k] == STANDBY or state[p, k] == DISCHARGING)
            ):
                order[m] = k
                m += 1
        _sort_desc(order, m, volt)
        for i in range(m):
            k = order[i]
            m2 = _engaged(state, chg_on, p, grp, k)
            _zero_load(grp, m2, ef, g, pred)
            if pred[k] > prm.i_merge or _max_over(grp, m2, pred) > prm.i_guard:
                continue
            r = _set(sw, ev, src, p, k, DISCHARGING, True, t, JOIN_LOAD, R_LOAD_MERGE)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = pred[k]
                ev.val[r, V_DATA + 2] = prm.i_merge
            conduct_since_s[p, k] = np.nan

    # Level rule: an admitted battery at or above the engaged batteries cannot be charged by
    # them *now*, so its charge FET may close directly (this completes an R2 join at once),
    # provided the cross-current guard agrees: under load a joiner v_co above the loaded
    # bus may still have a lower fast voltage (V + I*R) than an engaged battery, which would
    # charge it if the load vanished. Such a joiner stays admitted with its FET open (it
    # cannot be charged, its diode still lets it feed the bus) until the others have come
    # down to it. Highest first, each compared with everything engaged so far, so two
    # batteries joining in the same period cannot close onto each other.
    have_eng = False
    v_eng = 0.0
    for k in range(n):
        if state[p, k] == DISCHARGING and chg_on[p, k] and (not have_eng or volt[k] > v_eng):
            v_eng = volt[k]
            have_eng = True
    if have_eng:
        m = 0
        for k in range(n):
            if state[p, k] == DISCHARGING and not chg_on[p, k]:
                order[m] = k
                m += 1
        _sort_desc(order, m, volt)
        for i in range(m):
            k = order[i]
            if volt[k] >= v_eng:
                m2 = _engaged(state, chg_on, p, grp, k)
                _zero_load(grp, m2, ef, g, pred)
                if pred[k] <= prm.i_merge:
                    chg_on[p, k] = True
                    conduct_since_s[p, k] = np.nan
                    if volt[k] > v_eng:
                        v_eng = volt[k]

    # R3: charge diode conducting (charge FET off, discharge FET on, discharge current).
    # Only current measured over a period in which this controller held the charge FET off
    # and the discharge FET on can have flowed through the diode.
    for k in range(n):
        keep[k] = False
    for k in range(n):
        if (state[p, k] != DISCHARGING and state[p, k] != STANDBY) or chg_on[p, k]:
            conduct_since_s[p, k] = np.nan
            continue
        through = (not was_c[k]) and was_d[k] and cur[k] > i_det
        if not _diode_rule(prm, state, conduct_since_s, ev, src, p, k, through, t, dt):
            continue
        if state[p, k] == STANDBY:
            r = _set(sw, ev, src, p, k, DISCHARGING, True, t, JOIN_R3, R_R3)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = cur[k]
        else:
            chg_on[p, k] = True
        keep[k] = True
        if guard_opened[p, k]:
            # The guard opened it and the load made its diode conduct anyway: keep it
            # engaged at this load instead of opening it every other period.
            hold_load_a[p, k] = _load(pres, cur)
            guard_opened[p, k] = False

    _guard(prm, st, ev, src, p, pres, cur, t)
    v_ref_v[p] = _v_ref(state, p, volt)


@kernel_inline
def _charge_tick(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, cur: F64,
    pres: B1, t: float, dt: float,
) -> None:  # fmt: skip
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    at_risk = st.at_risk
    isolated_since_s = st.isolated_since_s
    zero_load_into_a = st.zero_load_into_a
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    rest_since_s = st.rest_since_s
    zero_load_valid = st.zero_load_valid
    was_c = st.was_c
    was_d = st.was_d
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    i_det = prm.i_det
    if not initialized[p]:
        for k in range(n):
            if pres[k]:
                _set(sw, ev, src, p, k, CHARGING, False, t, SET, R_CHARGE_MODE)
                conduct_since_s[p, k] = np.nan
        initialized[p] = True
    for k in range(n):
        if pres[k] and state[p, k] != CHARGING:
            _set(sw, ev, src, p, k, CHARGING, False, t, SET, R_INSERTED_CHARGING)
    # Mirror of the reverse-current rule: a charging battery feeding a sibling opens its
    # discharge FET, so its discharge diode blocks discharge again.
    for k in range(n):
        if state[p, k] == CHARGING and dsg_on[p, k] and cur[k] > prm.i_rev:
            sink = False
            for j in range(n):
                if j != k and pres[j] and cur[j] < -i_det:
                    sink = True
                    break
            if sink:
                dsg_on[p, k] = False
                conduct_since_s[p, k] = np.nan
                r = emit(ev, p, src, REVERSE_DSG, k, t)
                ev.val[r, 0] = cur[k]
                ev.val[r, 1] = prm.i_rev
                ev.val[r, 2] = PATH_DSG
                ev.val[r, 3] = k
    # R4: discharge diode conducting (discharge FET off, charging current).
    for k in range(n):
        if state[p, k] != CHARGING or dsg_on[p, k]:
            conduct_since_s[p, k] = np.nan
            continue
        through = was_c[k] and (not was_d[k]) and cur[k] < -i_det
        if _diode_rule(prm, state, conduct_since_s, ev, src, p, k, through, t, dt):
            dsg_on[p, k] = True
    v_ref_v[p] = np.nan
    rest_since_s[p] = np.nan
    zero_load_valid[p] = False
    for k in range(n):
        zero_load_into_a[p, k] = np.nan
        at_risk[p, k] = False


# ------------------------------------------------------------------------------ the step


@kernel_inline
def _validate(
    mode: I64, last_t_s: F64, fault: F64, p: int, t: float, dt_s: float, reported: B1,
    pres: B1, volt: F64, cur: F64,
) -> bool:  # fmt: skip
    """Why the sample is unusable, into ``fault[p]`` if the pack is not in the fail-safe yet
    (then the reason stays the first one of the episode); returns False if it is fine."""
    n = reported.shape[0]
    code = FAULT_NONE
    a = 0.0
    x = np.nan
    y = np.nan
    n_reported = 0
    for k in range(n):
        if reported[k]:
            n_reported += 1
    last = last_t_s[p]
    if n_reported != n:
        code = FAULT_COUNT
        a = n_reported
    elif not math.isfinite(t):
        code = FAULT_T
        x = t
    elif not math.isfinite(dt_s) or dt_s < 0.0:
        code = FAULT_DT
        x = dt_s
    elif not math.isnan(last) and t < last:
        code = FAULT_BACKWARDS
        x = last
        y = t
    else:
        for k in range(n):
            if not pres[k]:
                continue
            v = volt[k]
            if not math.isfinite(v) or v < 0.0:
                code = FAULT_VOLTAGE
                a = k
                x = v
                break
            c = cur[k]
            if not math.isfinite(c):
                code = FAULT_CURRENT
                a = k
                x = c
                break
    if code == FAULT_NONE:
        return False
    if mode[p] != MODE_FAULT:
        fault[p, 0] = code
        fault[p, 1] = a
        fault[p, 2] = x
        fault[p, 3] = y
    return True


@kernel_inline
def _fail_safe(
    st: SequencingState, p: int, reported: B1, pres: B1, ev: EventBuf, src: int, t: float
) -> None:
    """Every charge FET off, every present battery's discharge FET on (STANDBY), one Fault
    event per episode."""
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    at_risk = st.at_risk
    isolated_since_s = st.isolated_since_s
    zero_load_into_a = st.zero_load_into_a
    mode = st.mode
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    rest_since_s = st.rest_since_s
    zero_load_valid = st.zero_load_valid
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    if mode[p] != MODE_FAULT:
        r = emit(ev, p, src, FAULT, -1, t)
        ev.val[r, 0] = p  # the reason is read from st.fault[p] by the renderer
        ev.val[r, 1] = mode[p]
        mode[p] = MODE_FAULT
    same_n = True
    for k in range(n):
        if not reported[k]:
            same_n = False
    for k in range(n):
        present = pres[k] if same_n else state[p, k] != OFF
        new = STANDBY if present else OFF
        _set(sw, ev, src, p, k, new, False, t, SET, R_FAIL_SAFE)
        conduct_since_s[p, k] = np.nan
    initialized[p] = False
    v_ref_v[p] = np.nan
    rest_since_s[p] = np.nan
    zero_load_valid[p] = False
    for k in range(n):
        zero_load_into_a[p, k] = np.nan
        at_risk[p, k] = False


@kernel_inline
def _update_resistance(
    prm: SequencingParams, r_ohm: F64, last_v_v: F64, last_i_a: F64, ef: F64, g: F64, gp: F64,
    p: int, volt: F64, cur: F64, pres: B1,
) -> None:  # fmt: skip
    """Resistance estimate per battery: -dV/dI over the last current step >= ``i_step``.

    Voltages are battery-side, so the quotient is the battery's ohmic resistance whatever
    its FETs or diodes did; over one control period OCV and polarisation hardly move. Then
    the per-step values every rule shares: the fast voltage V + I*R (the voltage a battery
    shows the instant its current drops to zero: OCV minus the polarisation), 1 / R and
    1 / the pessimistic R (1.25 x the estimate, 2 x the prior before any current step).
    """
    n = pres.shape[0]
    r_batt = prm.r_batt_ohm
    for k in range(n):
        if not pres[k]:
            last_v_v[p, k] = np.nan
            last_i_a[p, k] = np.nan
            continue
        lv = last_v_v[p, k]
        li = last_i_a[p, k]
        if not math.isnan(lv) and not math.isnan(li):
            di = cur[k] - li
            if abs(di) >= prm.i_step:
                r = -(volt[k] - lv) / di
                if 0.0 < r <= 20.0 * r_batt:
                    r_ohm[p, k] = r
        last_v_v[p, k] = volt[k]
        last_i_a[p, k] = cur[k]
    for k in range(n):
        r = r_ohm[p, k]
        nan_r = math.isnan(r)
        r_est = r_batt if nan_r else r
        ef[k] = volt[k] + cur[k] * r_est
        g[k] = 1.0 / r_est
        gp[k] = 1.0 / ((2.0 if nan_r else 1.25) * r_est)


@kernel_inline
def _update_mode(
    prm: SequencingParams, mode: I64, mode_evidence_since_s: F64, initialized: B1,
    conduct_since_s: F64, ev: EventBuf, src: int, p: int, cur: F64, pres: B1, docked: bool,
    t: float,
) -> None:  # fmt: skip
    """Docking switches to charge mode at once; charging current alone must persist t_mode.
    Charge mode ends t_mode after the dock is gone and the pack is no longer charged."""
    pack_i = _load(pres, cur)
    charging_seen = pack_i < -prm.i_det
    if mode[p] == MODE_DISCHARGE:
        evidence = charging_seen
        switch = docked
        new_mode = MODE_CHARGE
    else:
        evidence = not (docked or charging_seen)
        switch = False
        new_mode = MODE_DISCHARGE
    if not evidence:
        mode_evidence_since_s[p] = np.nan
    else:
        if math.isnan(mode_evidence_since_s[p]):
            mode_evidence_since_s[p] = t
        persisted = t - mode_evidence_since_s[p]
        switch = switch or persisted + EPS_S >= prm.t_mode
    if not switch:
        return
    any_present = False
    for k in range(pres.shape[0]):
        if pres[k]:
            any_present = True
    r = emit(ev, p, src, MODE if any_present else MODE_NO_BATTERY, -1, t)
    ev.val[r, 0] = mode[p]
    ev.val[r, 1] = new_mode
    ev.val[r, 2] = 1.0 if docked else 0.0
    ev.val[r, 3] = pack_i
    mode[p] = new_mode
    mode_evidence_since_s[p] = np.nan
    initialized[p] = False
    for k in range(pres.shape[0]):
        conduct_since_s[p, k] = np.nan


@kernel_inline
def _output(
    st: SequencingState, p: int, cmd: CmdArrays, status: F64, s0: int
) -> None:  # fmt: skip
    """The FET commands (an opinion on every path, every step) and the status channels."""
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    at_risk = st.at_risk
    isolated_since_s = st.isolated_since_s
    zero_load_into_a = st.zero_load_into_a
    mode = st.mode
    last_t_s = st.last_t_s
    v_ref_v = st.v_ref_v
    zero_load_valid = st.zero_load_valid
    last = last_t_s[p]
    v_ref = v_ref_v[p]
    for k in range(state.shape[1]):
        put_chg(cmd, p, k, bool(chg_on[p, k]))
        put_dsg(cmd, p, k, bool(dsg_on[p, k]))
        status[p, k, s0 + ST_STATE] = state[p, k]
        status[p, k, s0 + ST_CHG] = 1.0 if chg_on[p, k] else 0.0
        status[p, k, s0 + ST_DSG] = 1.0 if dsg_on[p, k] else 0.0
        status[p, k, s0 + ST_MODE] = mode[p]
        status[p, k, s0 + ST_V_REF] = v_ref
        zl = zero_load_into_a[p, k] if zero_load_valid[p] else 0.0
        status[p, k, s0 + ST_ZERO_LOAD] = zl
        status[p, k, s0 + ST_AT_RISK] = 1.0 if at_risk[p, k] else 0.0
        iso = not math.isnan(isolated_since_s[p, k])
        status[p, k, s0 + ST_ISOLATED] = 1.0 if iso else 0.0
        since = conduct_since_s[p, k]
        diode_s = 0.0 if math.isnan(since) or math.isnan(last) else last - since
        status[p, k, s0 + ST_DIODE] = diode_s


@kernel_inline
def step_pack(
    prm: SequencingParams, st: SequencingState, tp: PackArrays, m: MeasArrays, p: int,
    dt_s: float, cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    """One control period of pack ``p``: validate, track presence and mode, apply the rules."""
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    isolated_since_s = st.isolated_since_s
    mode = st.mode
    initialized = st.initialized
    last_t_s = st.last_t_s
    mode_evidence_since_s = st.mode_evidence_since_s
    sw = Switches(state, chg_on, dsg_on, isolated_since_s)
    n = state.shape[1]
    t_meas = m.t_s[p]
    bat = m.bat
    volt = bat.voltage_v[p]
    cur = bat.current_a[p]
    pres = bat.present[p]
    reported = bat.reported[p]
    if _validate(mode, last_t_s, st.fault, p, t_meas, dt_s, reported, pres, volt, cur):
        last = last_t_s[p]
        if math.isfinite(t_meas):
            t = t_meas
        elif math.isnan(last) or last == 0.0:
            t = 0.0  # the scalar ``last_t_s or 0.0``
        else:
            t = last
        _fail_safe(st, p, reported, pres, ev, src, t)
        _output(st, p, cmd, status, s0)
        return

    t = t_meas
    last_t_s[p] = t
    if mode[p] == MODE_FAULT:
        r = emit(ev, p, src, FAULT_CLEARED, -1, t)
        ev.val[r, 0] = p
        mode[p] = MODE_DISCHARGE
        mode_evidence_since_s[p] = np.nan
        initialized[p] = False

    # FETs in force over the period the measurements cover (our previous commands).
    inserted = st.inserted
    was_c = st.was_c
    was_d = st.was_d
    for k in range(n):
        was_c[k] = chg_on[p, k]
        was_d[k] = dsg_on[p, k]
    # Presence: removal -> OFF; insertion -> STANDBY (R1/R2 decide when it joins).
    n_ins = 0
    for k in range(n):
        inserted[k] = False
        if not pres[k] and state[p, k] != OFF:
            _set(sw, ev, src, p, k, OFF, False, t, SET, R_REMOVED)
            conduct_since_s[p, k] = np.nan
        elif pres[k] and state[p, k] == OFF and initialized[p]:
            _set(sw, ev, src, p, k, STANDBY, False, t, SET, R_INSERTED)
            inserted[k] = True
            n_ins += 1

    _update_resistance(
        prm, st.r_ohm, st.last_v_v, st.last_i_a, st.ef, st.g, st.gp, p, volt, cur, pres
    )
    docked = bool(m.docked[p])
    _update_mode(
        prm, mode, mode_evidence_since_s, initialized, conduct_since_s, ev, src, p, cur, pres,
        docked, t,
    )  # fmt: skip
    if mode[p] == MODE_CHARGE:
        _charge_tick(prm, st, ev, src, p, cur, pres, t, dt_s)
    else:
        _discharge_tick(prm, st, ev, src, p, volt, cur, pres, t, dt_s, n_ins)
    _output(st, p, cmd, status, s0)


@kernel
def step_packs(
    prm: SequencingParams, st: SequencingState, tp: PackArrays, m: MeasArrays, dt_s: float,
    cmd: CmdArrays, ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        step_pack(prm, st, tp, m, p, dt_s, cmd, ev, src, status, s0)


def max_events(n: int) -> int:
    """Upper bound of the events one pack can emit in one step (N batteries)."""
    return n * n + 16 * n + 8
