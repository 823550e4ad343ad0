"""Property-based closed-loop tests of sequencing on the project plant.

Random N (2-6), rest voltages spread over 0-4 V, resistances 15-35 mOhm, piecewise-constant load
profiles (including drops to zero), a hot insertion at a random time, control periods 0.1-0.5 s.
Each example is a short run (<= 600 steps) so the whole file stays fast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config import parse_config
from packpilot.contract.record import Result
from packpilot.control.sequencing import SequencingConfig
from packpilot.model import loads
from packpilot.model.cell import ocv_v
from packpilot.sim.runner import Runner

CFG = SequencingConfig()
DURATION_S = 60.0


@dataclass(frozen=True)
class Case:
    ocv0_v: tuple[float, ...]
    r_ohm: tuple[float, ...]
    dt_s: float
    load_t_s: tuple[float, ...]
    load_a: tuple[float, ...]
    insert: tuple[int, float] | None


@st.composite
def cases(draw: st.DrawFn) -> Case:
    n = draw(st.integers(2, 6))
    low = draw(st.floats(21.0, 23.0))
    spread = draw(st.floats(0.0, 4.0))
    ocv0 = tuple(low + spread * draw(st.floats(0.0, 1.0)) for _ in range(n))
    r = tuple(draw(st.floats(0.015, 0.035)) for _ in range(n))
    dt = draw(st.sampled_from([0.1, 0.2, 0.5]))
    n_seg = draw(st.integers(1, 5))
    times = sorted({0.0, *(draw(st.floats(1.0, DURATION_S - 1.0)) for _ in range(n_seg - 1))})
    amps = tuple(draw(st.one_of(st.just(0.0), st.floats(0.5, 12.0 * n))) for _ in range(len(times)))
    insert = None
    if draw(st.booleans()):
        insert = (draw(st.integers(0, n - 1)), draw(st.floats(0.0, DURATION_S)))
    return Case(ocv0, r, dt, tuple(times), amps, insert)


def simulate(case: Case, sequencing: dict[str, float] | None = None) -> tuple[Result, np.ndarray]:
    """Run the case; also return each battery's open-circuit voltage after every period."""
    bats = []
    for k, (v, r) in enumerate(zip(case.ocv0_v, case.r_ohm, strict=True)):
        b: dict[str, object] = {
            "name": f"B{k}",
            "cells_per_group": 6,
            "ocv0_v": v,
            "resistance_ohm": r,
        }
        if case.insert is not None and case.insert[0] == k:
            b["present_from_s"] = case.insert[1]
        bats.append(b)
    cfg = parse_config(
        {
            "pack": {
                "cell": "uav_5ah",
                "switch": {"kind": "mosfet_pair", "on_ohm": 0.0001, "diode_drop_v": 0.6},
                "batteries": bats,
            },
            "load": {"kind": "current", "value": 1.0, "v_min_v": 15.0},
            "controller": ["sequencing"],
            "sequencing": sequencing or {},
            "sim": {"dt_s": case.dt_s, "duration_s": DURATION_S, "progress": False},
        }
    )
    runner = Runner(cfg)
    runner.profile = loads.LoadProfile(
        kind="current",
        t_s=np.array([*case.load_t_s, DURATION_S + 1.0]),
        value=np.array([*case.load_a, 0.0]),
    )
    n = len(bats)
    ocv_after: list[np.ndarray] = []

    def record_ocv(run: Runner, t_s: float) -> None:
        soc, temp = run.pack.cell_states()
        cell = ocv_v(run.pack.banks[0].params, soc[0], temp[0])
        ocv_after.append(np.bincount(run.pack.cell_string, weights=cell, minlength=n))

    runner.hooks = [record_ocv]
    res = runner.run()
    record_ocv(runner, runner.pack.t_s)
    return res, np.array(ocv_after[1:])


# Known to fail (issue #18; #15 replaces this invariant with "never above the charge limit"):
# Hypothesis finds cases often, e.g. the one pinned below, and ocv0 (22, 22, 22.75, 22, 23) V,
# battery 2 inserted at 2 s, 19 A then 0.5 A: 1.02 A into battery 2 at step 181. Not strict:
# a draw may miss them; the pinned case is strict.
@pytest.mark.xfail(strict=False, reason="issue #18: known counterexamples, see comment")
@settings(max_examples=50, deadline=None)
@given(cases())
def test_closed_loop_invariants(case: Case) -> None:
    _check_invariants(case)


@pytest.mark.xfail(
    strict=True,
    reason="issue #18: at step 11, 6.9 A flows into battery 5 while the load is supplied",
)
def test_closed_loop_invariants_known_counterexample() -> None:
    _check_invariants(
        Case(
            ocv0_v=(21.0, 21.0, 21.0, 21.0, 22.0, 21.5),
            r_ohm=(0.03125,) * 6,
            dt_s=0.1,
            load_t_s=(0.0, 1.0),
            load_a=(32.0, 1.0),
            insert=None,
        )
    )


def _check_invariants(case: Case) -> None:
    res, ocv = simulate(case)
    tr = res.trace
    n = len(case.ocv0_v)
    cur = tr.channel("current_a")
    volt = tr.channel("voltage_v")
    chg = tr.channel("chg_on") > 0.5
    chg_diode = tr.channel("chg_diode_a")
    states = tr.status["seq_state"]
    into = np.maximum(-cur, 0.0)
    supplied = tr.load_a > 1e-3
    isolated = tr.status["seq_isolated"]
    dsg = tr.channel("dsg_on") > 0.5

    # The load is always supplied (every battery is far above the load's 15 V lock-out).
    assert res.metrics["load_unsupplied_s"] == 0.0
    assert res.metrics["events"].get("Fault", 0) == 0

    for k in range(len(tr.t_s)):
        for j in range(n):
            # A battery in STANDBY never has its charge FET on.
            if states[k][j] == "STANDBY":
                assert not chg[k, j]
            # At most 1 A into a battery while the pack discharges, whatever the load does
            # next: the cross-current guard opens, before the load can fall, any battery the
            # others would charge with more than i_guard at zero load, and where it may not
            # (R3 closed that battery at this load: the R3 conflict) source isolation takes the
            # battery that would push that current off the bus (both FETs off) while the rest
            # can carry the load. No exception: every generated case.
            if supplied[k]:
                assert into[k, j] <= 1.0, (k, j, into[k, j])
            # An isolated battery has both FETs off and carries nothing.
            if isolated[k][j]:
                assert not chg[k, j] and not dsg[k, j] and abs(cur[k, j]) < 1e-6, (k, j)

        # Co-discharge: batteries engaged together share the bus, so their OCV spread is
        # bounded by v_co plus the difference of their internal (IR + polarisation) drops.
        engaged = [j for j in range(n) if chg[k, j] and states[k][j] == "DISCHARGING"]
        drop = ocv[k] - volt[k]
        for a in engaged:
            for b in engaged:
                if a < b:
                    spread = abs(ocv[k, a] - ocv[k, b])
                    assert spread <= CFG.v_co + abs(drop[a] - drop[b]) + 0.01, (k, a, b)

    # R3 deadline on the plant: a charge diode never conducts for longer than t_on plus one
    # control period in a row.
    limit = math.ceil((CFG.t_on + case.dt_s) / case.dt_s - 1e-9)
    for j in range(n):
        run = 0
        for k in range(len(tr.t_s)):
            run = run + 1 if chg_diode[k, j] > CFG.i_det else 0
            assert run <= limit, (j, k, run)


def _unflagged_cross_a(res: Result) -> float:
    """Largest current into a battery while the load is supplied, outside flagged risk."""
    tr = res.trace
    into = np.maximum(-tr.channel("current_a"), 0.0)
    risk = np.array(tr.status["seq_at_risk"], dtype=bool)
    mask = (tr.load_a > 1e-3)[:, None] & ~risk
    return float(into[mask].max()) if mask.any() else 0.0


# Four batteries 0.1 V apart with 16/24/20/30 mOhm (the four_spread resistances) sharing 39 A,
# then the load falls to 1.5 A at t = 55 s (the mission's landing step).
LANDING = Case(
    (23.0, 23.1, 23.2, 23.3), (0.016, 0.024, 0.02, 0.03), 0.1, (0.0, 55.0), (39.0, 1.5), None
)


def test_guard_is_what_keeps_the_landing_step_below_1a() -> None:
    # The invariant of test_closed_loop_invariants can fail: with the guard disabled (i_guard
    # huge) co-discharge and the landing step push more than 2 A into a battery.
    off, _ = simulate(LANDING, {"i_guard": 1e3})
    assert _unflagged_cross_a(off) > 2.0
    on, _ = simulate(LANDING)
    assert _unflagged_cross_a(on) <= 1.0
    assert on.metrics["peak_cross_current_a"] <= 1.0
    assert on.metrics["events"].get("CrossCurrentGuard", 0) >= 1
    assert on.metrics["load_unsupplied_s"] == 0.0


# A battery hot-inserted 1.3 V above five others under a 71 A load, which then falls to 10 A
# (found by the random sweep). The high battery alone sags so far that the others' charge diodes
# conduct, R3 closes them, and they co-discharge with it across a 1.3 V gap.
HOT_HEAVY = Case(
    (22.054, 23.354, 21.906, 22.006, 22.151, 22.210),
    (0.0295, 0.0285, 0.0308, 0.0258, 0.0166, 0.0303),
    0.1,
    (0.0, 13.63, 25.03, 58.41),
    (25.99, 71.32, 10.19, 56.43),
    (1, 22.77),
)


def test_source_isolation_keeps_the_hot_heavy_case_below_1a() -> None:
    # Without source isolation the guard can only flag the risk (the victims' diodes would
    # conduct if opened) and the load drop pushes well over 1 A into a battery.
    off, _ = simulate(HOT_HEAVY, {"isolate_source": False})
    assert off.metrics["peak_cross_current_a"] > 5.0
    on, _ = simulate(HOT_HEAVY)
    assert on.metrics["peak_cross_current_a"] <= 1.0
    assert on.metrics["events"].get("SourceIsolated", 0) >= 1
    assert on.metrics["load_unsupplied_s"] == 0.0
