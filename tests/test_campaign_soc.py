"""A campaign's SOC accuracy columns (issue #28) on a real loopback Dask scheduler: computed from
the plant's SOC against the estimates, recomputed here from single runs' traces."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot import campaign as cp
from packpilot.campaign.soc_accuracy import EPS_S, SETTLE_S
from packpilot.config import ScenarioConfig, parse_config, read_toml
from packpilot.errors import ConfigError
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SPREAD = "capacity=5%,r0=10%,soc0=0.04,ambient_c=5:35"
RUNS = 5
DURATION_S = 420.0


def _scenario(soc0_error: float = 0.10, **sensors: Any) -> ScenarioConfig:
    """soc_observer_sensors (20-minute flight, 5 mV cell noise, current +1 % and +0.2 A) cut
    to 7 minutes, the BMS starting ``soc0_error`` wrong."""
    data: dict[str, Any] = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["sim"].update(duration_s=DURATION_S, progress=False)
    data["sensors"].update(soc0_error=soc0_error, **sensors)
    return parse_config(data, "soc_campaign_test")


def _from_trace(cfg: ScenarioConfig, draw: cp.Draw) -> dict[str, float]:
    """The run alone (``Runner``, the draw's overrides), its errors from its own trace: the
    plant's ``soc`` channel against the status ``soc_est`` (shown) and ``soc_fallback``."""
    res = Runner(cfg, progress=False, pack_overrides=draw.pack_overrides()).run()
    tr = res.trace
    late = tr.t_s >= SETTLE_S - EPS_S  # the step starting at 300 s (a sum of 0.1 s steps)
    truth = np.clip(tr.channel("soc")[late, 0], 0.0, 1.0)  # past empty: 0 % on any display
    out = {}
    for key, ch in (("soc_err", "soc_est"), ("soc_err_old", "soc_fallback")):
        est = np.array([float(row[0]) for row in tr.status[ch]])[late]
        err = est - truth
        out[f"{key}_rms_0"] = float(np.sqrt(np.mean(err**2)))
        out[f"{key}_max_0"] = float(np.max(np.abs(err)))
    out["steps"] = float(late.sum())
    raw = tr.channel("soc")[late, 0]
    out["outside_s"] = float(np.sum((raw < 0.0) | (raw > 1.0)) * cfg.sim.dt_s)
    return out


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Any:
    cfg = _scenario()
    out = tmp_path_factory.mktemp("soc") / "soc.parquet"
    rep = cp.run_campaign(cfg, RUNS, out, spreads=SPREAD, seed=4, scheduler="processes", workers=1)
    return cfg, rep


def test_soc_columns_are_true_against_estimated_soc_on_a_loopback_cluster(campaign: Any) -> None:
    """Every run's columns equal the errors recomputed from the run alone (its trace: truth
    vs shown SOC and vs the fallback, after 5 minutes): a metric computed from anything else
    (estimate against estimate, all steps, a lagged truth, the wrong estimator) fails here."""
    cfg, rep = campaign
    assert rep.scheduler == "processes" and rep.failures == 0
    rows = rep.table.to_pylist()
    assert [r["run"] for r in rows] == list(range(RUNS))
    draws = cp.make_draws(cp.parse_spreads(SPREAD), 4, range(RUNS), cfg.pack.ambient_c)
    for row, draw in zip(rows, draws, strict=True):
        want = _from_trace(cfg, draw)
        assert row["soc_err_steps"] == want["steps"] > 1000
        for k, v in want.items():
            if k not in ("steps", "outside_s"):
                assert row[k] == pytest.approx(v, rel=1e-9, abs=1e-12), (row["run"], k)
        assert row["soc_err_rms"] == row["soc_err_rms_0"]  # one battery: the worst is it


def test_both_estimators_start_wrong_and_only_the_observer_recovers(campaign: Any) -> None:
    """``[sensors] soc0_error = 0.1`` reached both estimators: today's (no rest in 7 minutes)
    is still ~10 % off after 5 minutes, the observer has converged; the spreads vary the runs
    and the per-run noise makes the observer's error differ between them."""
    _, rep = campaign
    rows = rep.table.to_pylist()
    for r in rows:
        assert 0.06 < r["soc_err_old_rms"] < 0.14, r
        assert r["soc_err_rms"] < 0.5 * r["soc_err_old_rms"], r
        assert r["soc_err_max"] >= r["soc_err_rms"]
    assert len({r["soc_err_rms"] for r in rows}) == RUNS
    assert len({r["capacity_scale"] for r in rows}) == RUNS


def test_a_run_reads_the_same_noise_alone_as_in_its_batch() -> None:
    """The noise of a run comes from its own key (seed, run): run 2 of a batch of three and run
    2 alone give the same row, and another run's key gives other noise."""
    cfg = _scenario(soc0_error=0.0)
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": 330.0})})
    draws = cp.make_draws(cp.parse_spreads("capacity=5%"), 9, range(3), cfg.pack.ambient_c)
    batch = cp.run_batch(cfg, draws)
    alone = cp.run_batch(cfg, [draws[2]])[0]
    keys = set(alone) - {"wall_time_s"}
    assert all(batch[2][k] == alone[k] for k in keys), [k for k in keys if batch[2][k] != alone[k]]
    twin = cp.Draw(run=3, seed=9, capacity_scale=draws[2].capacity_scale)
    other = cp.run_batch(cfg, [twin])[0]
    assert other["soc_err_rms"] != alone["soc_err_rms"]
    assert not math.isnan(alone["soc_err_rms"])


def test_past_empty_counts_as_zero_and_its_time_is_reported() -> None:
    """A battery flown past empty (nothing protects it; the plant's SOC goes below 0): the
    error is against 0 %, what any display shows, and the time past empty is its own column."""
    cfg = _scenario()
    draw = cp.Draw(run=0, seed=4, soc0_offset=-0.72)
    row = cp.run_batch(cfg, [draw])[0]
    want = _from_trace(cfg, draw)
    assert want["outside_s"] > 30.0
    assert row["soc_truth_outside_s"] == pytest.approx(want["outside_s"], abs=1e-6)
    for k in ("soc_err_rms_0", "soc_err_max_0", "soc_err_old_rms_0", "soc_err_old_max_0"):
        assert row[k] == pytest.approx(want[k], rel=1e-9, abs=1e-12), k


@pytest.mark.parametrize("bad", [-0.1, 0.6, float("nan")])
def test_soc0_error_is_validated_naming_the_field(bad: float) -> None:
    with pytest.raises(ConfigError, match=r"sensors\.soc0_error"):
        _scenario(soc0_error=bad)
