"""Issue #28: sequencing's zero-load prediction from the battery observer, and the charge-limit
invariant without the reverse-current comparator on randomized abrupt load losses.

The cases are ``benchmarks/bench_zero_load.py``'s generator (2-6 batteries of spread age and
SOC, a 10-60 A hold of 1-20 minutes, then the load vanishes), on the real plant with the
comparator off; the benchmark runs 500 of them, this file a seeded subset that fits CI.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from benchmarks.bench_zero_load import REST_S, draw, run_case

from packpilot.contract.bms import Event
from packpilot.contract.record import Result
from packpilot.sim.loop import ClosedLoop
from tests.test_sequencing_closed_loop_properties import (
    CFG,
    I_LIM,
    Case,
    _check_invariants,
    simulate,
)

SUBSET = tuple(range(80))
"""Seeds of the CI subset (each a closed loop of up to ~2,450 periods of 0.5 s; the 80
together take ~40-60 s CPU)."""


@pytest.mark.parametrize("seed", SUBSET)
def test_an_abrupt_load_loss_never_pushes_more_than_the_charge_limit(seed: int) -> None:
    """Within the charge limit in every period, except where R3 had to close the battery's
    charge FET (its diode carried current) within ``R3_HOLD_S`` of the loss while the
    prediction put it above its limit, flagged in that step: the documented R3 exception
    (docs/parallel_discharge.md rule 8b, "not held by it"; seeds 23 and 63 of this subset),
    which only the comparator removes."""
    res = run_case(draw(seed), hook=True, open_=True)
    assert not res["unsupplied"], res
    assert res["worst"] <= 1.0 or (res["flagged"] and res["r3_forced"]), res


R3_FORCED = (23, 63)
"""The subset's cases above the limit (strictly), both R3-forced: the invariant does not hold
there without the comparator."""


@pytest.mark.parametrize("seed", R3_FORCED)
def test_the_r3_forced_cases_are_flagged_before_the_current_flows(seed: int) -> None:
    res = run_case(draw(seed), hook=True)
    assert res["worst"] > 1.0 and res["after_loss"], res
    assert res["flagged"] and res["r3_forced"], res


# Seed 0 of the generator: four batteries of spread age, 54.6 A for 67 s. The -dV/dI estimate
# (taken over a 0.5 s current step, polarisation included) predicted 1.31x battery 0's charge
# limit and flagged it; 0.545x flowed when the load vanished. The observer's R0 predicts it.
ACCURATE_SEED = 0


@pytest.mark.parametrize("seed", [ACCURATE_SEED, 14, 20])
def test_the_zero_load_prediction_uses_the_observers_r0(seed: int) -> None:
    """What the controller predicted when the load vanished against what flowed into each
    battery in that period (both / its charge limit; engaged batteries: prediction not 0).
    The -dV/dI prediction was 0.67-0.86 of the limit off on these seeds (1.31 / 1.37 / 1.44
    predicted, 0.45-0.59 flowed)."""
    res = run_case(draw(seed), hook=True)
    assert res["observer_ok"], res
    engaged = [k for k, x in enumerate(res["predicted_all"]) if x != 0.0]
    assert engaged, res
    for k in engaged:
        assert abs(res["predicted_all"][k] - res["at_loss_all"][k]) <= 0.1, (k, res)


def test_without_a_trusted_observer_the_prediction_is_the_resistance_estimates() -> None:
    """Fallback: the hook off gives the -dV/dI prediction (the same run, the same bits as a
    core whose observer is not trusted yet)."""
    case = draw(ACCURATE_SEED)
    on, off = run_case(case, hook=True), run_case(case, hook=False)
    assert on["worst"] == pytest.approx(off["worst"], abs=0.05)
    assert off["predicted"] > 1.0 > on["predicted"]


def test_the_core_tells_sequencing_where_the_observer_publishes() -> None:
    from benchmarks.bench_zero_load import scenario

    loop = ClosedLoop.of(scenario(draw(1), hook=True), 1)
    slots = {ch.name: s for s, ch, _ in loop.core.status_channels()}
    seq = next(x for x in loop.core.compiled if x.method.name == "sequencing")
    assert list(seq.prm.reads_slot) == [slots["soc_r0_ohm"], slots["soc_observer_ok"]]


# SOAK_4 (tests/test_sequencing_closed_loop_properties.py, open) after a minute at rest, so the
# observer is trusted (its 60 s window) when R3 closes battery 4 under 52 A and the load stops.
SOAK_4_OBSERVED = Case(
    ocv0_v=(21.0, 21.0, 21.0, 21.0, 23.25, 24.0),
    r_ohm=(0.03125, 0.03125, 0.03125, 0.03125, 0.03125, 0.015625),
    dt_s=0.5,
    load_t_s=(0.0, 61.0, 73.0),
    load_a=(0.0, 52.0, 0.0),
    insert=None,
)


def test_soak_4_with_the_observer_trusted_flags_what_r3_forces() -> None:
    """SOAK_4's open defect was an *unflagged* 2.64 A (limit 2.5 A): the -dV/dI estimate
    lowered the prediction to 1.71 A one period after R3. With the observer's R0 the
    prediction stays above the limit, so the property's R3 exception holds (flagged); the
    current itself is what R3 forces (battery 4's diode carried 52 A's share: it must close),
    which only the comparator removes."""
    res = _check_invariants(SOAK_4_OBSERVED, comparator=False, observer=True, duration_s=90.0)
    into = np.maximum(-res.trace.channel("current_a"), 0.0)
    assert float(into.max()) > I_LIM  # the R3-forced period is still there, flagged


# Rule 8c (issue #28, ``diode_hold_a``): R3 leaves a battery on its charge diode while closing
# it would put it above its charge limit at zero load and the diode carries at most the cap.
HOLD = {"diode_hold_a": 5.0}


def _held_events(res: Result) -> list[Event]:
    return [e for e in res.events if e.kind == "CrossCurrentRisk" and "held off" in e.message]


def test_r3_leaves_a_lower_battery_on_its_diode_while_closing_it_would_exceed_its_limit() -> None:
    """SOAK_4 with the observer trusted: battery 4 (23.25 V) stands by while battery 5
    (24.0 V) carries 52 A; the bus sags until battery 4's diode conducts. R3 closed it (its
    deadline) and the loss of the load at 73 s pushed 2.64 A into it (limit 2.5 A). With rule
    8c it stays on its diode, which carries a few amperes, and the loss pushes nothing into it
    above the limit."""
    res, _ = simulate(SOAK_4_OBSERVED, sequencing=HOLD, observer=True, duration_s=90.0)
    into = np.maximum(-res.trace.channel("current_a"), 0.0)
    assert float(into.max()) <= I_LIM, float(into.max())
    held = _held_events(res)
    assert held and all(e.battery == 4 for e in held), held
    diode = res.trace.channel("chg_diode_a")[:, 4]
    assert float(diode.max()) <= 1.2 * HOLD["diode_hold_a"], float(diode.max())


# SOAK_4_OBSERVED with battery 4 at 23.6 V (admitted by R1, not engaged: 0.4 V over 47 mOhm
# is 3.4x its limit) and a 90 A load: battery 4's diode takes 10-14 A at once, and closing it
# stays above the limit for ~4 s (held, with no cap, for 9 periods).
HEAVY_DIODE = Case(
    ocv0_v=(21.0, 21.0, 21.0, 21.0, 23.6, 24.0),
    r_ohm=SOAK_4_OBSERVED.r_ohm,
    dt_s=0.5,
    load_t_s=(0.0, 61.0, 75.0),
    load_a=(0.0, 90.0, 0.0),
    insert=None,
)


def test_a_diode_carrying_more_than_diode_hold_a_is_closed_on_r3s_deadline() -> None:
    """The cap: battery 4's diode carries 10-14 A, above ``diode_hold_a`` = 2 A, so R3 closes
    it on its deadline as without rule 8c (the diode must not carry more than its rating)."""
    res, _ = simulate(HEAVY_DIODE, sequencing={"diode_hold_a": 2.0}, observer=True, duration_s=80.0)
    diode = res.trace.channel("chg_diode_a")[:, 4]
    assert float(diode.max()) > 5.0  # the case does put its diode above the cap
    limit = math.ceil((CFG.t_on + HEAVY_DIODE.dt_s) / HEAVY_DIODE.dt_s - 1e-9)
    run = longest = 0
    for x in diode:
        run = run + 1 if x > CFG.i_det else 0
        longest = max(longest, run)
    assert longest <= limit, (longest, float(diode.max()))
    assert not _held_events(res)


HOLD_10 = {"diode_hold_a": 10.0}


@pytest.mark.parametrize("seed", [*R3_FORCED, 230])
def test_rules_8b_and_8c_together_hold_the_charge_limit_where_r3_forced_it(seed: int) -> None:
    """Rule 8b alone leaves the R3-forced class (seeds 23 and 63: 1.30x and 1.37x; 230: 2.50x):
    8b opens a battery, its diode conducts under the load, R3 closes it again within seconds
    and the load goes. With rule 8c (diode up to 10 A) R3 leaves it on its diode while the
    prediction is above the limit, and 8b may open a battery R3 closed within the cap at once
    (seed 230: 1.13x three seconds after such a closure while 8b waited R3_HOLD_S)."""
    res = run_case(draw(seed), hook=True, open_=True, extra=HOLD_10)
    assert not res["unsupplied"], res
    assert res["worst"] <= 1.0, res


# Seed 230 of the generator (five batteries, 56.8 A) with the load lost at every period from
# 71 s to 77 s instead of at 126 s: rules 8b and 8c hand the load over between batteries 3
# and 4, and R3 closed battery 3 at 67.5 s and battery 4 at 72 s at 0.83x and 0.77x their
# limits (below rule 8c's 0.9, their diodes carrying 9 and 3 A, within the 10 A cap), after
# which the prediction passed 1.0x within 1-1.5 s. Rule 8b waited R3_HOLD_S (5 s) before it
# could open them, and a loss in that window pushed up to 1.62x into battery 4 (loss at
# 76.5 s; 9 of these 13 instants above the limit; over 70-90 s, 18 of 41).
WINDOW_SEED = 230
WINDOW_LOSSES_S = tuple(71.0 + 0.5 * i for i in range(13))


def _losses_at(seed: int, losses_s: tuple[float, ...]) -> list[tuple[float, dict[str, Any]]]:
    """Case ``seed`` (rules 8a+8b+8c, ``diode_hold_a`` 10 A) with its load lost at each of
    ``losses_s`` instead: (the instant, its result) each, the load supplied throughout."""
    case0 = draw(seed)
    out = []
    for t_off in losses_s:
        res = run_case(dataclasses.replace(case0, hold_s=t_off - REST_S), hook=True, open_=True,
                       extra=HOLD_10)  # fmt: skip
        assert not res["unsupplied"], (t_off, res)
        out.append((t_off, res))
    return out


def test_a_load_loss_just_after_r3_closes_a_battery_within_the_cap_stays_in_the_limit() -> None:
    """The charge limit holds wherever the loss lands in the hand-over cycle, including the
    seconds after R3 closed a battery whose diode carried at most ``diode_hold_a``: rule 8b
    opens it as soon as its prediction passes ``open_ratio`` (rule 8c then holds it on its
    diode), instead of waiting ``R3_HOLD_S``. The losses do land in R3's hold (the worst
    battery was closed by R3 less than ``R3_HOLD_S`` before the loss in some of them)."""
    worst: list[tuple[float, float]] = []
    forced = 0
    for t_off, res in _losses_at(WINDOW_SEED, WINDOW_LOSSES_S):
        worst.append((res["worst"], t_off))
        forced += bool(res["r3_forced"])
    assert forced >= 5, forced
    assert max(w for w, _ in worst) <= 1.0, sorted(worst)[-5:]


# Seed 75 (five batteries, 40.9 A): at 116.5 s and 149 s R3 closes batteries 3 and 4 in one
# period (8b had opened them; their diodes carried 2-6 A). Rule 8c judged battery 3 against
# the batteries engaged before it, and battery 4's closure put it above its limit: a loss in
# that period pushed 1.20x and 1.65x into it while rule 8b skipped a battery R3 closed in the
# period (mutant r3-closed-now-skipped).
SAME_PERIOD_SEED = 75
SAME_PERIOD_LOSSES_S = (116.5, 149.0)


def test_a_load_loss_in_the_period_r3_closes_two_batteries_stays_in_the_limit() -> None:
    """Rule 8b looks, in the same period, at a battery R3 closed within ``diode_hold_a`` (rule
    8c then holds it on its diode); the loss lands in the period of R3's closures."""
    for t_off, res in _losses_at(SAME_PERIOD_SEED, SAME_PERIOD_LOSSES_S):
        assert res["worst"] <= 1.0, (t_off, res)


def test_r3_recloses_a_battery_rule_8b_opened_only_below_the_clear_ratio() -> None:
    """Seed 230 as generated (loss at 126 s). Once rule 8b may open a battery R3 closed within
    the cap at once, R3 re-closed battery 3 one period after 8b opened it: on its diode its
    prediction was 0.83x (below rule 8c's 0.9), closed again 0.94x at once (the prediction
    moves with the current by I x R0's error, as the engage rule's re-close does), a 1.5 s
    hand-over cycle, 48 charge-FET changes per minute of hold. Rule 8c holds a battery 8b
    opened down to ``risk_clear_ratio`` (0.8), the engage rule's criterion for it: 33 (16
    while 8b waited ``R3_HOLD_S`` and left the window above open)."""
    res = run_case(draw(WINDOW_SEED), hook=True, open_=True, extra=HOLD_10)
    assert res["worst"] <= 1.0, res
    assert res["fet_changes_per_min"] <= 40.0, res


# Seed 2928 (five batteries, 46.5 A for 514 s): battery 0 stands on its charge diode (7.4 A,
# within the 10 A cap, never opened by rule 8b) while the trusted prediction with it engaged
# is 0.93x its limit at 333.5 s. Rule 8c's margin is the engage rule's 0.9: it stays on its
# diode then and is closed at 334 s at 0.80x predicted; a loss then pushes 0.785x into it. At
# rule 8b's 0.95 (mutant diode-hold-at-open-ratio) R3 closed it at 333.5 s, and a loss in that
# period pushed 0.981x (the prediction 5 % low, which the 0.95 leaves no room for): rule 8b
# cannot act on a battery before R3 has closed it, so since it may open one R3 closed within the
# cap at once (h28look), the period of the closure is what this margin still covers.
MARGIN_SEED = 2928
MARGIN_LOSSES_S = (333.5, 334.0)


def test_r3_closes_a_battery_held_on_its_diode_only_within_the_charge_limit_margin() -> None:
    """A loss in the period R3 closes a battery rule 8c held (within the cap, observer
    trusted, one rule 8b never opened) pushes at most ``charge_limit_margin`` (0.9) x its
    limit: 8c lets R3 close it only once its prediction is that far within the limit."""
    for t_off, res in _losses_at(MARGIN_SEED, MARGIN_LOSSES_S):
        assert res["worst"] <= 0.9, (t_off, res)
