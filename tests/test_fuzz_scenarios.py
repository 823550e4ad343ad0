"""Issue #26 §3: scenario mutations from a fuzzer built on the schema, not on the examples
(``tests/scenario_fuzz.py``). CI runs a seeded few hundred (load, validate and build the BMS,
no run; a sample also simulates 0.2 s through the CLI); ``benchmarks/fuzz_scenarios.py`` runs
the 2,000 of the acceptance and writes its figures to benchmarks/RESULTS.md."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.scenario_fuzz import PHYSICAL, Tally, out_of_range, run_case

CI_CASES = 300
SIMULATE_EVERY = 8
"""Every 8th accepted case also runs (about 5 short simulations)."""


def test_fuzzed_scenarios_are_refused_in_one_line_or_within_physical_ranges(
    tmp_path: Path,
) -> None:
    tally = Tally()
    for seed in range(CI_CASES):
        run_case(tmp_path, seed, tally, SIMULATE_EVERY)
    assert tally.cases == CI_CASES
    assert tally.simulated >= 3, tally
    assert not tally.tracebacks, tally.tracebacks[:5]
    assert not tally.hangs, tally.hangs[:5]
    assert not tally.bad_errors, tally.bad_errors[:5]
    assert not tally.out_of_range, tally.out_of_range[:5]
    # the mix is meaningful: both outcomes occur often (a fuzzer that only ever produced
    # unparseable files would pass the asserts above and test nothing)
    assert tally.accepted >= CI_CASES // 20 and tally.refused >= CI_CASES // 2, tally


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [("sequencing", "i_rev", 1e300), ("charger", "current_a", 1e308), ("soc", "blend", 2.0)],
)
def test_the_range_check_sees_a_threshold_outside_its_range(
    section: str, key: str, value: float
) -> None:
    """The fuzzer's own check is not vacuous: a dumped config with one threshold out of its
    physical range is reported."""
    dumped = {section: {key: value}}
    assert f"{section}.{key}" in PHYSICAL
    (bad,) = out_of_range(dumped)
    assert bad.startswith(f"{section}.{key} = ")
