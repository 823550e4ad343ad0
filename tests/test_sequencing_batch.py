"""BatchSequencing (numba, P packs in lockstep) against the scalar SequencingController.

The scalar controller is the reference. Every test steps one scalar controller per pack next to
the batch and, after every step, compares the commands, the (kind, battery) event lists and the
whole controller state (floats bit for bit, None as NaN): closed loop on the real plant for the
example scenarios, random measurement sequences (Hypothesis) with invalid inputs, presence and
docking flips, time going backwards, and a check that the random sequences fire every event
kind (otherwise the equivalence would prove little).
"""

from __future__ import annotations

import copy
import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.control.sequencing import (
    SequencingConfig,
    SequencingController,
    SequencingState,
    battery_measurement,
)
from packpilot.control.sequencing_batch import (
    FAULT_REASONS,
    KINDS,
    MODE_CODES,
    STATE_CODES,
    BatchSequencing,
    BatchStep,
    event_counts,
)
from packpilot.control.types import ControlOutput, Measurements, PackInfo, SwitchKind

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

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
COVERAGE_CONFIGS = ("default", "fast_iso", "fast_no_iso", "high_cutoff", "slow_mode")


def _info(n: int, cells: int = 6) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(1,) * n,
        cells_per_group=(cells,) * n,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
    )


# ------------------------------------------------------------------------------ comparison
def _same_float(x: float, ref: float | None) -> bool:
    """Bit-identical (sign of zero included), NaN equal to NaN, None stored as NaN."""
    if ref is None or math.isnan(ref):
        return math.isnan(x)
    return x == ref and math.copysign(1.0, x) == math.copysign(1.0, ref)


def _fault_code(reason: str) -> int:
    if not reason:
        return 0
    if reason.startswith("battery") and ": voltage" in reason:
        return 4
    if reason.startswith("battery") and ": current" in reason:
        return 5
    codes = [c for c, r in enumerate(FAULT_REASONS) if c and reason.startswith(r)]
    assert len(codes) == 1, reason
    return codes[0]


def assert_pack_equal(
    batch: BatchSequencing,
    res: BatchStep,
    p: int,
    state: SequencingState,
    out: ControlOutput,
    where: str,
) -> None:
    ev_ref = [(e.kind, e.battery) for e in out.events]
    assert res.events_of(p) == ev_ref, where
    assert tuple(bool(x) for x in res.chg_on[p]) == out.commands.chg_on, where
    assert tuple(bool(x) for x in res.dsg_on[p]) == out.commands.dsg_on, where
    for k, b in enumerate(state.batteries):
        w = f"{where} battery {k}"
        assert STATE_CODES[batch.state[p, k]] is b.state, w
        assert bool(batch.chg_on[p, k]) is b.chg_on, w
        assert bool(batch.dsg_on[p, k]) is b.dsg_on, w
        assert bool(batch.guard_opened[p, k]) is b.guard_opened, w
        assert bool(batch.at_risk[p, k]) is b.at_risk, w
        for name in (
            "conduct_since_s",
            "r_ohm",
            "last_v_v",
            "last_i_a",
            "hold_load_a",
            "isolated_since_s",
            "released_at_s",
        ):
            got = float(getattr(batch, name)[p, k])
            assert _same_float(got, getattr(b, name)), f"{w} {name}: {got} != {getattr(b, name)}"
    assert MODE_CODES[batch.mode[p]] is state.mode, where
    assert bool(batch.fault[p]) is (state.mode.value == "fault"), where
    assert bool(batch.initialized[p]) is state.initialized, where
    for name in ("last_t_s", "mode_evidence_since_s", "v_ref_v", "rest_since_s"):
        got = float(getattr(batch, name)[p])
        assert _same_float(got, getattr(state, name)), f"{where} {name}: {got}"
    assert int(batch.fault_code[p]) == _fault_code(state.fault_reason), where
    zl = state.zero_load_into_a
    assert bool(batch.zero_load_valid[p]) is (zl is not None), where
    for k in range(len(state.batteries)):
        ref = None if zl is None else zl[k]
        assert _same_float(float(batch.zero_load_into_a[p, k]), ref), f"{where} zl {k}"


# ------------------------------------------------------------------------------ random cases
@dataclass(frozen=True)
class Case:
    """Inputs of one random run: common time axis, per-pack measurements."""

    n: int
    config: str
    t_s: np.ndarray  # (T,)
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
    stretches, presence and docking flips, rare NaN/inf/negative inputs, and a common time axis
    with repeats, gaps and backward steps."""
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
        if config == "dyadic":
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
    return Case(n, config, t, dt, volt, cur, pres, dock)


def _meas(case: Case, i: int, p: int) -> Measurements:
    bats = tuple(
        battery_measurement(
            float(case.volt[i, p, k]), float(case.cur[i, p, k]), bool(case.present[i, p, k])
        )
        for k in range(case.n)
    )
    return Measurements(
        t_s=float(case.t_s[i]), batteries=bats, bus_v=math.nan, docked=bool(case.docked[i, p])
    )


def _reason(kind: str, data: Mapping[str, float | int | str | bool | None]) -> str:
    """Which rule produced a scalar event (its ``reason``, diode path or fault class)."""
    if kind in ("DiodeBypassed", "ReverseCurrent"):
        return str(data.get("path", "chg"))
    if kind in ("Fault", "FaultCleared"):
        return FAULT_REASONS[_fault_code(str(data["reason"]))]
    reason = str(data.get("reason", ""))
    if reason.startswith("R1 battery"):
        return "R1 battery k inserted"
    if kind in ("SourceIsolated", "CrossCurrentGuard"):
        return ""
    return reason


def run_case(case: Case) -> Counter[tuple[str, str]]:
    """Step the batch and one scalar controller per pack; compare after every step. Returns how
    often each (kind, rule) occurred in the scalar events."""
    cfg = CONFIGS[case.config]
    info = _info(case.n)
    n_packs = case.volt.shape[1]
    batch = BatchSequencing(cfg, info, n_packs)
    ctrls = [SequencingController(cfg, info) for _ in range(n_packs)]
    seen: Counter[tuple[str, str]] = Counter()
    for i in range(len(case.t_s)):
        res = batch.step(
            float(case.t_s[i]),
            case.volt[i],
            case.cur[i],
            case.present[i],
            case.docked[i],
            float(case.dt_s[i]),
        )
        for p, ctrl in enumerate(ctrls):
            out = ctrl.step(_meas(case, i, p), float(case.dt_s[i]))
            assert_pack_equal(batch, res, p, ctrl.state, out, f"step {i} pack {p}")
            seen.update((e.kind, _reason(e.kind, e.data)) for e in out.events)
    return seen


@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 4),
    config=st.sampled_from(sorted(CONFIGS)),
    n_packs=st.integers(1, 4),
    steps=st.integers(30, 120),
)
def test_random_sequences_match_the_scalar_controller(
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
    *(("Fault", r) for r in FAULT_REASONS[1:]),
    *(("FaultCleared", r) for r in FAULT_REASONS[1:]),
}


def test_random_sequences_fire_every_event_kind_and_rule() -> None:
    """The random generator is not hollow: over a fixed set of cases every event kind, and every
    rule behind one, occurs (and the batch matches the scalar controller on all of them)."""
    seen: Counter[tuple[str, str]] = Counter()
    # Seeds 0-39 fire every rule; with seeds 91 (bus estimate from an admitted battery, no
    # engaged one) and 99 (a take-over stopped by the spread of two isolated batteries) they
    # execute every reachable line of the scalar controller (checked with a line tracer when
    # this was written). The take-over refused below cut-off has its own test below.
    for seed in [*range(40), 91, 99]:
        rng = np.random.default_rng(seed)
        n = 1 + (seed // len(COVERAGE_CONFIGS)) % 4
        config = COVERAGE_CONFIGS[seed % len(COVERAGE_CONFIGS)]
        seen += run_case(gen_case(rng, n, config, 3, 100))
    kinds = {k for k, _ in seen}
    assert kinds == set(KINDS), f"event kinds never fired: {set(KINDS) - kinds}"
    assert set(seen) == RULES, (
        f"rules never fired: {RULES - set(seen)}; unknown: {set(seen) - RULES}"
    )


def test_threshold_ties_on_a_binary_grid_match() -> None:
    """Exact ties at the thresholds (``<`` vs ``<=``): the dyadic config on its 1/8 V grid. Among
    these seeds, a line tracer found R2 candidates exactly v_co above the bus (seeds 5, 17, 19,
    ...) and a rest merge exactly v_merge wide (seed 8) when this was written."""
    for seed in range(30):
        run_case(gen_case(np.random.default_rng(seed), 2 + seed % 3, "dyadic", 3, 100))


def test_batch_of_p_equals_p_batches_of_one() -> None:
    case = gen_case(np.random.default_rng(7), 3, "fast_iso", 5, 120)
    cfg = CONFIGS[case.config]
    info = _info(case.n)
    batch = BatchSequencing(cfg, info, 5)
    singles = [BatchSequencing(cfg, info, 1) for _ in range(5)]
    names = [
        *("state", "chg_on", "dsg_on", "guard_opened", "at_risk", "conduct_since_s", "r_ohm"),
        *("last_v_v", "last_i_a", "hold_load_a", "isolated_since_s", "released_at_s"),
        *("zero_load_into_a", "mode", "fault_code", "initialized", "zero_load_valid"),
        *("last_t_s", "mode_evidence_since_s", "v_ref_v", "rest_since_s", "event_totals"),
    ]
    for i in range(len(case.t_s)):
        args = (float(case.t_s[i]), case.volt[i], case.cur[i], case.present[i], case.docked[i])
        res = batch.step(*args, float(case.dt_s[i]))
        for p, one in enumerate(singles):
            r1 = one.step(
                args[0],
                args[1][p : p + 1],
                args[2][p : p + 1],
                args[3][p : p + 1],
                args[4][p : p + 1],
                float(case.dt_s[i]),
            )
            assert res.events_of(p) == r1.events_of(0)
            for name in names:
                np.testing.assert_array_equal(
                    getattr(batch, name)[p], getattr(one, name)[0], err_msg=f"{i} {p} {name}"
                )
    assert int(batch.event_totals.sum()) > 0


def test_event_counts_and_totals() -> None:
    case = gen_case(np.random.default_rng(3), 2, "default", 3, 60)
    batch = BatchSequencing(CONFIGS[case.config], _info(case.n), 3)
    acc = np.zeros((3, len(KINDS)), np.int64)
    for i in range(len(case.t_s)):
        res = batch.step(
            float(case.t_s[i]),
            case.volt[i],
            case.cur[i],
            case.present[i],
            case.docked[i],
            float(case.dt_s[i]),
        )
        acc += event_counts(res, 3)
    np.testing.assert_array_equal(acc, batch.event_totals)
    assert acc.sum() > 0


def test_bad_shapes_are_rejected() -> None:
    batch = BatchSequencing(SequencingConfig(), _info(2), 3)
    v = np.full((3, 2), 22.0)
    with pytest.raises(ValueError, match="shape"):
        batch.step(0.0, v[:2], v, np.ones((3, 2), bool), np.zeros(3, bool), 0.1)
    with pytest.raises(ValueError, match="docked"):
        batch.step(0.0, v, v, np.ones((3, 2), bool), np.zeros(2, bool), 0.1)


# ------------------------------------------------------------------------------ closed loop
class _Recording:
    """Wraps the scalar controller of a closed-loop run and records what it saw and did."""

    def __init__(self, inner: SequencingController) -> None:
        self.inner = inner
        self.log: list[tuple[Measurements, float, ControlOutput, SequencingState]] = []

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        out = self.inner.step(meas, dt_s)
        self.log.append((meas, dt_s, out, copy.deepcopy(self.inner.state)))
        return out


@pytest.mark.parametrize(
    ("name", "duration_s", "dt_s"),
    [
        ("dual_hover", 2400.0, 0.5),
        ("four_spread", 1210.0, 0.5),  # source isolation, take-over and isolation merge fire
        ("hot_insert", 2400.0, 0.5),
        ("hot_insert", 320.0, 0.1),  # the file's own period, through the insertion at 300 s
    ],
)
def test_closed_loop_on_the_plant_matches(name: str, duration_s: float, dt_s: float) -> None:
    from packpilot.config import load_config
    from packpilot.sim.runner import Runner

    cfg = load_config(EXAMPLES / f"sequencing_{name}.toml")
    cfg = cfg.model_copy(
        update={
            "controller": ["sequencing"],
            "sim": cfg.sim.model_copy(
                update={"progress": False, "duration_s": duration_s, "dt_s": dt_s}
            ),
        }
    )
    runner = Runner(cfg)
    inner = runner.controller
    assert isinstance(inner, SequencingController)
    rec = _Recording(inner)
    runner.controller = rec
    runner.run()
    info = runner.info
    seq_cfg = inner.config
    n = info.n_batteries
    # Packs 0-2: the closed-loop measurements; pack 3: the same with perturbed voltages, a
    # removal and an invalid sample, against its own scalar controller (packs independent).
    batch = BatchSequencing(seq_cfg, info, 4)
    other = SequencingController(seq_cfg, info)
    rng = np.random.default_rng(1)
    kinds: set[str] = set()
    diverged = False
    for i, (meas, dt, out, state) in enumerate(rec.log):
        v = np.array([b.voltage_v for b in meas.batteries])
        c = np.array([b.current_a for b in meas.batteries])
        pr = np.array([b.present for b in meas.batteries])
        v3 = v + rng.normal(0.0, 0.05, n)
        pr3 = pr.copy()
        if 100 <= i < 140:
            pr3[-1] = False
        if i == 200:
            v3[0] = math.nan
        volt = np.vstack([v, v, v, v3])
        cur = np.vstack([c, c, c, c])
        pres = np.vstack([pr, pr, pr, pr3])
        dock = np.array([meas.docked] * 4)
        res = batch.step(meas.t_s, volt, cur, pres, dock, dt)
        for p in range(3):
            assert_pack_equal(batch, res, p, state, out, f"{name} step {i} pack {p}")
        bats3 = tuple(
            battery_measurement(float(v3[k]), float(c[k]), bool(pr3[k])) for k in range(n)
        )
        out3 = other.step(
            Measurements(t_s=meas.t_s, batteries=bats3, bus_v=math.nan, docked=meas.docked), dt
        )
        assert_pack_equal(batch, res, 3, other.state, out3, f"{name} step {i} pack 3")
        kinds.update(e.kind for e in out.events)
        diverged = diverged or res.events_of(3) != res.events_of(0)
    assert len(rec.log) > 100
    assert len(kinds) >= 2, kinds
    assert diverged  # pack 3 really ran its own course next to packs 0-2


def test_directed_take_over_refused_below_cut_off_then_forced_release() -> None:
    """A path the random sequences rarely reach: an isolated battery, alone after its sibling
    is removed, would take over below cut-off + reserve, so the take-over is refused and the
    release is forced. Scalar and batch step through it together."""
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
    batch = BatchSequencing(cfg, info, 1)
    ctrl = SequencingController(cfg, info)
    log = []
    for t, v, c, pr in seq:
        res = batch.step(t, np.array([v]), np.array([c]), np.array([pr]), np.zeros(1, bool), 0.1)
        bats = tuple(battery_measurement(v[k], c[k], pr[k]) for k in range(2))
        out = ctrl.step(Measurements(t_s=t, batteries=bats, bus_v=math.nan), 0.1)
        assert_pack_equal(batch, res, 0, ctrl.state, out, f"t={t}")
        log.append([(e.kind, e.battery, e.data.get("reason")) for e in out.events])
    assert ("SourceIsolated", 1, "would charge battery 0, which R3 closed at this load") in log[4]
    # Take-over refused (ready, alone, spread 0, but below cut-off + reserve) -> forced release
    # (then R1, nobody being admitted).
    assert log[6] == [
        ("StateChanged", 0, "removed"),
        ("StateChanged", 1, "isolation forced"),
        ("StateChanged", 1, "R1 no battery discharging"),
    ]
