"""Discharge sequencing of parallel batteries behind charge/discharge MOSFET pairs, compiled.

Spec: ``spec/parallel_discharge.md`` (DJI CN 201680002560.8), generalised to N >= 2 batteries;
issue #15 section 1 supersedes the spec's [REC] where they disagree (docs/parallel_discharge.md).
Each battery sits behind a charge FET (its body diode conducts when the battery *discharges*)
in series with a discharge FET (its diode conducts when the battery is *charged*). A battery
whose charge FET is off can feed the bus through the diode but can never be charged by a
higher sibling, so directly paralleled batteries at different voltages do not push tens of
amperes into each other.

States (per battery) and the FET pattern each one commands:

* ``DISCHARGING`` - admitted to discharge: discharge FET on; charge FET on while *engaged*.
  The charge FET is on only while the battery discharges (embodiments 5 and 7): it closes
  when discharge current flows (R3, through the diode) or is predicted to flow at the present
  load (the engage rule, which completes R2), and opens when charging current is seen.
* ``STANDBY`` - discharge FET on, charge FET off (the charge diode blocks any charging).
* ``CHARGING`` - charge FET on; discharge FET on once charging current is seen (R4).
* ``OFF`` - both FETs off: the battery is not present.

The invariant (issue #15): current into a battery never exceeds its charge limit
(``charge_limit_c`` x capacity), any reverse current is cut within one control period (plus
the FET's switching delay), and reverse current above 1 A never lasts longer than that.

Rules applied every control period in discharge mode (see ``docs/parallel_discharge.md``):

* R1 at (re)initialisation (power-up, fault recovery, return from charge mode, empty
  discharging set): batteries within ``v_th`` of the highest are admitted (DISCHARGING), the
  others stand by. A hot-inserted battery ``v_th`` or more above the bus reference takes over
  (R1 re-applied to it); any other inserted battery starts in STANDBY.
* Reverse cut (embodiment 5): an engaged battery taking more than ``i_rev`` of charge from a
  sibling, or ``q_rev_as`` of charge in one episode of smaller reverse current (a light-load
  circulating current), has its charge FET opened at once. It stays admitted (DISCHARGING):
  the engage rule or R3 closes the FET again when it would discharge, so a load drop costs
  one FET opening and no state change.
* R2: a standby battery joins (DISCHARGING) once its *fast voltage* ``E = V + I*R`` (R
  estimated online; the open-circuit voltage minus polarisation) is within ``v_co`` of the
  highest admitted battery's, or above it: "the voltages meet".
* Engage (R2's FET action): an admitted battery whose charge FET is open closes it when, with
  it engaged, (a) at the present load it would discharge and nobody engaged would take more
  than ``i_rev / 2`` (hysteresis against the reverse cut), and (b) if the load vanished, no
  battery would take more than its charge limit. Highest fast voltage first.
* R3: a battery with discharge FET on and charge FET off that sources more than ``i_det``
  (its charge diode conducts) gets its charge FET on after a debounce, no later than ``t_on``.
  Only current measured over a period in which the controller held that FET off counts. If,
  engaged, it would charge an engaged sibling by more than ``i_rev`` at the present load, that
  sibling's charge FET opens in the same period (hand-over to the higher battery).
  R3 outranks (b): the diode must not carry the current; if the zero-load prediction then
  exceeds a charge limit the battery is flagged (``CrossCurrentRisk``) and the reverse cut
  (or the plant's reverse-current comparator, ``[pack.switch] reverse_comparator``) bounds it.

Invalid measurements (a battery missing from the sample; non-finite or negative voltage,
non-finite current, time or period) put the pack in a fail-safe: every charge FET off, every
present battery's discharge FET on (the pack can discharge only through the charge diodes,
nothing can be charged), with one ``Fault`` event. When measurements are valid again the
controller re-initialises with R1.

Deterministic: the only clock is the sample time ``m.t_s[p]`` (for timers) and ``dt_s`` (the
control period, used to predict whether waiting one more period would miss the ``t_on``
deadline). "None" is NaN (floats) or -1 (indices), a ranking is a stable insertion sort, sums
run from 0 left to right. Arrays are bound to local names once per function (a tuple
attribute read in a loop costs a reference-count round trip in numba).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.control.commands import emit, fmin, put_chg, put_dsg
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

EPS_S = 1e-9
"""Tolerance for comparing accumulated times, so 0.1 + 0.1 + 0.1 counts as 0.3 s."""
R3_HOLD_S = 5.0
"""Rule 8b does not open a battery R3 closed less than this long ago (``forced_s``), unless
rule 8c would hold it on its diode once opened (:func:`_r3_holds_off`)."""
ZL_DWELL_S = 30.0
"""A battery rule 8b opened stays open at least this long (about the RC time constant of the
cell sets shipped, uav_5ah's 30 s): the engage rule does not close it before."""

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
"""The reverse cut opened an engaged battery's charge FET (ReverseCurrent, no state change)."""
INSERTED_ABOVE = 3
JOIN_R2 = 4
JOIN_R3 = 5
DIODE = 6
REVERSE_DSG = 7
RISK = 8
MODE = 9
MODE_NO_BATTERY = 10
"""ModeChanged with no battery present: the scalar pack current was the integer 0."""
FAULT = 11
FAULT_CLEARED = 12
HANDOVER = 13
"""A sibling would charge this engaged battery at the present load once a cut or an R3 closure
has changed the engaged set: its charge FET opened (ReverseCurrent, predicted, no state
change)."""
ZERO_LOAD_OPEN = 14
"""The observer-based zero-load prediction put this engaged battery above ``open_ratio`` x its
charge limit: its charge FET opened (CrossCurrentRisk, no state change; rule 8b)."""
DIODE_HOLD = 15
"""R3 keeps this battery's charge FET off although its diode conducts: with it engaged the
trusted zero-load prediction would put it above ``hold_ratio`` x its charge limit, and its
diode carries no more than ``diode_hold_a`` (CrossCurrentRisk, once per episode; rule 8c)."""

# Slots of a state-change event: from, to, reason, battery (message only), then the data.
V_FROM = 0
V_TO = 1
V_REASON = 2
V_BATTERY = 3
V_DATA = 4

# Reason labels (``controller.REASON_LABELS``); then "R1 battery {k} inserted" for each k.
R_NONE = 0
R_FAIL_SAFE = 1
R_REMOVED = 2
R_INSERTED = 3
R_CHARGE_MODE = 4
R_INSERTED_CHARGING = 5
R_R1_INIT = 6
R_R1_EMPTY = 7
R_INSERTED_ABOVE = 8
R_R2 = 9
R_R3 = 10
R_HELD = 11
"""Another layer held the battery's discharge path open (:func:`_held_out`)."""
N_FIXED_REASONS = 12

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
ST_DIODE = 7


class SequencingParams(NamedTuple):
    v_th: float
    v_co: float
    i_det: float
    t_on: float
    t_debounce: float
    i_rev: float
    q_rev_as: float
    """Slow reverse cut: charge (A s) a sibling may push into an engaged battery per episode."""
    t_mode: float
    charge_limit_c: float
    """Charge limit per battery in C: at most charge_limit_c x capacity_ah amperes into it."""
    charge_limit_margin: float
    """Share of the charge limit a zero-load prediction may reach (the prediction's error)."""
    risk_clear_ratio: float
    """The zero-load risk flag clears below this fraction of the charge limit (hysteresis)."""
    default_capacity_ah: float
    """Capacity assumed where the topology does not state one (replay logs)."""
    r_batt_ohm: float
    i_step: float
    zero_load_observer: bool
    """Take the zero-load prediction's R0 from the battery observer where it is trusted."""
    open_ratio: float
    """Rule 8b: an engaged battery whose trusted zero-load prediction exceeds this fraction of
    its charge limit has its charge FET opened."""
    diode_hold_a: float
    """Rule 8c: R3 leaves a battery on its charge diode while the diode carries at most this
    (A) and the trusted zero-load prediction with it engaged puts it above ``hold_ratio`` x its
    charge limit; 0 = off (R3 closes on its deadline, as the spec says)."""
    hold_ratio: float
    """Rule 8c's threshold, a fraction of the charge limit: ``charge_limit_margin`` (the
    engage rule's), below rule 8b's ``open_ratio``. A held battery R3 closes takes more current
    and polarises, so its prediction rises after the closure; at 0.95 it crossed the limit
    within 3 s, before rule 8b may open a battery R3 closed (``bench_zero_load`` seed 230)."""
    reads_slot: I64
    """Status slots of the observer's channels (``controller.READS``: its battery R0 and its
    trust flag), written by the core (``Method.reads``); -1 = no observer in this core."""
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
    at_risk: B1
    """The zero-load prediction puts more than its charge limit into this engaged battery."""
    rev_q_as: F64
    """Charge (A s) pushed into this engaged battery by siblings in the present episode of
    reverse current (0 when it sources or is not engaged)."""
    zero_load_into_a: F64
    """Zero-load prediction of the last discharge period (valid where ``zero_load_valid``)."""
    mode: I64
    """(P,) MODE_DISCHARGE, MODE_CHARGE or MODE_FAULT."""
    initialized: B1
    last_t_s: F64
    """(P,) time of the last valid sample; NaN = none yet."""
    mode_evidence_since_s: F64
    """(P,) first sample of the current run of evidence for leaving the mode."""
    v_ref_v: F64
    """(P,) bus reference of the last period (highest admitted fast voltage)."""
    zero_load_valid: B1
    """(P,)."""
    fault: F64
    """(P, N_FAULT) the last fail-safe reason: code (FAULT_*), then its numbers; kept after
    the fault clears (the FaultCleared event names it)."""
    forced_s: F64
    """(P, B) when R3 last closed this battery's charge FET (its diode carried current; NaN:
    not since it was engaged): rule 8b leaves it engaged for ``R3_HOLD_S`` after that
    (opening it at once could put the current back on the diode, R3 would close it again
    in the next period: chatter)."""
    forced_a: F64
    """(P, B) the current its diode carried in the period R3 closed it (valid with
    ``forced_s``): within ``diode_hold_a`` rule 8c would hold it on the diode if it were opened
    again, so rule 8b need not wait ``R3_HOLD_S`` (:func:`_r3_holds_off`)."""
    zl_open_s: F64
    """(P, B) when rule 8b opened this battery's charge FET (NaN: it has been engaged since,
    or never): the engage rule closes it again only ``ZL_DWELL_S`` later and with its own
    prediction within ``risk_clear_ratio`` x its limit (not ``charge_limit_margin``), so an
    opened battery does not chatter about the threshold (its prediction jumps by I x the
    error of R0 when it takes current again, and its polarisation builds again)."""
    diode_held: B1
    """(P, B) rule 8c holds this battery's charge FET off in the present diode-conduction
    episode (its event was emitted; cleared when the diode stops conducting)."""
    held: B1
    """(P, B) another layer (protection, limits, plausibility, the supervisor) opened this
    MOSFET-pair battery's discharge FET in the last step although sequencing commanded it on:
    written by :func:`close_out_pack` from the final commands, read by the next step
    (:func:`_held_out`). Never set for a relay battery (its STANDBY is open)."""
    # Scratch, (B,): values of the pack being stepped, nothing carried between steps (packs
    # are stepped one after the other; a State is never stepped by two threads at once).
    ef: F64
    """Fast voltage V + I*R of each battery."""
    g: F64
    """1 / R estimate."""
    ez: F64
    """Fast voltage for the zero-load prediction: V + I * R0 with the observer's R0 where
    it is trusted, else ``ef`` (:func:`_zero_load_sources`)."""
    gz: F64
    """1 / R0 for the zero-load prediction (else ``g``)."""
    zl_obs: B1
    """This battery's ``ez``/``gz`` are the observer's (trusted) this period."""
    i_lim: F64
    """Charge limit (A) of each battery in this pack."""
    pred: F64
    grp: I64
    order: I64
    cut: B1
    skip: B1
    """Batteries a re-prediction may not open this period (measured sourcing, or closed by
    R3)."""
    inserted: B1
    was_c: B1
    was_d: B1


class Switches(NamedTuple):
    """The arrays a state change writes (built once per kernel from the State)."""

    state: I64
    chg_on: B1
    dsg_on: B1


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
def _share(grp: I64, m: int, ef: F64, g: F64, load_a: float, out: F64) -> None:
    """Current (A, > 0 = charging) into each battery of ``grp[:m]`` if they alone carried
    ``load_a`` (0 = the load vanished).

    The engaged batteries form a loop of voltage sources behind their resistances: the bus
    settles at (sum E g - load) / sum g. FET on-resistances are left out, which overestimates
    any current between them (the safe side).
    """
    if m < 1:
        return
    num = 0.0
    for i in range(m):
        k = grp[i]
        num += ef[k] * g[k]
    den = 0.0
    for i in range(m):
        den += g[grp[i]]
    v0 = (num - load_a) / den
    for i in range(m):
        k = grp[i]
        out[k] = (v0 - ef[k]) * g[k]


@kernel_inline
def _max_discharging(state: I64, p: int, x: F64) -> float:
    """Highest ``x`` over the DISCHARGING batteries (NaN: none). With the fast voltages: the
    bus reference for R2 (admitted batteries whose charge FET is still open count too, so a
    standby battery joins only when it meets every battery already admitted to discharge);
    with the terminal voltages: the reference for hot insertion."""
    have = False
    v = np.nan
    for k in range(state.shape[1]):
        if state[p, k] == DISCHARGING and (not have or x[k] > v):
            v = x[k]
            have = True
    return v


@kernel_inline
def _charge_in(pres: B1, cur: F64, can_charge: B1) -> float:
    """Pack current as evidence of charging: the present batteries' currents, where a battery
    whose charge path does not conduct (feedback) counts no charging current — it cannot
    take any, so a negative reading there is its sensor's, and one battery's implausible
    reading must not move the others' switches into charge mode (issue #26: a standby
    battery reading -30 A opened the healthy battery's discharge FET in flight)."""
    tot = 0.0
    for k in range(pres.shape[0]):
        if pres[k]:
            c = cur[k]
            tot += c if can_charge[k] or not c < 0.0 else 0.0
    return tot


@kernel_inline
def _r1(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, volt: F64,
    pres: B1, t: float, reason: int,
) -> None:  # fmt: skip
    """R1: within ``v_th`` of the highest -> DISCHARGING (not yet engaged), else STANDBY."""
    state = st.state
    conduct_since_s = st.conduct_since_s
    held = st.held
    sw = Switches(state, st.chg_on, st.dsg_on)
    n = state.shape[1]
    have = False
    v_max = 0.0
    for k in range(n):
        if pres[k] and not held[p, k] and (not have or volt[k] > v_max):
            v_max = volt[k]
            have = True
    for k in range(n):
        if not pres[k]:
            continue
        new = DISCHARGING if v_max - volt[k] < prm.v_th else STANDBY
        if held[p, k]:
            new = STANDBY  # cannot discharge while another layer holds it open
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


# ------------------------------------------------------------------------------ discharge mode


@kernel_inline
def _held_out(st: SequencingState, ev: EventBuf, src: int, p: int, t: float) -> None:
    """A battery another layer held open in the last step stands by (charge FET off).

    Sequencing's commands are wishes: protection, the limits, plausibility (a stale or
    implausible battery kept as a reserve) and the supervisor may open a path after it. A
    battery whose discharge path was held open carried no current over that period (its
    readings may be frozen or stale), and the OCVs of it and its siblings drift apart
    meanwhile: it rested, they discharged and polarised. Had it stayed DISCHARGING with its
    charge FET on, the step that releases it would connect it to the bus directly, and the
    rested, higher battery would push the voltage difference over two resistances into an
    engaged sibling (issue #26: 15.8 A into a 9.7 A-limited battery after a 35 s isolation).
    In STANDBY it is released onto the bus through its charge FET's body diode (it can only
    discharge) and rejoins as any standby battery does: R2 once the fast voltages meet, R3
    with its hand-over once its diode carries current (the sibling it would charge is opened
    in that period), the engage rule only with every zero-load prediction within the limit.
    Over the held period its FETs did not conduct, whatever sequencing commanded. MOSFET
    pairs only (``close_out_pack``): a relay has no diode, its STANDBY is open, and standing
    a held relay battery by would withhold the reserve plausibility brings in when the last
    trusted source trips; a relay's release stays a direct closure."""
    state = st.state
    held = st.held
    sw = Switches(state, st.chg_on, st.dsg_on)
    for k in range(state.shape[1]):
        if not held[p, k]:
            continue
        st.was_c[k] = False
        st.was_d[k] = False
        st.conduct_since_s[p, k] = np.nan
        st.rev_q_as[p, k] = 0.0
        if state[p, k] == DISCHARGING:
            _set(sw, ev, src, p, k, STANDBY, False, t, SET, R_HELD)


@kernel_inline
def _zl_may_engage(
    prm: SequencingParams, st: SequencingState, p: int, k: int, pred: float, lim: float,
    t: float,
) -> bool:  # fmt: skip
    """May the engage rule close battery ``k`` again (rule 8b's dwell and hysteresis)?"""
    since = st.zl_open_s[p, k]
    if math.isnan(since):
        return True
    return t - since >= ZL_DWELL_S - EPS_S and pred <= prm.risk_clear_ratio * lim


@kernel_inline
def _engage(
    prm: SequencingParams, st: SequencingState, p: int, pres: B1, load_a: float, t: float
) -> None:  # fmt: skip
    """Engage rule (R2's FET action; embodiment 5: the charge FET is on only while discharge
    current flows): close the charge FET of an admitted battery when, with it engaged, it
    would discharge at the present load, no engaged battery would take more than ``i_rev``/2
    (half the reverse cut's threshold: no close-cut-close chatter) and, if the load vanished,
    none would take more than its charge limit. Highest fast voltage first, each against
    everything engaged so far."""
    state = st.state
    chg_on = st.chg_on
    conduct_since_s = st.conduct_since_s
    ef = st.ef
    g = st.g
    i_lim = st.i_lim
    pred = st.pred
    grp = st.grp
    order = st.order
    cut = st.cut
    n = state.shape[1]
    m = 0
    for k in range(n):
        if state[p, k] == DISCHARGING and not chg_on[p, k] and not cut[k] and pres[k]:
            order[m] = k
            m += 1
    _sort_desc(order, m, ef)
    for i in range(m):
        k = order[i]
        m2 = _engaged(state, chg_on, p, grp, k)
        _share(grp, m2, ef, g, load_a, pred)
        ok = pred[k] <= 0.0
        for q in range(m2):
            j = grp[q]
            if j != k and pred[j] > 0.5 * prm.i_rev:
                ok = False
        if not ok:
            continue
        _share(grp, m2, st.ez, st.gz, 0.0, pred)
        for q in range(m2):
            j = grp[q]
            if pred[j] > prm.charge_limit_margin * i_lim[j]:
                ok = False
            if j == k and not _zl_may_engage(prm, st, p, k, pred[j], i_lim[j], t):
                ok = False
        if not ok:
            continue
        chg_on[p, k] = True
        conduct_since_s[p, k] = np.nan


@kernel_inline
def _trusted(zl: B1, grp: I64, m: int) -> bool:
    """Are the zero-load sources of every battery in ``grp[:m]`` the trusted observer's?"""
    for q in range(m):  # noqa: SIM110 (a generator in all() does not compile in numba)
        if not zl[grp[q]]:
            return False
    return True


@kernel_inline
def _r3_holds_off(
    prm: SequencingParams, st: SequencingState, p: int, k: int, t: float
) -> bool:  # fmt: skip
    """Does R3's closure keep rule 8b from opening engaged battery ``k`` now? For
    ``R3_HOLD_S`` after R3 closed it (its diode carried current: opened at once, the diode
    would carry it again and R3 would close it in the next period, chatter) - except where
    rule 8c is on and that diode current was within ``diode_hold_a``: opened on 8b's
    prediction (> ``open_ratio`` > ``hold_ratio`` x its limit), 8c then holds it on the diode,
    so nothing chatters. Why (issue #28): R3 closes a battery whose prediction is below 8c's
    ``hold_ratio``; the closed battery then takes more current and polarises, and its
    prediction passed its limit within ~1-2 s and kept rising (``bench_zero_load`` seed 230:
    0.77x at the closure, 1.74x 4.5 s later, 1.62x flowed at a loss there) while 8b waited."""
    if not t - st.forced_s[p, k] < R3_HOLD_S - EPS_S:  # also when NaN
        return False
    within: bool = prm.diode_hold_a > 0.0 and st.forced_a[p, k] <= prm.diode_hold_a
    return not within


@kernel_inline
def _r3_closed_now_within_cap(
    prm: SequencingParams, st: SequencingState, p: int, k: int, t: float
) -> bool:  # fmt: skip
    """Did R3 close battery ``k`` in this very period, its diode carrying at most
    ``diode_hold_a`` with rule 8c on? Rule 8c judged it against the batteries engaged before
    it; when R3 closes several in one period, the later ones can put an earlier one above its
    limit (``bench_zero_load`` seed 75: 1.65x at a loss at 149 s), so rule 8b looks at it in
    the same period (opened, rule 8c holds it on its diode from the next period)."""
    now: bool = st.forced_s[p, k] == t and not _r3_holds_off(prm, st, p, k, t)
    return now


@kernel_inline
def _open_worst(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, load_a: float,
    t: float, zero_load: bool,
) -> None:  # fmt: skip
    """Open, worst first, the charge FET of every engaged battery (not in ``st.skip``) that
    its engaged siblings would charge past a criterion, predicting the rest again after each
    (opening one shifts the others). The R3 hand-over, the reverse cut's cascade and rule 8b
    are this one loop; they differ only in the criterion:

    * ``zero_load`` False (hand-over, cascade): at the present pack current ``load_a`` with
      rule 0's sources, more than ``i_rev`` into it (ranked by amperes);
    * ``zero_load`` True (rule 8b): at zero load with the observer's sources (only while every
      engaged battery's are trusted), more than ``open_ratio`` x its charge limit (ranked
      relative to the limit), and not a battery R3 closed less than ``R3_HOLD_S`` ago
      unless rule 8c would hold it on its diode (:func:`_r3_holds_off`)."""
    state = st.state
    chg_on = st.chg_on
    ef = st.ef
    pred = st.pred
    grp = st.grp
    skip = st.skip
    i_lim = st.i_lim
    while True:
        m = _engaged(state, chg_on, p, grp, -1)
        if m < 2:
            break
        if zero_load:
            if not _trusted(st.zl_obs, grp, m):
                break
            _share(grp, m, st.ez, st.gz, 0.0, pred)
        else:
            _share(grp, m, ef, st.g, load_a, pred)
        j = -1
        top = -1
        for q in range(m):
            x = grp[q]
            if top < 0 or ef[x] > ef[top]:
                top = x
            if skip[x] and not (zero_load and _r3_closed_now_within_cap(prm, st, p, x, t)):
                continue
            if zero_load:
                held_r3 = _r3_holds_off(prm, st, p, x, t)
                if held_r3 or not pred[x] > prm.open_ratio * i_lim[x]:
                    continue
                if j < 0 or pred[x] / i_lim[x] > pred[j] / i_lim[j]:
                    j = x
            elif pred[x] > prm.i_rev and (j < 0 or pred[x] > pred[j]):
                j = x
        if j < 0:
            break
        chg_on[p, j] = False
        st.cut[j] = True
        st.conduct_since_s[p, j] = np.nan
        if zero_load:
            st.zl_open_s[p, j] = t
            r = emit(ev, p, src, ZERO_LOAD_OPEN, j, t)
            ev.val[r, 0] = pred[j]
            ev.val[r, 1] = i_lim[j]
            ev.val[r, 2] = j
        else:
            r = emit(ev, p, src, HANDOVER, j, t)
            ev.val[r, 0] = -pred[j]
            ev.val[r, 1] = prm.i_rev
            ev.val[r, 2] = PATH_CHG
            ev.val[r, 3] = j
            ev.val[r, 4] = top


@kernel_inline
def _open_charged(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, load_a: float,
    t: float,
) -> None:  # fmt: skip
    """The hand-over and the cascade (:func:`_open_worst` at the present load): used after the
    reverse cut (so the remaining siblings do not pour the same current into the next battery
    in the following period) and after R3 (the hand-over)."""
    _open_worst(prm, st, ev, src, p, load_a, t, False)


@kernel_inline
def _open_predicted(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, t: float
) -> None:  # fmt: skip
    """Rule 8b (issue #28; :func:`_open_worst` at zero load): open an engaged battery the
    trusted observer's prediction puts above ``open_ratio`` x its charge limit. The -dV/dI
    estimate is too uncertain to act on (the old guard that acted on it defeated
    co-discharge); a battery R3 closed is not opened (its diode would carry the current
    again). It stays admitted: the engage rule closes it again after ``ZL_DWELL_S`` once the
    prediction with it engaged is within ``risk_clear_ratio`` x the limits. Why: after a join
    the joiner polarises and its fast voltage falls below the others' while nothing changes
    the FETs; the circulating current at a load loss then grows past the limit
    (``bench_zero_load`` seed 25: 1.40x after 30 s, predicted 1.47x)."""
    _open_worst(prm, st, ev, src, p, 0.0, t, True)


@kernel_inline
def _diode_holds(
    prm: SequencingParams, st: SequencingState, p: int, k: int, cur_a: float
) -> bool:  # fmt: skip
    """Rule 8c (issue #28): must R3 leave battery ``k``'s charge FET off although its diode
    conducts? Yes while the diode carries at most ``diode_hold_a`` and the trusted zero-load
    prediction with ``k`` engaged puts ``k`` itself above ``hold_ratio`` x its charge limit
    (``risk_clear_ratio`` for a battery rule 8b opened). A sibling it would expose is no
    reason: ``k`` is then the higher one, and the hand-over and rule 8b open the sibling, as
    the spec's R3 does.

    Embodiment 5 closes the FET because discharge current means "the battery is the higher
    one, no other battery can charge it". Under a heavy load that premise fails: the bus sags
    more than the diode drop below a *lower* battery, its diode conducts, and once R3 has
    closed it the others push their EMF difference into it the moment the load goes (the
    R3-forced class of ``bench_zero_load``). On its diode it cannot be charged; the diode
    takes only what exceeds its 0.6 V drop, so its heat is bounded by the cap."""
    if not cur_a <= prm.diode_hold_a:
        return False
    grp = st.grp
    pred = st.pred
    m = _engaged(st.state, st.chg_on, p, grp, k)
    if m < 2 or not _trusted(st.zl_obs, grp, m):
        return False
    _share(grp, m, st.ez, st.gz, 0.0, pred)
    # A battery rule 8b opened is held down to risk_clear_ratio, as the engage rule asks of
    # it: on its diode it carries less, and its prediction rises again by I x R0's error the
    # period it is closed (0.83x -> 0.94x, then 8b opened it again: a 1.5 s cycle, seed 230).
    ratio = prm.hold_ratio if math.isnan(st.zl_open_s[p, k]) else prm.risk_clear_ratio
    above: bool = pred[k] > ratio * st.i_lim[k]
    return above


@kernel_inline
def _discharge_tick(
    prm: SequencingParams, st: SequencingState, ev: EventBuf, src: int, p: int, volt: F64,
    cur: F64, pres: B1, t: float, dt: float, n_inserted: int,
) -> None:  # fmt: skip
    state = st.state
    chg_on = st.chg_on
    dsg_on = st.dsg_on
    conduct_since_s = st.conduct_since_s
    at_risk = st.at_risk
    zero_load_into_a = st.zero_load_into_a
    zero_load_valid = st.zero_load_valid
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    ef = st.ef
    i_lim = st.i_lim
    pred = st.pred
    grp = st.grp
    order = st.order
    cut = st.cut
    inserted = st.inserted
    was_c = st.was_c
    was_d = st.was_d
    sw = Switches(state, chg_on, dsg_on)
    n = state.shape[1]
    i_det = prm.i_det

    held = st.held
    _held_out(st, ev, src, p, t)
    if not initialized[p]:
        _r1(prm, st, ev, src, p, volt, pres, t, R_R1_INIT)
        initialized[p] = True
        n_inserted = 0

    # Reverse cut (embodiment 5): the charge FET is on only while discharge current flows. A
    # sibling charging an engaged battery by more than i_rev, or by q_rev_as in one episode of
    # smaller reverse current, opens its charge FET in this period; the battery stays admitted
    # (the engage rule or R3 closes it again once it would discharge). Only when some other
    # battery sources current; otherwise the charge comes from outside (mode logic).
    rev_q_as = st.rev_q_as
    skip = st.skip
    for k in range(n):
        cut[k] = False
    for k in range(n):
        if not (state[p, k] == DISCHARGING and chg_on[p, k] and cur[k] < 0.0):
            rev_q_as[p, k] = 0.0
            continue
        # Fed by siblings: what they source together (five siblings at 0.2 A each, none above
        # i_det alone, kept 1 A flowing into a sixth with no cut at all: found by the nightly
        # soak). Only the part of the reverse current the siblings can supply counts (charge
        # from outside, e.g. a regenerating load, is not a sibling's). No dead band on the
        # feed: after a load drop one battery trickled 0.08-0.15 A into another for 120 s
        # while the feed test asked for more than i_det (issue #24 item 7); embodiment 5 keeps
        # the charge FET on only while discharge current flows.
        fed = 0.0
        for j in range(n):
            if j != k and pres[j] and not held[p, j] and cur[j] > 0.0:
                fed += cur[j]
        if fed <= 0.0:
            rev_q_as[p, k] = 0.0
            continue
        rev_q_as[p, k] += fmin(-cur[k], fed) * dt
        if cur[k] < -prm.i_rev or rev_q_as[p, k] > prm.q_rev_as + 1e-12:
            rev_q_as[p, k] = 0.0
            chg_on[p, k] = False
            conduct_since_s[p, k] = np.nan
            cut[k] = True
            r = emit(ev, p, src, REVERSE, k, t)
            ev.val[r, 0] = cur[k]
            ev.val[r, 1] = prm.i_rev
            ev.val[r, 2] = PATH_CHG
            ev.val[r, 3] = k
    # Cascade: with the victims open, the remaining siblings would pour the same current into
    # the next engaged battery in the coming period; open those now (not one that sources).
    any_cut = False
    for k in range(n):
        skip[k] = cur[k] > i_det
        any_cut = any_cut or cut[k]
    if any_cut:
        _open_charged(prm, st, ev, src, p, _charge_in(pres, cur, was_c), t)

    # Hot insertion (R1 re-applied to the newcomer): a battery v_th above the bus takes over
    # and the batteries v_th below it stand by in the same period, so none is charged.
    if n_inserted > 0:
        for k in range(n):
            if not inserted[k] or held[p, k]:
                continue
            v_ref = _max_discharging(state, p, volt)
            if math.isnan(v_ref) or volt[k] - v_ref < prm.v_th:
                continue
            for j in range(n):
                if state[p, j] == DISCHARGING and volt[k] - volt[j] >= prm.v_th:
                    _set(sw, ev, src, p, j, STANDBY, False, t, SET, N_FIXED_REASONS + k)
            r = _set(sw, ev, src, p, k, DISCHARGING, False, t, INSERTED_ABOVE, R_INSERTED_ABOVE)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = v_ref

    # Nobody admitted to discharge and no diode conducting: start over with R1.
    any_d = False
    for k in range(n):
        if state[p, k] == DISCHARGING:
            any_d = True
            break
    if not any_d:
        diode = False
        for k in range(n):
            if pres[k] and not held[p, k] and cur[k] > i_det:  # held: cannot conduct
                diode = True
                break
        if not diode:
            _r1(prm, st, ev, src, p, volt, pres, t, R_R1_EMPTY)

    # R2: a standby battery whose fast voltage has met the admitted ones' (within v_co below
    # the highest, or above it) joins. Fast voltages, not terminal voltages: under load the
    # discharging battery's terminal voltage sits I*R below its open-circuit voltage, so the
    # source's terminal-voltage test fires while that battery is still I*R - v_co higher and
    # co-discharge would start lopsided (issue #15; docs/parallel_discharge.md).
    e_ref = _max_discharging(state, p, ef)
    if not math.isnan(e_ref):
        m = 0
        for k in range(n):
            if state[p, k] == STANDBY and pres[k] and not held[p, k]:
                order[m] = k
                m += 1
        _sort_desc(order, m, ef)
        for i in range(m):
            k = order[i]
            if e_ref - ef[k] >= prm.v_co:
                continue
            r = _set(sw, ev, src, p, k, DISCHARGING, False, t, JOIN_R2, R_R2)
            if r >= 0:
                ev.val[r, V_DATA] = ef[k]
                ev.val[r, V_DATA + 1] = e_ref
                ev.val[r, V_DATA + 2] = ef[k] - e_ref

    # Engage (R2 switches the joiner's charge FET; also re-closes one the reverse cut opened).
    _engage(prm, st, p, pres, _charge_in(pres, cur, was_c), t)

    # R3: charge diode conducting (charge FET off, discharge FET on, discharge current).
    # Only current measured over a period in which this controller held the charge FET off
    # and the discharge FET on can have flowed through the diode. Outranks the engage rule's
    # charge-limit test: the diode must not carry the current (flagged below if at risk).
    any_r3 = False
    for k in range(n):
        skip[k] = False
    for k in range(n):
        if state[p, k] != DISCHARGING and state[p, k] != STANDBY:
            conduct_since_s[p, k] = np.nan
            st.diode_held[p, k] = False
            continue
        through = (not was_c[k]) and was_d[k] and cur[k] > i_det
        if chg_on[p, k]:
            st.diode_held[p, k] = False
            # The engage rule closed it in this period while its diode carried discharge
            # current: like one R3 closes, it sources, so the hand-over must not reopen it
            # (it did, and the diode kept conducting past t_on: #18's deadline property).
            conduct_since_s[p, k] = np.nan
            skip[k] = through
            continue
        if not through:
            st.diode_held[p, k] = False
        elif _diode_holds(prm, st, p, k, cur[k]):
            # Rule 8c: on its diode it cannot be charged; the episode's clock runs on.
            if math.isnan(conduct_since_s[p, k]):
                conduct_since_s[p, k] = t
            if not st.diode_held[p, k]:
                st.diode_held[p, k] = True
                r = emit(ev, p, src, DIODE_HOLD, k, t)
                ev.val[r, 0] = pred[k]
                ev.val[r, 1] = i_lim[k]
                ev.val[r, 2] = cur[k]
                ev.val[r, 3] = k
            continue
        if not _diode_rule(prm, state, conduct_since_s, ev, src, p, k, through, t, dt):
            continue
        st.diode_held[p, k] = False
        if state[p, k] == STANDBY:
            r = _set(sw, ev, src, p, k, DISCHARGING, True, t, JOIN_R3, R_R3)
            if r >= 0:
                ev.val[r, V_DATA] = volt[k]
                ev.val[r, V_DATA + 1] = cur[k]
        else:
            chg_on[p, k] = True
        skip[k] = True
        st.forced_s[p, k] = t
        st.forced_a[p, k] = cur[k]
        any_r3 = True
    # Hand-over: if the batteries R3 closed, now engaged, would charge an engaged sibling by
    # more than i_rev at the present load, they are the higher ones (embodiment 5: discharge
    # current means no other battery can charge them) and the sibling's charge FET opens in
    # the same period, before the current flows; it stays admitted and re-engages by the
    # engage rule. Never one R3 closed in this period: its diode current says it sources.
    if any_r3:
        _open_charged(prm, st, ev, src, p, _charge_in(pres, cur, was_c), t)

    # Rule 8b: open an engaged battery the trusted zero-load prediction puts above its limit.
    _open_predicted(prm, st, ev, src, p, t)

    # Zero-load prediction of the engaged set: an engaged battery that would take more than
    # its charge limit if the load vanished (R3 closed it across a wider gap, or the fast
    # voltages drifted apart during co-discharge) is flagged once per episode; the reverse cut
    # (or the plant's comparator) bounds it. Nothing is opened on a prediction. The flag
    # clears only below risk_clear_ratio x the limit (the prediction is an estimate).
    m = _engaged(state, chg_on, p, grp, -1)
    for k in range(n):
        pred[k] = 0.0
    _share(grp, m, st.ez, st.gz, 0.0, pred)
    for k in range(n):
        # Raised near the limit, cleared only well below it: the prediction is an estimate.
        risk = pred[k] > prm.charge_limit_margin * i_lim[k] or (
            at_risk[p, k] and pred[k] > prm.risk_clear_ratio * i_lim[k]
        )
        if risk and not at_risk[p, k]:
            r = emit(ev, p, src, RISK, k, t)
            ev.val[r, 0] = pred[k]
            ev.val[r, 1] = i_lim[k]
            ev.val[r, 2] = k
        at_risk[p, k] = risk
        zero_load_into_a[p, k] = pred[k]
        if not (state[p, k] == DISCHARGING and chg_on[p, k]):
            st.forced_s[p, k] = np.nan
        if state[p, k] != DISCHARGING or chg_on[p, k]:
            st.zl_open_s[p, k] = np.nan
    zero_load_valid[p] = True
    v_ref_v[p] = _max_discharging(state, p, ef)


# ------------------------------------------------------------------------------ charge mode


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
    zero_load_into_a = st.zero_load_into_a
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    zero_load_valid = st.zero_load_valid
    was_c = st.was_c
    was_d = st.was_d
    sw = Switches(state, chg_on, dsg_on)
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
    zero_load_into_a = st.zero_load_into_a
    mode = st.mode
    initialized = st.initialized
    v_ref_v = st.v_ref_v
    zero_load_valid = st.zero_load_valid
    sw = Switches(state, chg_on, dsg_on)
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
    zero_load_valid[p] = False
    for k in range(n):
        zero_load_into_a[p, k] = np.nan
        at_risk[p, k] = False


@kernel_inline
def _update_resistance(
    prm: SequencingParams, r_ohm: F64, last_v_v: F64, last_i_a: F64, ef: F64, g: F64, p: int,
    volt: F64, cur: F64, pres: B1,
) -> None:  # fmt: skip
    """Resistance estimate per battery: -dV/dI over the last current step >= ``i_step``.

    Voltages are battery-side, so the quotient is the battery's ohmic resistance whatever
    its FETs or diodes did; over one control period OCV and polarisation hardly move. Then
    the per-step values every rule shares: the fast voltage V + I*R (the voltage a battery
    shows the instant its current drops to zero: OCV minus the polarisation) and 1 / R.
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
        r_est = r_batt if math.isnan(r) else r
        ef[k] = volt[k] + cur[k] * r_est
        g[k] = 1.0 / r_est


@kernel_inline
def _zero_load_sources(
    prm: SequencingParams, st: SequencingState, status: F64, p: int, volt: F64, cur: F64,
    pres: B1,
) -> None:  # fmt: skip
    """Fast voltage and conductance of each battery for the zero-load prediction (issue #28).

    The prediction asks what flows the instant the load vanishes: each battery is then its
    EMF less its polarisation, ``EMF - v_rc`` (what it shows before the RC branch has had
    time to relax), behind its ohmic resistance R0. By the observer's own model the terminal
    voltage is ``EMF - R0 * I - v_rc``, so that source voltage is ``V + I * R0`` with the
    observer's R0, read here from the measured V (the observer tracks one cell x the series
    count, and runs after this method: its EMF and v_rc are one period old and miss the
    other cells' spread). The -dV/dI estimate (``ef``, ``g``), taken over a whole period,
    takes in part of the polarisation: a resistance too high, a source voltage too high for
    a battery under load, and a circulating current predicted low (1.34x the charge limit
    flowed where 0.9x was predicted). Where the observer is off, restarting or diverged
    (its trust flag not 1), or its R0 is not plausible, the -dV/dI estimate stays."""
    ez = st.ez
    gz = st.gz
    ef = st.ef
    g = st.g
    s_r0 = prm.reads_slot[0]
    s_ok = prm.reads_slot[1]
    use = prm.zero_load_observer and s_r0 >= 0 and s_ok >= 0
    r_max = 20.0 * prm.r_batt_ohm
    zl = st.zl_obs
    for k in range(pres.shape[0]):
        ez[k] = ef[k]
        gz[k] = g[k]
        zl[k] = False
        if not use or not pres[k]:
            continue
        r0 = status[p, k, s_r0]
        if status[p, k, s_ok] == 1.0 and 0.0 < r0 <= r_max:
            ez[k] = volt[k] + cur[k] * r0
            gz[k] = 1.0 / r0
            zl[k] = True


@kernel_inline
def _update_mode(
    prm: SequencingParams, mode: I64, mode_evidence_since_s: F64, initialized: B1,
    conduct_since_s: F64, ev: EventBuf, src: int, p: int, cur: F64, pres: B1, docked: bool,
    t: float, can_charge: B1,
) -> None:  # fmt: skip
    """Docking switches to charge mode at once; charging current alone must persist t_mode.
    Charge mode ends t_mode after the dock is gone and the pack is no longer charged.
    Charging current counts only where a charge path conducts (:func:`_charge_in`)."""
    pack_i = _charge_in(pres, cur, can_charge)
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
    mode = st.mode
    initialized = st.initialized
    last_t_s = st.last_t_s
    mode_evidence_since_s = st.mode_evidence_since_s
    sw = Switches(state, chg_on, dsg_on)
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

    _update_resistance(prm, st.r_ohm, st.last_v_v, st.last_i_a, st.ef, st.g, p, volt, cur, pres)
    _zero_load_sources(prm, st, status, p, volt, cur, pres)
    cap = tp.capacity_ah[p]
    i_lim = st.i_lim
    for k in range(n):
        c = cap[k] if k < cap.shape[0] else np.nan
        i_lim[k] = prm.charge_limit_c * (c if c > 0.0 else prm.default_capacity_ah)
    docked = bool(m.docked[p])
    _update_mode(
        prm, mode, mode_evidence_since_s, initialized, conduct_since_s, ev, src, p, cur, pres,
        docked, t, bat.sw_chg[p],
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


@kernel_inline
def close_out_pack(st: SequencingState, tp: PackArrays, p: int, cmd: CmdArrays) -> None:
    """Out of charge mode, a battery whose discharge path any layer opened in this step gets
    its charge FET opened in the same step.

    Embodiments 5 and 7 (the charge FET is on only while the battery discharges), made exact at
    the command level: with its discharge FET off the battery cannot discharge, and a charge FET
    left on would let a sibling charge it through the discharge FET's body diode (a protection
    trip of the lower battery while a higher one takes over pushed 46 A into it for one period
    before the reverse cut). Runs after every layer and the supervisor (``Method.after``).

    Also notes, for the next step, which batteries another layer held open against
    sequencing's command (``st.held``, :func:`_held_out`)."""
    held = st.held
    charge = st.mode[p] == MODE_CHARGE
    for k in range(st.state.shape[1]):
        relay = tp.relay[k]
        # MOSFET pairs only: a relay in STANDBY is open (no diode), so standing a held relay
        # battery by would withhold the reserve plausibility brings in make-before-break.
        held[p, k] = cmd.dsg_on[p, k] == 0 and st.dsg_on[p, k] and not relay and not charge
        if cmd.dsg_on[p, k] == 0 and not relay and not charge:
            put_chg(cmd, p, k, False)


@kernel
def close_out_packs(
    prm: SequencingParams, st: SequencingState, tp: PackArrays, m: MeasArrays, cmd: CmdArrays
) -> None:  # fmt: skip
    for p in range(m.t_s.shape[0]):
        close_out_pack(st, tp, p, cmd)


def max_events(n: int) -> int:
    """Upper bound of the events one pack can emit in one step (N batteries)."""
    return n * n + 17 * n + 8
