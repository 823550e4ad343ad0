"""Campaigns on a real ``dask.distributed.LocalCluster`` (2 worker processes on loopback)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from packpilot import campaign as cp
from packpilot.campaign import schedule
from packpilot.config import ScenarioConfig, parse_config
from packpilot.errors import InputError
from tests.conftest import dual_pack

SPREAD = "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35"


@pytest.fixture(scope="module")
def cluster() -> Iterator[Any]:
    from distributed import LocalCluster

    cl = LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        host="127.0.0.1",
        dashboard_address=None,
    )
    try:
        yield cl
    finally:
        cl.close()


@pytest.fixture(scope="module")
def cfg() -> ScenarioConfig:
    # Two 6S batteries 2 V apart under a 20 A load, sequencing on: events and diode work vary.
    d = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0001},
        load={"kind": "current", "value": 20.0},
        duration_s=5.0,
    )
    d["controller"] = ["sequencing"]
    return parse_config(d)


def _results(table: pa.Table) -> pa.Table:
    """Everything but the (non-deterministic) wall time."""
    return table.drop_columns(["wall_time_s"])


def test_twenty_runs_on_a_local_cluster(
    cluster: Any, cfg: ScenarioConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv(cp.FAIL_ENV, "5")
    out = tmp_path / "a.parquet"
    rep = cp.run_campaign(
        cfg, 20, out, spreads=SPREAD, seed=11, scheduler=cluster.scheduler_address
    )
    table = pq.read_table(out)
    assert table.num_rows == 20 == rep.computed and rep.skipped == 0
    assert table.column("run").to_pylist() == list(range(20))
    assert set(table.column("seed").to_pylist()) == {11}
    params = np.column_stack([table.column(c).to_numpy() for c in cp.PARAM_COLUMNS])
    assert len({tuple(p) for p in params}) == 20
    assert np.unique(params[:, 3]).size == 20
    # The deliberately failing run is a row with its parameters and error, not a crash.
    status = table.column("status").to_pylist()
    assert status.count("error") == 1 == rep.failures and status[5] == "error"
    row5 = table.slice(5, 1).to_pylist()[0]
    assert "DeliberateFailure" in row5["error"] and row5["min_cell_v"] is None
    assert (
        row5["capacity_scale"] == cp.draw_run(cp.parse_spreads(SPREAD), 11, 5, 25.0).capacity_scale
    )
    ok = table.filter(pa.compute.equal(table.column("status"), "ok"))
    assert ok.column("error").null_count == 19
    # Event counts: 0 (not null) where an ok run never saw that kind; null for the failed run.
    events = [c for c in table.column_names if c.startswith("events_")]
    assert events and all(ok.column(c).null_count == 0 for c in events)
    assert all(row5[c] is None for c in events)
    # Outcomes follow the draws: peak cell temperature tracks the drawn ambient.
    assert np.all(
        np.abs(ok.column("max_temp_c").to_numpy() - ok.column("ambient_c").to_numpy()) < 3
    )
    assert {"final_soc_0", "final_soc_1", "events_StateChanged", "peak_string_current_a_1"} <= set(
        table.column_names
    )
    assert not (tmp_path / "a.parquet.parts").exists()
    assert rep.summary and {r["metric"] for r in rep.summary} >= {"min_cell_v", "joule_heat_j"}

    # Same seed again (on the cluster) -> identical results; a different batching on the
    # threaded scheduler -> identical too (a run's draw depends only on (seed, run)).
    again = cp.run_campaign(
        cfg, 20, tmp_path / "b.parquet", spreads=SPREAD, seed=11, client=_client(cluster)
    )
    assert _results(again.table).equals(_results(table))
    threaded = cp.run_campaign(
        cfg, 20, tmp_path / "c.parquet", spreads=SPREAD, seed=11, scheduler="threads", batch=3
    )
    assert _results(threaded.table).equals(_results(table))
    other = cp.run_campaign(
        cfg, 20, tmp_path / "d.parquet", spreads=SPREAD, seed=12, scheduler="threads"
    )
    assert not np.allclose(other.table.column("capacity_scale").to_numpy(), params[:, 0])
    assert other.failures == 1  # the env knob still names run 5


def _client(cluster: Any) -> Any:
    from distributed import Client

    return Client(cluster)


def test_resume_finishes_only_the_missing_runs(
    cluster: Any, cfg: ScenarioConfig, tmp_path: Path
) -> None:
    out = tmp_path / "r.parquet"
    addr = cluster.scheduler_address
    part = cp.run_campaign(
        cfg, 20, out, spreads=SPREAD, seed=3, scheduler=addr, limit=7, fail_runs=[2]
    )
    assert part.computed == 7 and pq.read_table(out).num_rows == 7
    rest = cp.run_campaign(
        cfg, 20, out, spreads=SPREAD, seed=3, scheduler=addr, resume=True, fail_runs=[2]
    )
    assert (rest.computed, rest.skipped) == (13, 7)
    full = cp.run_campaign(
        cfg, 20, tmp_path / "full.parquet", spreads=SPREAD, seed=3, scheduler=addr, fail_runs=[2]
    )
    assert _results(pq.read_table(out)).equals(_results(full.table))

    # A crash mid-campaign: consolidated file holds 0..19, parts of a later extension hold
    # a few more; drop one part as if it had never been written, then resume to 30.
    store = cp.ResultStore(out, cp.campaign_meta(cfg, cp.parse_spreads(SPREAD), 3))
    draws = cp.make_draws(cp.parse_spreads(SPREAD), 3, range(20, 26), 25.0)
    store.write_part(cp.run_batch(cfg, draws[:3]))
    lost = store.write_part(cp.run_batch(cfg, draws[3:]))
    lost.unlink()
    assert len(store.done_runs()) == 23
    ext = cp.run_campaign(
        cfg, 30, out, spreads=SPREAD, seed=3, scheduler=addr, resume=True, fail_runs=[2]
    )
    assert (ext.computed, ext.skipped) == (7, 23)
    final = pq.read_table(out)
    assert final.column("run").to_pylist() == list(range(30))
    assert final.column("status").to_pylist().count("error") == 1

    # Resuming with another seed or other spreads would mix two campaigns: refused.
    with pytest.raises(InputError, match="different seed"):
        cp.run_campaign(cfg, 30, out, spreads=SPREAD, seed=4, scheduler="sync", resume=True)
    with pytest.raises(InputError, match="different spreads"):
        cp.run_campaign(cfg, 30, out, spreads="r0=1%", seed=3, scheduler="sync", resume=True)


def test_default_local_cluster_path(cfg: ScenarioConfig, tmp_path: Path) -> None:
    """``scheduler="processes"`` builds (and closes) its own loopback LocalCluster."""
    rep = cp.run_campaign(
        cfg, 4, tmp_path / "p.parquet", spreads=SPREAD, seed=11, scheduler="processes", workers=2
    )
    assert rep.scheduler == "processes" and rep.table.num_rows == 4 and rep.failures == 0
    png = cp.plot_histograms(rep.table, tmp_path / "p.png")
    assert png is not None and png.stat().st_size > 5_000


def test_unreachable_scheduler_is_an_input_error(
    cfg: ScenarioConfig, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(schedule, "CONNECT_TIMEOUT_S", 1.0)
    with pytest.raises(InputError, match="cannot connect"):
        cp.run_campaign(cfg, 2, tmp_path / "u.parquet", scheduler="tcp://127.0.0.1:1")
