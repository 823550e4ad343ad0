"""The Hypothesis budgets scale with the profile (#18 §2): a soak really runs more examples."""

from __future__ import annotations

from tests.budget import CI_MIN, NIGHTLY_MIN, scaled


def test_ci_keeps_the_written_budget() -> None:
    assert scaled(60, "ci") == 60 and scaled(CI_MIN, "ci") == CI_MIN


def test_nightly_runs_at_least_ten_thousand_and_scales_the_larger_ones() -> None:
    assert scaled(8, "nightly") == NIGHTLY_MIN >= 10_000
    assert scaled(500, "nightly") > scaled(200, "nightly") >= NIGHTLY_MIN


def test_dev_runs_fewer_but_never_none() -> None:
    assert scaled(200, "dev") == 20 and scaled(8, "dev") == 5
