"""The compiled sequencing method against the scalar oracle it replaced (see ``common.py``).

The oracle (``tests/oracles/sequencing.py``) is the reference. Every test steps one oracle per
pack next to the compiled rules and, after every step, compares commands, events (time, kind,
battery, message, data) and status of each pack, and the whole controller state (floats bit
for bit, None as NaN): random measurement sequences with invalid inputs (NaN, inf, negative
voltages, missing batteries), presence and docking flips, time going backwards, odd periods and
exact threshold ties, under six configs including ``isolate_source=False``; fixed seeds that
fire every event kind and every rule behind one; the generic sequences of ``common.py``; and
closed loops on the real plant (the example scenarios, one pack perturbed).

The compiled side runs P packs in one ``step_packs`` call (each with its own time axis) with
its status channels at an offset and its events under a non-zero source id, as the core runs
it, and as the one-pack :class:`SequencingController`.
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config.sequencing import SequencingConfig
from packpilot.contract.arrays import (
    clear_commands,
    cmd_arrays,
    commands,
    event_buf,
    meas_arrays,
    pack_arrays,
    put_measurements,
)
from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.events import Source, render
from packpilot.contract.topology import PackInfo
from packpilot.control.method import status_values
from packpilot.control.sequencing import METHOD, SequencingController, battery_measurement
from packpilot.control.sequencing.controller import MODES, STATES, fault_reason
from packpilot.control.sequencing.rules import SequencingState
from tests.equivalence.common import assert_same_output, sequence
from tests.oracles.sequencing import SequencingController as Oracle
from tests.oracles.sequencing import SequencingState as OracleState

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

CONFIGS = {
    "default": SequencingConfig(),
    # Short timers so debounces, rest, mode switches and isolation holds expire within a case.
    "fast_no_iso": SequencingConfig(
        isolate_source=False,
        t_on=0.15,
        t_debounce=0.05,
        t_mode=0.3,
        t_rest=0.1,
        t_iso_hold=0.2,
    ),
    "fast_iso": SequencingConfig(
        t_on=0.15,
        t_debounce=0.05,
        t_mode=0.3,
        t_rest=0.1,
        t_iso_hold=0.2,
        r_loop_ohm=0.2,
    ),
    # Charging current must persist 3 s before charge mode: discharge rules see negative loads.
    "slow_mode": SequencingConfig(t_mode=3.0, t_iso_hold=0.1, t_rest=0.05, i_guard=0.6),
    # Cut-off 20.7 V (6 cells) amid the voltage levels: forced releases and reserve checks.
    "high_cutoff": SequencingConfig(
        v_cutoff_cell_v=3.45, t_on=0.15, t_debounce=0.05, t_mode=0.5, t_iso_hold=0.15
    ),
    # Thresholds that are binary fractions, with samples on a 1/8 V, 1/4 A grid: differences
    # land exactly on v_th, v_co, v_merge (0.125 V), i_det... so every < / <= is exercised.
    "dyadic": SequencingConfig(
        v_th=0.5,
        v_co=0.25,
        i_det=0.5,
        i_rev=0.5,
        i_merge=0.5,
        r_loop_ohm=0.25,
        i_guard=0.75,
        r_batt_ohm=0.015625,
        i_step=1.0,
        v_diode=0.5,
        v_cutoff_cell_v=3.375,
        v_reserve=0.25,
        v_iso_margin=0.125,
        t_on=0.125,
        t_debounce=0.0625,
        t_mode=0.5,
        t_rest=0.125,
        t_iso_hold=0.25,
    ),
}
EPS = 1e-9
"""The oracle's tolerance on accumulated times (``_EPS_S``)."""
# Timers one tolerance above a binary fraction, on a time grid of 1/16 s: ``elapsed + EPS >=
# timer`` ties exactly (R3/R4 debounce, mode debounce, rest, isolation hold).
CONFIGS["timer_ties"] = CONFIGS["dyadic"].model_copy(
    update={
        "t_debounce": 0.0625 + EPS,
        "t_on": 0.25,
        "t_mode": 0.5 + EPS,
        "t_rest": 0.125 + EPS,
        "t_iso_hold": 0.25 + EPS,
    }
)
COVERAGE_CONFIGS = ("default", "fast_iso", "fast_no_iso", "high_cutoff", "slow_mode")


def _info(n: int, cells: int = 6) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(1,) * n,
        cells_per_group=(cells,) * n,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
    )


# ------------------------------------------------------------------------------ the batch
S0 = 3
"""Status channels of the method start here (as behind other parts in a core)."""
SRC = 1


class Batch:
    """P packs of the compiled method in one ``step_packs`` call, rendered as scalar outputs."""

    def __init__(self, cfg: SequencingConfig, info: PackInfo, n_packs: int) -> None:
        infos = [info] * n_packs
        n = info.n_batteries
        self.info = info
        self.n_packs = n_packs
        self.prm, self.st = METHOD.build(cfg, infos)
        self.tp = pack_arrays(infos)
        self.m = meas_arrays(n_packs, n, 1)
        self.cmd = cmd_arrays(n_packs, n, 1)
        self.ev = event_buf(n_packs * METHOD.max_events(info))
        self.status = np.full((n_packs, n, S0 + len(METHOD.status) + 2), -7.0)
        self.sources = [Source((), {}), Source(METHOD.reasons, METHOD.labels(self.prm))]

    def step(self, meas: Sequence[Measurements], dt_s: float) -> list[ControlOutput]:
        for p, mp in enumerate(meas):
            put_measurements(self.m, p, mp)
        clear_commands(self.cmd)
        self.ev.n[0] = 0
        METHOD.step_packs(
            self.prm, self.st, self.tp, self.m, float(dt_s), self.cmd, self.ev, SRC,
            self.status, S0,
        )  # fmt: skip
        assert int(self.ev.dropped[0]) == 0
        # Nothing outside the method's own status columns was written.
        assert (self.status[:, :, :S0] == -7.0).all()
        assert (self.status[:, :, S0 + len(METHOD.status) :] == -7.0).all()
        events = render(self.ev, self.sources, self.n_packs)
        labels = self.sources[SRC].labels
        return [
            ControlOutput(
                commands=commands(self.cmd, p, self.info.groups_per_battery),
                events=tuple(events[p]),
                status=status_values(self.status, p, S0, METHOD.status, labels),
            )
            for p in range(self.n_packs)
        ]


# ------------------------------------------------------------------------------ comparison
def _same_float(x: float, ref: float | None) -> bool:
    """Bit-identical (sign of zero included), NaN equal to NaN, None stored as NaN."""
    if ref is None or math.isnan(ref):
        return math.isnan(x)
    return x == ref and math.copysign(1.0, x) == math.copysign(1.0, ref)


def assert_state_equal(s: SequencingState, p: int, n: int, ref: OracleState, where: str) -> None:
    """The whole state of pack ``p`` equals the oracle's."""
    for k, b in enumerate(ref.batteries):
        w = f"{where} battery {k}"
        assert STATES[s.state[p, k]].value == b.state.value, w
        assert bool(s.chg_on[p, k]) is b.chg_on, w
        assert bool(s.dsg_on[p, k]) is b.dsg_on, w
        assert bool(s.guard_opened[p, k]) is b.guard_opened, w
        assert bool(s.at_risk[p, k]) is b.at_risk, w
        for name in (
            "conduct_since_s",
            "r_ohm",
            "last_v_v",
            "last_i_a",
            "hold_load_a",
            "isolated_since_s",
            "released_at_s",
        ):
            got = float(getattr(s, name)[p, k])
            assert _same_float(got, getattr(b, name)), f"{w} {name}: {got} != {getattr(b, name)}"
    assert MODES[s.mode[p]].value == ref.mode.value, where
    assert bool(s.initialized[p]) is ref.initialized, where
    for name in ("last_t_s", "mode_evidence_since_s", "v_ref_v", "rest_since_s"):
        got = float(getattr(s, name)[p])
        assert _same_float(got, getattr(ref, name)), f"{where} {name}: {got}"
    reason = "" if MODES[s.mode[p]].value != "fault" else fault_reason(list(s.fault[p]), n)
    assert reason == ref.fault_reason, where
    zl = ref.zero_load_into_a
    assert bool(s.zero_load_valid[p]) is (zl is not None), where
    for k in range(n):
        r = None if zl is None else zl[k]
        assert _same_float(float(s.zero_load_into_a[p, k]), r), f"{where} zl {k}"


# ------------------------------------------------------------------------------ random cases
@dataclass(frozen=True)
class Case:
    """Inputs of one random run: a time axis per pack, per-pack measurements."""

    n: int
    config: str
    t_s: np.ndarray  # (T, P)
    dt_s: np.ndarray  # (T,)
    volt: np.ndarray  # (T, P, N)
    cur: np.ndarray  # (T, P, N)
    present: np.ndarray  # (T, P, N)
    docked: np.ndarray  # (T, P)


LEVELS = np.array([19.0, 20.0, 20.3, 20.6, 21.0, 21.02, 21.3, 21.6, 22.0, 22.5, 23.0, 24.0])
OFFSETS = np.array([0.0, 0.0, 0.0, 0.005, 0.01, 0.03, 0.06, 0.2, 0.35, 0.6, 1.0])
CURRENTS = np.array([0.0, 0.0, 0.0, 0.2, -0.2, 0.7, 1.5, 3.0, 8.0, 15.0, 25.0, -0.8, -3.0, -10.0])


def gen_case(rng: np.random.Generator, n: int, config: str, n_packs: int, steps: int) -> Case:
    """A random sequence per pack: voltages around a few levels or clustered (so spreads
    straddle v_th, v_co, v_merge and the guard limits), currents of both signs with idle
    stretches, presence and docking flips, rare NaN/inf/negative inputs, and a time axis with
    repeats, gaps and backward steps (pack p's is shifted by 0.25 * p s: packs keep time
    independently)."""
    dt0 = float(rng.choice([0.02, 0.05, 0.1, 0.2]))
    t = np.empty(steps)
    dt = np.full(steps, dt0)
    now = float(rng.choice([0.0, 100.0]))
    for i in range(steps):
        u = rng.random()
        if u < 0.03:
            now -= dt0  # time goes backwards
        elif u < 0.06:
            pass  # same time again
        elif u < 0.08:
            now += 5.0 * dt0  # a gap
        else:
            now += dt0
        t[i] = now
        w = rng.random()
        if w < 0.01:
            t[i] = float(rng.choice([math.nan, math.inf]))
        elif w < 0.02:
            dt[i] = float(rng.choice([math.nan, -0.1, 0.0]))
        elif w < 0.06:
            dt[i] = 0.5 * dt0
    volt = np.empty((steps, n_packs, n))
    cur = np.empty((steps, n_packs, n))
    pres = np.empty((steps, n_packs, n), bool)
    dock = np.empty((steps, n_packs), bool)
    for p in range(n_packs):
        if rng.random() < 0.5:  # clustered: one level plus small or large offsets
            base = rng.choice(LEVELS) + rng.choice(OFFSETS, size=n)
        else:
            base = rng.choice(LEVELS, size=n) + rng.normal(0.0, 0.05, size=n)
        present = rng.random(n) < 0.85
        present[0] = True
        i_now = rng.choice(CURRENTS, size=n)
        docked = rng.random() < 0.1
        hold = int(rng.integers(1, 12))  # how long currents persist (R3/R4 debounce)
        p_nan = float(rng.choice([0.0, 0.005, 0.02]))
        noise = float(rng.choice([0.0005, 0.003, 0.01]))
        r_true = rng.choice([0.01, 0.02, 0.02, 0.04], size=n)
        # ADC resolution (V, A): quantised samples make exact ties (sort order, first maximum).
        q_v, q_i = [(0.0, 0.0), (0.01, 0.1), (0.05, 0.5)][int(rng.integers(3))]
        twin = int(rng.integers(n - 1)) if n >= 2 and rng.random() < 0.3 else -1
        if config in ("dyadic", "timer_ties"):
            q_v, q_i = 0.125, 0.25
        for i in range(steps):
            if rng.random() < 0.04:
                present[rng.integers(n)] ^= True
            if rng.random() < 0.03:
                docked = not docked
            if rng.random() < 0.05:
                base[rng.integers(n)] = rng.choice(LEVELS)
            if rng.random() < 0.02:  # several batteries step up together (R2 joins in turn)
                base += (rng.random(n) < 0.6) * rng.uniform(0.3, 1.2, size=n)
            base -= 0.0002 * np.maximum(i_now, 0.0) * rng.random(n)
            if i % hold == 0:
                i_now = rng.choice(CURRENTS, size=n) * rng.choice([1.0, 1.0, 0.3])
                u = rng.random()
                if u < 0.3:  # co-discharge: currents share the sign
                    i_now = np.abs(i_now)
                elif u < 0.45:  # rest
                    i_now = np.zeros(n)
            v = base - r_true * i_now + rng.normal(0.0, noise, size=n)
            c = i_now + rng.normal(0.0, 0.05, size=n)
            if q_v:
                v = np.round(v / q_v) * q_v
                c = np.round(c / q_i) * q_i
            for k in range(n):
                if rng.random() < p_nan:
                    u = rng.random()
                    if u < 0.75:
                        v[k] = float(rng.choice([math.nan, math.inf, -1.0]))
                    if u > 0.25:  # both bad: the voltage is reported (checked first)
                        c[k] = float(rng.choice([math.nan, -math.inf]))
                if not present[k] and rng.random() < 0.5:
                    v[k] = math.nan  # an absent battery's reading is not validated
                    c[k] = math.nan
            if twin >= 0:  # battery n-1 is an exact copy of battery twin: ties everywhere
                v[n - 1], c[n - 1], present[n - 1] = v[twin], c[twin], present[twin]
            volt[i, p], cur[i, p], pres[i, p], dock[i, p] = v, c, present, docked
    t_p = t[:, None] + 0.25 * np.arange(n_packs)[None, :]
    return Case(n, config, t_p, dt, volt, cur, pres, dock)


def _meas(case: Case, i: int, p: int) -> Measurements:
    bats = tuple(
        battery_measurement(
            float(case.volt[i, p, k]), float(case.cur[i, p, k]), bool(case.present[i, p, k])
        )
        for k in range(case.n)
    )
    return Measurements(
        t_s=float(case.t_s[i, p]),
        batteries=bats,
        bus_v=math.nan,
        docked=bool(case.docked[i, p]),
    )


FAULT_CLASSES = (
    "expected",
    "t_s is not finite",
    "dt_s must be a finite number >= 0",
    "time went backwards",
    "voltage",
    "current",
)


def _fault_class(reason: str) -> str:
    for c in FAULT_CLASSES:
        if reason.startswith(c) or (reason.startswith("battery") and f": {c} " in reason):
            return c
    raise AssertionError(reason)


def _reason(kind: str, data: Mapping[str, Any]) -> str:
    """Which rule produced an oracle event (its ``reason``, diode path or fault class)."""
    if kind in ("DiodeBypassed", "ReverseCurrent"):
        return str(data.get("path", "chg"))
    if kind in ("Fault", "FaultCleared"):
        return _fault_class(str(data["reason"]))
    reason = str(data.get("reason", ""))
    if reason.startswith("R1 battery"):
        return "R1 battery k inserted"
    if kind in ("SourceIsolated", "CrossCurrentGuard"):
        return ""
    return reason


def run_case(case: Case) -> Counter[tuple[str, str]]:
    """Step the compiled batch and one oracle per pack; compare after every step. Returns how
    often each (kind, rule) occurred in the oracle's events."""
    cfg = CONFIGS[case.config]
    info = _info(case.n)
    n_packs = case.volt.shape[1]
    batch = Batch(cfg, info, n_packs)
    oracles = [Oracle(cfg, info) for _ in range(n_packs)]
    seen: Counter[tuple[str, str]] = Counter()
    for i in range(len(case.dt_s)):
        dt = float(case.dt_s[i])
        meas = [_meas(case, i, p) for p in range(n_packs)]
        outs = batch.step(meas, dt)
        for p, ctrl in enumerate(oracles):
            ref = ctrl.step(meas[p], dt)
            where = f"step {i} pack {p}"
            assert_same_output(outs[p], ref, case.n, where)
            assert_state_equal(batch.st, p, case.n, ctrl.state, where)
            seen.update((e.kind, _reason(e.kind, e.data)) for e in ref.events)
    return seen


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 4),
    config=st.sampled_from(sorted(CONFIGS)),
    n_packs=st.integers(1, 4),
    steps=st.integers(30, 120),
)
def test_random_sequences_match_the_oracle(
    seed: int, n: int, config: str, n_packs: int, steps: int
) -> None:
    run_case(gen_case(np.random.default_rng(seed), n, config, n_packs, steps))


# Every rule that emits an event, as (kind, reason / diode path / fault class).
RULES = {
    *(("BatteryJoined", r) for r in ("R2", "R3", "rest merge", "load merge")),
    *(("BatteryJoined", r) for r in ("isolation merge", "isolation take-over")),
    *(("StateChanged", r) for r in ("R1 init", "R1 no battery discharging", "fail-safe")),
    *(("StateChanged", r) for r in ("R1 battery k inserted", "R1 inserted above bus")),
    *(("StateChanged", r) for r in ("removed", "inserted", "inserted while charging")),
    *(("StateChanged", r) for r in ("charge mode", "isolation take-over")),
    *(("StateChanged", r) for r in ("isolation ended", "isolation forced")),
    ("DiodeBypassed", "chg"),
    ("DiodeBypassed", "dsg"),
    ("ReverseCurrent", "chg"),
    ("ReverseCurrent", "dsg"),
    ("CrossCurrentGuard", ""),
    ("CrossCurrentRisk", ""),
    ("SourceIsolated", ""),
    ("ModeChanged", ""),
    *(("Fault", r) for r in FAULT_CLASSES[1:]),
    *(("FaultCleared", r) for r in FAULT_CLASSES[1:]),
}
"""The battery-count fault cannot occur in these cases (every battery is in every sample);
``test_generic_sequences_match_the_oracle`` and ``test_directed_missing_battery`` cover it."""


def test_random_sequences_fire_every_event_kind_and_rule() -> None:
    """The random generator is not hollow: over a fixed set of cases every event kind, and every
    rule behind one, occurs (and the compiled rules match the oracle on all of them)."""
    seen: Counter[tuple[str, str]] = Counter()
    # Seeds 0-39 fire every rule; with seeds 91 (bus estimate from an admitted battery, no
    # engaged one) and 99 (a take-over stopped by the spread of two isolated batteries) they
    # executed every reachable line of the scalar controller (line tracer, when the batch twin
    # these tests come from was written).
    for seed in [*range(40), 91, 99]:
        rng = np.random.default_rng(seed)
        n = 1 + (seed // len(COVERAGE_CONFIGS)) % 4
        config = COVERAGE_CONFIGS[seed % len(COVERAGE_CONFIGS)]
        seen += run_case(gen_case(rng, n, config, 3, 100))
    kinds = {r.kind for r in METHOD.reasons}
    assert {k for k, _ in seen} == kinds, f"never fired: {kinds - {k for k, _ in seen}}"
    assert set(seen) == RULES, (
        f"rules never fired: {RULES - set(seen)}; unknown: {set(seen) - RULES}"
    )


def on_time_grid(case: Case, dt: float = 0.0625) -> Case:
    """``case`` sampled every ``dt`` s exactly (no jumps, no invalid times)."""
    steps, n_packs = case.t_s.shape
    t = dt * np.arange(steps)[:, None] + 0.25 * np.arange(n_packs)[None, :]
    return replace(case, t_s=t, dt_s=np.full(steps, dt))


def test_timer_ties_on_a_binary_time_grid_match() -> None:
    """Exact ties of the timers (``elapsed + EPS >= timer``): timers one EPS above a multiple
    of the 1/16 s sample period."""
    for seed in range(30):
        case = gen_case(np.random.default_rng(seed), 2 + seed % 3, "timer_ties", 3, 100)
        run_case(on_time_grid(case))


def test_threshold_ties_on_a_binary_grid_match() -> None:
    """Exact ties at the thresholds (``<`` vs ``<=``): the dyadic config on its 1/8 V grid. Among
    these seeds, a line tracer found R2 candidates exactly v_co above the bus (seeds 5, 17, 19,
    ...) and a rest merge exactly v_merge wide (seed 8) when this was written."""
    for seed in range(30):
        run_case(gen_case(np.random.default_rng(seed), 2 + seed % 3, "dyadic", 3, 100))


# ------------------------------------------------------------------------------ generic inputs
@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 4),
    config=st.sampled_from(sorted(CONFIGS)),
)
def test_generic_sequences_match_the_oracle(data: Any, n: int, config: str) -> None:
    """``common.sequence``: full measurements (aux, charger, group voltages), one battery
    redrawn per step, batteries missing from a sample, weird dt, time jumping back; voltages
    of 6 cells so the rules have something to sequence. The one-pack face."""
    cfg = CONFIGS[config]
    info = _info(n)
    new = SequencingController(cfg, info)
    old = Oracle(cfg, info)
    seq = data.draw(sequence(n, 6, v_cell=(3.3, 4.2), current=(-12.0, 25.0)))
    for k, (raw, dt) in enumerate(seq):
        # ``sum(())`` makes an int 0 V reading, which the oracle would echo as an int in its
        # event data; readings are floats in the contract (the arrays store them as floats).
        bats = tuple(replace(b, voltage_v=float(b.voltage_v)) for b in raw.batteries)
        meas = replace(raw, batteries=bats)
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")
        assert_state_equal(new.st, 0, n, old.state, f"step {k}")


def test_directed_missing_battery() -> None:
    """A sample without every battery is a fault (and its reason names the count)."""
    cfg = SequencingConfig()
    info = _info(3)
    new = SequencingController(cfg, info)
    old = Oracle(cfg, info)
    full = (battery_measurement(24.0, 1.0), battery_measurement(23.0, 0.0))
    seq = [
        (Measurements(0.0, (*full, battery_measurement(22.0, 0.0)), math.nan), 0.1),
        (Measurements(0.1, full, math.nan), 0.1),
        (Measurements(0.2, full[:1], math.nan), 0.1),
        (Measurements(0.3, (*full, battery_measurement(22.0, 0.0)), math.nan), 0.1),
    ]
    reasons = []
    for k, (meas, dt) in enumerate(seq):
        out = new.step(meas, dt)
        assert_same_output(out, old.step(meas, dt), 3, f"step {k}")
        reasons += [e.data["reason"] for e in out.events if e.kind.startswith("Fault")]
    assert reasons == ["expected 3 batteries in the measurements, got 2"] * 2


def test_directed_fault_time_after_a_negative_zero_time() -> None:
    """A non-finite time faults at the last valid time, ``last_t_s or 0.0``: +0.0 after -0.0
    (the sign of zero is compared here, which ``same`` does not)."""
    info = _info(2)
    new = SequencingController(SequencingConfig(), info)
    old = Oracle(SequencingConfig(), info)
    bats = (battery_measurement(24.0, 1.0), battery_measurement(23.0, 0.0))
    for t in (-0.0, math.nan):
        meas = Measurements(t, bats, math.nan)
        a, b = new.step(meas, 0.1), old.step(meas, 0.1)
        assert_same_output(a, b, 2, f"t={t}")
        assert [math.copysign(1.0, e.t_s) for e in a.events] == [
            math.copysign(1.0, e.t_s) for e in b.events
        ]
    assert a.events[0].kind == "Fault" and math.copysign(1.0, a.events[0].t_s) == 1.0


def test_directed_take_over_refused_below_cut_off_then_forced_release() -> None:
    """A path the random sequences rarely reach: an isolated battery, alone after its sibling
    is removed, would take over below cut-off + reserve, so the take-over is refused and the
    release is forced."""
    cfg = CONFIGS["high_cutoff"]  # cut-off + reserve 21.0 V, + margin 21.2 V
    info = _info(2)
    seq = [  # t, volts, currents, present
        (0.0, (22.0, 22.3), (0.0, 0.0), (True, True)),  # R1: both admitted, FETs open
        (0.1, (22.0, 22.3), (0.0, 10.0), (True, True)),  # battery 1's diode conducts
        (0.2, (22.0, 22.3), (0.0, 10.0), (True, True)),  # R3 closes battery 1
        (0.3, (21.9, 21.9), (5.0, 10.0), (True, True)),  # battery 0's diode conducts
        (0.4, (21.9, 21.9), (5.0, 10.0), (True, True)),  # R3 closes it -> battery 1 isolated
        (0.5, (21.9, 22.0), (15.0, 0.0), (True, True)),  # held: not yet t_iso_hold
        (0.6, (math.nan, 20.9), (math.nan, 0.0), (False, True)),  # alone, below 21.0 V
    ]
    new = SequencingController(cfg, info)
    old = Oracle(cfg, info)
    log = []
    for t, v, c, pr in seq:
        bats = tuple(battery_measurement(v[k], c[k], pr[k]) for k in range(2))
        meas = Measurements(t_s=t, batteries=bats, bus_v=math.nan)
        out = new.step(meas, 0.1)
        assert_same_output(out, old.step(meas, 0.1), 2, f"t={t}")
        assert_state_equal(new.st, 0, 2, old.state, f"t={t}")
        log.append([(e.kind, e.battery, e.data.get("reason")) for e in out.events])
    assert ("SourceIsolated", 1, "would charge battery 0, which R3 closed at this load") in log[4]
    assert log[6] == [
        ("StateChanged", 0, "removed"),
        ("StateChanged", 1, "isolation forced"),
        ("StateChanged", 1, "R1 no battery discharging"),
    ]


def test_a_pack_of_p_equals_p_packs_of_one() -> None:
    """Packs are independent: the batch's pack p is the one-pack controller on its inputs."""
    case = gen_case(np.random.default_rng(7), 3, "fast_iso", 5, 120)
    cfg = CONFIGS[case.config]
    info = _info(case.n)
    batch = Batch(cfg, info, 5)
    singles = [SequencingController(cfg, info) for _ in range(5)]
    for i in range(len(case.dt_s)):
        meas = [_meas(case, i, p) for p in range(5)]
        outs = batch.step(meas, float(case.dt_s[i]))
        for p, one in enumerate(singles):
            assert_same_output(outs[p], one.step(meas[p], float(case.dt_s[i])), 3, f"{i} {p}")
            for name, a in batch.st._asdict().items():
                if a.shape[0] == 5:  # not the (B,) scratch
                    np.testing.assert_array_equal(a[p], getattr(one.st, name)[0], err_msg=name)


# ------------------------------------------------------------------------------ closed loop
class RecordingOracle:
    """The oracle in a closed-loop run (built by the runner as the scenario's sequencing
    part), recording what it saw and did."""

    made: ClassVar[list[RecordingOracle]] = []

    def __init__(self, config: SequencingConfig, info: PackInfo) -> None:
        self.inner = Oracle(config, info)
        self.config = config
        self.info = info
        self.log: list[tuple[Measurements, float, ControlOutput, OracleState]] = []
        RecordingOracle.made.append(self)

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        out = self.inner.step(meas, dt_s)
        self.log.append((meas, dt_s, out, copy.deepcopy(self.inner.state)))
        return out


@pytest.mark.parametrize(
    ("name", "duration_s", "dt_s"),
    [
        ("sequencing_dual_hover", 2400.0, 0.5),
        ("sequencing_four_spread", 1210.0, 0.5),  # isolation, take-over and isolation merge
        ("sequencing_hot_insert", 2400.0, 0.5),
        ("sequencing_hot_insert", 320.0, 0.1),  # the file's own period, through the insertion
        ("uav_mission", 1500.0, None),  # supervised, with the other methods; docks at 1300 s
    ],
)
def test_closed_loop_on_the_plant_matches(
    name: str, duration_s: float, dt_s: float | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The oracle is the scenario's sequencing part on the real plant; the compiled rules
    (packs 0-2) see its measurements and must do what it did; pack 3 gets perturbed voltages,
    a removal and an invalid sample, next to its own oracle."""
    from packpilot.config import load_config
    from packpilot.control.registry import REGISTRY
    from packpilot.sim import runner as runner_mod

    oracle = replace(REGISTRY["sequencing"], target=f"{__name__}:RecordingOracle")
    monkeypatch.setitem(REGISTRY, "sequencing", oracle)
    RecordingOracle.made.clear()
    cfg = load_config(EXAMPLES / f"{name}.toml")
    sim: dict[str, Any] = {"progress": False, "duration_s": duration_s}
    if dt_s is not None:
        sim["dt_s"] = dt_s
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update=sim)})
    runner = runner_mod.Runner(cfg)
    runner.run()
    (rec,) = RecordingOracle.made
    info = rec.info
    n = info.n_batteries
    batch = Batch(rec.config, info, 4)
    other = Oracle(rec.config, info)
    rng = np.random.default_rng(1)
    kinds: set[str] = set()
    diverged = False
    for i, (meas, dt, out, state) in enumerate(rec.log):
        bats3 = []
        for k, b in enumerate(meas.batteries):
            v = b.voltage_v + rng.normal(0.0, 0.05)
            present = b.present and not (100 <= i < 140 and k == n - 1)
            if i == 200 and k == 0:
                v = math.nan
            bats3.append(battery_measurement(float(v), b.current_a, present))
        meas3 = Measurements(
            t_s=meas.t_s, batteries=tuple(bats3), bus_v=math.nan, docked=meas.docked
        )
        outs = batch.step([meas, meas, meas, meas3], dt)
        for p in range(3):
            assert_same_output(outs[p], out, n, f"{name} step {i} pack {p}")
            assert_state_equal(batch.st, p, n, state, f"{name} step {i} pack {p}")
        out3 = other.step(meas3, dt)
        assert_same_output(outs[3], out3, n, f"{name} step {i} pack 3")
        assert_state_equal(batch.st, 3, n, other.state, f"{name} step {i} pack 3")
        kinds.update(e.kind for e in out.events)
        diverged = diverged or [e.kind for e in outs[3].events] != [e.kind for e in out.events]
    assert len(rec.log) > 100
    assert len(kinds) >= 2, kinds
    assert diverged  # pack 3 really ran its own course next to packs 0-2
    if name == "uav_mission":
        assert "ModeChanged" in kinds
