"""Property-based closed-loop tests of sequencing on the project plant.

Random N (2-6), rest voltages spread over 0-4 V, resistances 15-35 mOhm, piecewise-constant load
profiles (including drops to zero), a hot insertion at a random time, control periods 0.1-0.5 s.
Each example is a short run (<= 600 steps) so the whole file stays fast.

Invariant (issue #15, replacing "at most 1 A into any battery, ever"): current into a battery
never exceeds its charge limit (0.5C), any reverse current is cut within one control period
(plus the FET delay: none in this plant, commands apply from the next step), and reverse
current above 1 A never lasts longer than that. Without the reverse-current comparator the
charge limit can be exceeded in the one period in which the load falls only where R3 had to
close a battery's charge FET (its diode conducted) although the zero-load prediction put it
above its limit - the controller flags exactly that (``seq_at_risk``); with the comparator
fitted nothing above its 1 A trip flows into any battery.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.config import parse_config
from packpilot.contract.record import Result
from packpilot.control.sequencing import SequencingConfig
from packpilot.model import loads
from packpilot.model.cell import ocv_v
from packpilot.sim.runner import Runner
from tests.budget import budget

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


def simulate(
    case: Case,
    sequencing: dict[str, float] | None = None,
    comparator: bool = False,
    observer: bool = False,
    duration_s: float = DURATION_S,
) -> tuple[Result, np.ndarray]:
    """Run the case; also return each battery's open-circuit voltage after every period.
    ``observer``: with ``[soc]`` (the battery observer, whose R0 the zero-load prediction
    then reads, issue #28)."""
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
    data: dict[str, object] = {
        "pack": {
            "cell": "uav_5ah",
            "switch": {
                "kind": "mosfet_pair",
                "on_ohm": 0.0001,
                "diode_drop_v": 0.6,
                "reverse_comparator": comparator,
            },
            "batteries": bats,
        },
        "load": {"kind": "current", "value": 1.0, "v_min_v": 15.0},
        "controller": ["sequencing"],
        "sequencing": sequencing or {},
        "sim": {"dt_s": case.dt_s, "duration_s": duration_s, "progress": False},
    }
    if observer:
        data["soc"] = {}
    cfg = parse_config(data)
    runner = Runner(cfg)
    runner.profile = loads.LoadProfile(
        kind="current",
        t_s=np.array([*case.load_t_s, duration_s + 1.0]),
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


I_LIM = CFG.charge_limit_c * 5.0
"""0.5C of the 5 Ah uav_5ah batteries: 2.5 A."""
TRIP_A = 1.0
"""The comparator's default trip current."""


# CI runs a fixed set of 200 examples (derandomized, as the equalization closed loop does): the
# nightly soak, which explores new ones every night (budget drops derandomize there), still
# finds rare cases at 0.5 s periods (SOAK_4 below, open), and CI must not fail at random on
# one. Every counterexample the soak finds is added as a named case.
@budget(200, derandomize=True)
@given(cases(), st.booleans())
def test_closed_loop_invariants(case: Case, comparator: bool) -> None:
    _check_invariants(case, comparator)


# Issue #18's shrunk case (was a strict xfail: 6.9 A into battery 5 at step 11 while the load
# was supplied, under the old "<= 1 A ever" property and the guard/isolation rules). The new
# rules never close battery 5's charge FET onto the others at that gap; kept as a regression
# test, with and without the comparator.
KNOWN_18 = Case(
    ocv0_v=(21.0, 21.0, 21.0, 21.0, 22.0, 21.5),
    r_ohm=(0.03125,) * 6,
    dt_s=0.1,
    load_t_s=(0.0, 1.0),
    load_a=(32.0, 1.0),
    insert=None,
)
# The other case named in issue #18: 1.02 A into battery 2 at step 181.
KNOWN_18B = Case(
    ocv0_v=(22.0, 22.0, 22.75, 22.0, 23.0),
    r_ohm=(0.02,) * 5,
    dt_s=0.1,
    load_t_s=(0.0, 30.0),
    load_a=(19.0, 0.5),
    insert=(2, 2.0),
)


# Found by a 300-example sweep of the new property (seed 7): battery 3 inserted 0.4 V above
# battery 2 (below v_th) waited open while its diode carried just under i_det for 44 s; when R3
# closed it, it pushed 5.1 A into battery 2 at the unchanged 5 A load for one period. Fixed by the
# R3 hand-over (battery 2's charge FET opens in the same period).
SWEEP_7 = Case(
    ocv0_v=(21.0, 21.0, 21.75, 22.0, 21.0),
    r_ohm=(0.03125,) * 5,
    dt_s=0.1,
    load_t_s=(0.0,),
    load_a=(5.0,),
    insert=(3, 1.0),
)


# The same sweep after the hand-over: battery 3 inserted 0.46 V above battery 2; R3 closed it
# and the hand-over opened batteries 1 and 4 (predicted > i_rev) but not battery 2, which the
# prediction with 1 and 4 still engaged kept below i_rev: 2.7 A into it for one period. The
# hand-over now opens the worst first and predicts the rest again.
SWEEP_7B = Case(
    ocv0_v=(21.0, 21.5625, 21.6328125, 22.08984375, 21.5625),
    r_ohm=(0.03125, 0.03125, 0.03125, 0.02734375, 0.03125),
    dt_s=0.1,
    load_t_s=(0.0, 1.0),
    load_a=(0.0, 11.0),
    insert=(3, 1.0),
)


# The third: R3 closed battery 3 (0.375 V above battery 2) under 19 A; when the load fell to 0
# batteries 1 and 4 took charge (flagged) and were cut, and in the next period battery 3 poured
# 5.9 A into battery 2, which the full set had kept below i_rev. The reverse cut now predicts
# the remaining set at the present load and opens the next victim in the same period.
SWEEP_7C = Case(
    ocv0_v=(21.0, 21.5, 21.625, 22.0, 21.5),
    r_ohm=(0.03125, 0.015625, 0.03125, 0.03125, 0.03125),
    dt_s=0.1,
    load_t_s=(0.0, 1.0, 2.0),
    load_a=(0.0, 19.0, 0.0),
    insert=(3, 1.0),
)


# Found by the nightly soak (10,000 examples, 2026-11-25): with dt 0.5 s (> t_on) R3 closes
# five standby batteries in the step that first sees their diodes conduct under 18 A, flags
# the zero-load risk (2.79 A predicted) in that same step, and the load drops to 0 in the
# period after it: 2.57 A flows into each for one period, then the reverse cut opens them. The
# behaviour is the documented R3 exception; the property was wrong to demand the flag one
# period *before* the closing step (it now accepts the flag raised by that step).
SOAK_1 = Case(
    ocv0_v=(21.5, 21.0, 21.0, 21.0, 21.0, 21.0),
    r_ohm=(0.03125,) * 6,
    dt_s=0.5,
    load_t_s=(0.0, 1.0, 1.5),
    load_a=(0.0, 18.0, 0.0),
    insert=None,
)


# Found next (the CI budget replayed it from the example database after the soak): six
# batteries, one with half the resistance; when 59 A stops, the other five push 0.19-0.21 A
# each into it, 1.0 A in all, and the reverse cut never fired because it looked for one
# sibling sourcing more than i_det (0.5 A). It now counts what the siblings source together.
SOAK_2 = Case(
    ocv0_v=(21.0,) * 6,
    r_ohm=(0.03125,) * 5 + (0.015625,),
    dt_s=0.1,
    load_t_s=(0.0, 1.0, 27.0),
    load_a=(0.0, 59.0, 0.0),
    insert=None,
)


# Found by a CI-budget run of the property (2026-11-25, a helper's full suite): 0.5 s periods,
# R3 closed battery 3 (half the others' resistance) under 27 A and flagged 3.87 A predicted at
# zero load; as the two discharging batteries converged the prediction fell to just under the
# 2.5 A limit and the flag cleared one period before the load fell to 0, when 2.72 A flowed
# into battery 3 for one period. The resistances, estimated over a 0.5 s current step, take in
# polarization and under-predict by ~9 %: the flag now clears only below risk_clear_ratio
# (0.8) x the limit.
SUITE_3 = Case(
    ocv0_v=(21.0, 21.0, 21.703125, 21.515625, 21.0),
    r_ohm=(0.03125, 0.03125, 0.03125, 0.015625, 0.03125),
    dt_s=0.5,
    load_t_s=(0.0, 7.0),
    load_a=(27.0, 0.0),
    insert=None,
)


# Then the nightly soak (10,000 examples, the same day): the engage rule closed battery 1's
# charge FET with 2.46-2.49 A predicted at zero load (limit 2.5 A); when 22 A stopped, 2.51 A
# flowed into it for one period, never flagged. The prediction was within 1.6 % but the rule
# used the limit itself: it now keeps predictions within charge_limit_margin (0.9) x the
# limit, and the flag is raised above that.
SOAK_3 = Case(
    ocv0_v=(21.0, 21.078125, 21.0, 21.546875, 21.15625, 21.234375),
    r_ohm=(0.03125, 0.02, 0.03125, 0.03125, 0.03125, 0.03125),
    dt_s=0.1,
    load_t_s=(0.0, 1.0, 20.0),
    load_a=(0.0, 22.0, 0.0),
    insert=None,
)


# Open (found by the soak after both margin fixes): 0.5 s periods, R3 closes battery 4 under
# 52 A with 5.98 A predicted at zero load (flagged); one period later a new resistance estimate,
# taken over the 0.5 s current step and so including polarization, lowers the prediction to
# 1.71 A and the flag clears; the load stops the next period and 2.64 A (limit 2.5 A) flows
# for one period, unflagged. The prediction was 35 % low: no fixed margin covers that. A flag
# that holds for a settling time after R3 (or a resistance fit that excludes polarization at
# long periods) would; not done.
SOAK_4 = Case(
    ocv0_v=(21.0, 21.0, 21.0, 21.0, 23.25, 24.0),
    r_ohm=(0.03125, 0.03125, 0.03125, 0.03125, 0.03125, 0.015625),
    dt_s=0.5,
    load_t_s=(0.0, 1.0, 13.0),
    load_a=(0.0, 52.0, 0.0),
    insert=None,
)


# Issue #28: with the battery observer trusted the prediction no longer drops after R3 and
# the same case passes (tests/test_sequencing_zero_load.py::
# test_soak_4_with_the_observer_trusted_flags_what_r3_forces, after a minute's rest). This
# scenario has no [soc] and its load falls at 13 s, before any observer is trusted (its 60 s
# window): the -dV/dI fallback, so it stays open here.
@pytest.mark.xfail(strict=True, reason="open without an observer: the -dV/dI zero-load "
                   "prediction 35 % low at 0.5 s right after R3 (SOAK_4's comment)")  # fmt: skip
def test_closed_loop_invariants_open_counterexample() -> None:
    _check_invariants(SOAK_4, comparator=False)


@pytest.mark.parametrize("comparator", [False, True])
@pytest.mark.parametrize(
    "case",
    [KNOWN_18, KNOWN_18B, SWEEP_7, SWEEP_7B, SWEEP_7C, SOAK_1, SOAK_2, SUITE_3, SOAK_3],
    ids=["step11", "step181", "sweep7", "sweep7b", "sweep7c", "soak1", "soak2", "suite3",
         "soak3"],
)
def test_closed_loop_invariants_known_counterexample(case: Case, comparator: bool) -> None:
    res = _check_invariants(case, comparator)
    peak = float(np.maximum(-res.trace.channel("current_a"), 0.0).max())
    # Without the comparator a load drop can push more than 1 A into a battery for one period
    # (step181: ~1.3 A at 30 s; sweep7c: 7.7 A into a battery R3 forced and the controller had
    # flagged), which _check_invariants bounds; with it nothing above its trip.
    if comparator:
        assert peak <= TRIP_A


def _check_invariants(
    case: Case, comparator: bool = False, observer: bool = False, duration_s: float = DURATION_S
) -> Result:
    res, _ocv = simulate(case, comparator=comparator, observer=observer, duration_s=duration_s)
    tr = res.trace
    n = len(case.ocv0_v)
    cur = tr.channel("current_a")
    chg = tr.channel("chg_on") > 0.5
    chg_diode = tr.channel("chg_diode_a")
    states = tr.status["seq_state"]
    risk = np.array(tr.status["seq_at_risk"], dtype=bool)
    into = np.maximum(-cur, 0.0)

    # The load is always supplied (every battery is far above the load's 15 V lock-out).
    assert res.metrics["load_unsupplied_s"] == 0.0
    assert res.metrics["events"].get("Fault", 0) == 0

    # Reverse current above 1 A never lasts longer than one control period (the period in
    # which the load fell; the reverse cut acts on the next sample).
    for j in range(n):
        run = 0
        for k in range(len(tr.t_s)):
            run = run + 1 if into[k, j] > 1.0 else 0
            assert run <= 1, (j, k, into[k, j])

    for k in range(len(tr.t_s)):
        for j in range(n):
            # A battery in STANDBY never has its charge FET on.
            if states[k][j] == "STANDBY":
                assert not chg[k, j]
            if comparator:
                # The comparator cuts within the step: nothing above its trip current.
                assert into[k, j] <= TRIP_A + 1e-9, (k, j, into[k, j])
            elif into[k, j] > I_LIM:
                # Above the charge limit only where R3 had to close it and the controller
                # flagged the risk before the current flowed: in the step that closed it (row
                # k is a decision and the period after it) or in the period before.
                assert risk[k, j] or (k > 0 and risk[k - 1, j]), (k, j, into[k, j])

    # R3 deadline on the plant: a charge diode never conducts for longer than t_on plus one
    # control period in a row.
    limit = math.ceil((CFG.t_on + case.dt_s) / case.dt_s - 1e-9)
    for j in range(n):
        run = 0
        for k in range(len(tr.t_s)):
            run = run + 1 if chg_diode[k, j] > CFG.i_det else 0
            assert run <= limit, (j, k, run)
    return res


# Four batteries 0.1 V apart with 16/24/20/30 mOhm (the four_spread resistances) sharing 39 A,
# then the load falls to 1.5 A at t = 55 s (the mission's landing step).
LANDING = Case(
    (23.0, 23.1, 23.2, 23.3), (0.016, 0.024, 0.02, 0.03), 0.1, (0.0, 55.0), (39.0, 1.5), None
)


def test_landing_step_stays_within_the_charge_limit_and_is_cut_in_one_period() -> None:
    res = _check_invariants(LANDING)
    into = np.maximum(-res.trace.channel("current_a"), 0.0)
    assert float(into.max()) <= I_LIM
    assert res.metrics["events"].get("CrossCurrentGuard", 0) == 0


# A battery hot-inserted 1.3 V above five others under a 71 A load, which then falls to 10 A
# (found by the random sweep of the old guard). The high battery alone sags so far that the
# others' charge diodes conduct, R3 closes them, and they co-discharge with it across a 1.3 V
# gap: the load drop pushes more than the charge limit into them for one period without the
# comparator (flagged), nothing above 1 A with it.
HOT_HEAVY = Case(
    (22.054, 23.354, 21.906, 22.006, 22.151, 22.210),
    (0.0295, 0.0285, 0.0308, 0.0258, 0.0166, 0.0303),
    0.1,
    (0.0, 13.63, 25.03, 58.41),
    (25.99, 71.32, 10.19, 56.43),
    (1, 22.77),
)


@pytest.mark.parametrize("comparator", [False, True])
def test_hot_heavy_case_holds_the_invariant(comparator: bool) -> None:
    res = _check_invariants(HOT_HEAVY, comparator)
    assert res.metrics["load_unsupplied_s"] == 0.0
