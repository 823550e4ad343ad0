"""Campaign building blocks without a cluster: spread syntax, draws, rows, failure knob."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot import campaign as cp
from packpilot.config import parse_config
from packpilot.errors import InputError
from tests.budget import budget
from tests.conftest import dual_pack


def test_spread_forms() -> None:
    sp = cp.parse_spreads(" capacity=5%, r0=0.1 ,soc0=+-3%,ambient_c=-10:35 ")
    assert sp["capacity"] == cp.Spread("capacity", "normal", 0.05)
    assert sp["r0"] == cp.Spread("r0", "normal", 0.1)
    assert sp["soc0"] == cp.Spread("soc0", "uniform", -0.03, 0.03, relative=True)
    assert sp["ambient_c"] == cp.Spread("ambient_c", "uniform", -10.0, 35.0)
    assert cp.parse_spreads(None) == {} == cp.parse_spreads("")
    assert cp.parse_spreads("capacity=90%:110%")["capacity"] == cp.Spread(
        "capacity", "uniform", 0.9, 1.1
    )


@pytest.mark.parametrize(
    ("text", "token", "why"),
    [
        ("capacity=5x", "capacity=5x", "not a number"),
        ("capacity=5%,volume=3", "volume=3", "unknown parameter"),
        ("r0", "r0", "expected name=value"),
        ("soc0=", "soc0=", "missing value"),
        ("ambient_c=10%", "ambient_c=10%", "not a percentage"),
        ("ambient_c=35:-10", "ambient_c=35:-10", "lo must be <= hi"),
        ("capacity=0:2", "capacity=0:2", "within"),
        ("r0=-5%", "r0=-5%", "sigma must be >= 0"),
        ("capacity=1%,capacity=2%", "capacity=2%", "given twice"),
        ("ambient_c=nan", "ambient_c=nan", "not a number"),
    ],
)
def test_bad_spread_names_the_token(text: str, token: str, why: str) -> None:
    with pytest.raises(InputError) as err:
        cp.parse_spreads(text)
    msg = str(err.value)
    assert repr(token) in msg and why in msg
    assert "\n" not in msg


def test_draws_depend_only_on_seed_and_run_index() -> None:
    sp = cp.parse_spreads("capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35")
    all_at_once = cp.make_draws(sp, 7, range(50), 25.0)
    one_by_one = [cp.draw_run(sp, 7, i, 25.0) for i in reversed(range(50))][::-1]
    assert all_at_once == one_by_one
    values = np.array(
        [[d.capacity_scale, d.r0_scale, d.soc0_offset, d.ambient_c] for d in one_by_one]
    )
    assert len({tuple(v) for v in values}) == 50
    assert cp.draw_run(sp, 8, 3, 25.0) != all_at_once[3]
    # Sample statistics match the requested spreads (loose bounds, 2000 draws).
    many = np.array(
        [
            [d.capacity_scale, d.r0_scale, d.soc0_offset, d.ambient_c]
            for d in cp.make_draws(sp, 1, range(2000), 25.0)
        ]
    )
    assert abs(many[:, 0].std() - 0.05) < 0.005 and abs(many[:, 0].mean() - 1.0) < 0.005
    assert abs(many[:, 1].std() - 0.10) < 0.01
    assert abs(many[:, 2].std() - 0.05) < 0.005
    assert many[:, 3].min() >= -10 and many[:, 3].max() <= 35 and np.ptp(many[:, 3]) > 40


def test_unspread_parameters_stay_nominal() -> None:
    d = cp.draw_run(cp.parse_spreads("r0=10%"), 0, 4, 12.5)
    assert (d.capacity_scale, d.soc0_offset, d.ambient_c) == (1.0, 0.0, 12.5)
    assert d.r0_scale != 1.0
    rel = cp.draw_run(cp.parse_spreads("ambient_c=+-2"), 0, 4, 12.5)
    assert 10.5 <= rel.ambient_c <= 14.5


@budget(200)
@given(
    seed=st.integers(0, 2**32),
    run=st.integers(0, 10**6),
    subset=st.sets(st.sampled_from(["capacity=5%", "r0=20%", "soc0=0.3", "ambient_c=-40:60"])),
)
def test_a_spread_never_shifts_another_spreads_draw(seed: int, run: int, subset: set[str]) -> None:
    full = cp.draw_run(
        cp.parse_spreads("capacity=5%,r0=20%,soc0=0.3,ambient_c=-40:60"), seed, run, 25.0
    )
    part = cp.draw_run(cp.parse_spreads(",".join(sorted(subset))), seed, run, 25.0)
    for name, col in (("capacity", "capacity_scale"), ("r0", "r0_scale")):
        if any(s.startswith(name + "=") for s in subset):
            assert getattr(part, col) == getattr(full, col)
    # Physical clipping always holds.
    assert full.capacity_scale >= 0.05 and full.r0_scale >= 0.05
    assert -1 <= full.soc0_offset <= 1 and -60 <= full.ambient_c <= 80


def test_fail_knob_from_environment() -> None:
    assert cp.fail_runs_from_env({cp.FAIL_ENV: "3, 7"}) == {3, 7}
    assert cp.fail_runs_from_env({}) == frozenset()
    with pytest.raises(InputError, match=cp.FAIL_ENV):
        cp.fail_runs_from_env({cp.FAIL_ENV: "3;7"})


def test_flatten_metrics() -> None:
    flat = cp.flatten_metrics(
        {
            "wall_time_s": 1.0,
            "min_cell_v": 3.1,
            "steps": 10,
            "peak_string_current_a": [1.5, -2.0],
            "events": {"StateChanged": 2, "DiodeBypassed": 1},
            "battery_names": ["A", "B"],
        }
    )
    assert flat == {
        "min_cell_v": 3.1,
        "steps": 10,
        "peak_string_current_a_0": 1.5,
        "peak_string_current_a_1": -2.0,
        "events_DiodeBypassed": 1,
        "events_StateChanged": 2,
    }


def _cfg() -> Any:
    d = dual_pack(load={"kind": "current", "value": 20.0}, duration_s=3.0)
    return parse_config(d)


def test_run_one_applies_the_draw_through_the_plant() -> None:
    cfg = _cfg()
    cold = cp.run_one(cfg, cp.Draw(run=0, seed=0, ambient_c=-5.0, capacity_scale=0.5))
    warm = cp.run_one(cfg, cp.Draw(run=1, seed=0, ambient_c=30.0, capacity_scale=0.5))
    big = cp.run_one(cfg, cp.Draw(run=2, seed=0, ambient_c=30.0, capacity_scale=2.0))
    huge = cp.run_one(cfg, cp.Draw(run=3, seed=0, ambient_c=30.0, capacity_scale=1000.0))
    low = cp.run_one(cfg, cp.Draw(run=4, seed=0, ambient_c=30.0, soc0_offset=-0.2))
    assert {r["status"] for r in (cold, warm, big, huge, low)} == {"ok"}
    assert cold["max_temp_c"] < 0 < 25 < warm["max_temp_c"]
    # The same charge out of a 4x smaller cell moves its SOC 4x further.
    drop_small = huge["final_soc_0"] - warm["final_soc_0"]
    drop_big = huge["final_soc_0"] - big["final_soc_0"]
    assert 3.5 < drop_small / drop_big < 4.5
    assert low["final_soc_0"] == pytest.approx(huge["final_soc_0"] - 0.2, abs=0.01)
    assert cold["capacity_scale"] == 0.5 and cold["run"] == 0


def test_run_one_records_exceptions_and_non_finite_metrics() -> None:
    cfg = _cfg()
    row = cp.run_batch(cfg, [cp.Draw(run=4, seed=0)], fail_runs=frozenset({4}))[0]
    assert row["status"] == "error" and "DeliberateFailure" in row["error"]
    assert row["run"] == 4 and row["wall_time_s"] >= 0

    # A draw that drives the plant non-finite (NaN ambient) is an error row naming the metric.
    row = cp.run_one(cfg, cp.Draw(run=5, seed=0, ambient_c=math.nan))
    assert row["status"] == "error" and "max_temp_c" in row["error"]
    assert math.isnan(row["max_temp_c"]) and row["run"] == 5


def test_auto_scheduler_picks_processes_only_for_real_work() -> None:
    cfg = _cfg()  # 30 steps per run
    assert cp.choose_scheduler(cfg, 20, 2) == "sync"
    assert cp.choose_scheduler(cfg, 100_000, 2) == "processes"
    assert cp.choose_scheduler(cfg, 100_000, 1) == "sync"
