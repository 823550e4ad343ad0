"""Campaign throughput: runs/s on 1 vs 2 workers, and 1,000 one-hour missions extrapolated.

The issue's target is 1,000 one-hour missions at a 0.1 s step (36 M pack-steps) in <= 5 min on
the 2-core machine. The closed loop (sensors -> controller -> plant -> sample) costs a few
hundred microseconds per step of a 12-cell pack, almost all of it Python/NumPy call overhead,
so per-pack runs cannot get there; the last rows measure the plant alone stepping many packs
in one NumPy call (``Pack(cfg, n_packs=P)``) to show what vectorizing the whole loop over packs
would buy. Wall-clock figures depend on what else the machine runs: the load average is
reported. Run: ``python benchmarks/bench_campaign.py``.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

MISSION_S = 3600.0
DT_S = 0.1
MISSIONS = 1000
TARGET_S = 300.0
SPREAD = "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35"


def _cfg(duration_s: float) -> Any:
    from packpilot.config import parse_config

    # Two 6S batteries 2 V apart behind MOSFET pairs, 20 A load, parallel-discharge
    # sequencing: the spec's example, on the always-present ecm_example cell set.
    return parse_config(
        {
            "controller": ["sequencing"],
            "pack": {
                "cell": "ecm_example",
                "switch": {"kind": "mosfet_pair", "on_ohm": 0.0001},
                "batteries": [
                    {"name": "A", "cells_per_group": 6, "ocv0_v": 24.2, "resistance_ohm": 0.02},
                    {"name": "B", "cells_per_group": 6, "ocv0_v": 22.2, "resistance_ohm": 0.02},
                ],
            },
            "load": {"kind": "current", "value": 20.0},
            "sim": {"dt_s": DT_S, "duration_s": duration_s, "progress": False},
        }
    )


def _timed_campaign(cfg: Any, runs: int, repeat: int = 2, **kw: Any) -> float:
    """Best wall time of ``repeat`` campaigns (the machine is shared: take the quiet one)."""
    from packpilot.sim.campaign import run_campaign

    best = math.inf
    for _ in range(repeat):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            rep = run_campaign(cfg, runs, Path(tmp) / "c.parquet", spreads=SPREAD, **kw)
            best = min(best, time.perf_counter() - t0)
        assert rep.table.num_rows == runs and rep.failures == 0, rep.failures
    return best


def _cluster(n: int) -> tuple[Any, Any, float]:
    """A warmed LocalCluster: imports and numba caches loaded in every worker."""
    import importlib

    from packpilot.sim.campaign import QUIET_WORKER_CONFIG, draw_run, run_batch

    dist: Any = importlib.import_module("distributed")  # untyped for mypy --strict
    dask: Any = importlib.import_module("dask")
    t0 = time.perf_counter()
    with dask.config.set(QUIET_WORKER_CONFIG):  # as the campaign's own LocalCluster
        cluster = dist.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        )
    client = dist.Client(cluster)
    warm = _cfg(1.0)
    futs = [
        client.submit(run_batch, warm, [draw_run({}, 0, i, 25.0)], pure=False) for i in range(n)
    ]
    client.gather(futs)
    return cluster, client, time.perf_counter() - t0


def _plant_us_per_pack_step(n_packs: int, steps: int = 300) -> float:
    from packpilot.model.pack import Pack

    pack = Pack(_cfg(60.0), n_packs=n_packs)
    load = np.full(n_packs, 20.0)
    pack.step(DT_S, "current", load)
    t0 = time.process_time()  # CPU time: robust to other load on the machine
    for _ in range(steps):
        pack.step(DT_S, "current", load)
    return (time.process_time() - t0) / steps / n_packs * 1e6


def run() -> list[dict[str, Any]]:
    from packpilot.sim.campaign import Draw, run_one

    load0 = os.getloadavg()[0]
    short_s = 60.0
    steps_short = round(short_s / DT_S)
    steps_hour = round(MISSION_S / DT_S)
    cfg = _cfg(short_s)
    rows: list[dict[str, Any]] = []

    def row(case: str, figure: float, unit: str, note: str = "") -> None:
        rows.append({"case": case, "figure": figure, "unit": unit, "note": note})

    run_one(cfg, Draw(0, 0))  # numba caches, imports
    cpu0 = time.process_time()
    wall_sync = _timed_campaign(cfg, 24, scheduler="sync")
    short_cpu_us = (time.process_time() - cpu0) / (2 * 24 * steps_short) * 1e6
    sync_rate = 24 / wall_sync
    row("in-process (sync), 60 s runs", sync_rate, "runs/s", "no Dask, one core")
    wall_thr = _timed_campaign(cfg, 24, scheduler="threads", workers=2)
    row("threaded scheduler, 2 threads", 24 / wall_thr, "runs/s", "GIL ping-pong: slower than 1")

    rates: dict[int, float] = {}
    for n, runs in ((1, 24), (2, 48)):
        cluster, client, start_s = _cluster(n)
        try:
            wall = _timed_campaign(cfg, runs, client=client, batch=3)
        finally:
            client.close()
            cluster.close()
        rates[n] = runs / wall
        row(f"LocalCluster {n} worker(s), 60 s runs", rates[n], "runs/s", f"start {start_s:.1f} s")
    busy = max(load0, os.getloadavg()[0]) > 1.0
    note = "BUSY MACHINE: not a speed-up figure" if busy else "wall clock, cluster warm"
    row("speed-up 1 -> 2 workers", rates[2] / rates[1], "x", note)

    # One real one-hour mission (36,000 steps) in-process: does the per-step cost hold?
    cpu0, t0 = time.process_time(), time.perf_counter()
    mission = run_one(_cfg(MISSION_S), Draw(0, 0))
    mission_s = time.perf_counter() - t0
    long_cpu_us = (time.process_time() - cpu0) / steps_hour * 1e6
    assert mission["status"] == "ok", mission["error"]
    row("one 1-hour mission, 0.1 s step, in-process", mission_s, "s", f"{steps_hour} steps")
    row(
        "closed-loop step (12 cells), CPU time", long_cpu_us, "us", f"60 s runs: {short_cpu_us:.0f}"
    )
    ideal = MISSIONS * steps_hour * long_cpu_us * 1e-6 / 2
    verdict = "met" if ideal <= TARGET_S else f"{ideal / TARGET_S:.0f}x over"
    row("1,000 one-hour missions, 2 cores, CPU cost / 2", ideal, "s", f"target 300 s: {verdict}")
    measured = MISSIONS * steps_hour / (rates[2] * steps_short) * long_cpu_us / short_cpu_us
    row("1,000 one-hour missions at the measured 2-worker rate", measured, "s", "wall clock")
    budget_us = TARGET_S * 2 / (MISSIONS * steps_hour) * 1e6
    row("per pack-step budget for the target", budget_us, "us", "2 cores, 36 M pack-steps")
    for p in (1, 64, 512):
        us = _plant_us_per_pack_step(p)
        row(f"plant only, {p} packs per NumPy step", us, "us/pack-step", "no controller/sensors")
    row(
        "1,000 missions, plant vectorized x512, no controllers (lower bound)",
        MISSIONS * steps_hour * rows[-1]["figure"] * 1e-6 / 2,
        "s",
        "controllers + sensors must vectorize too",
    )
    row("load average at start", load0, "", f"end {os.getloadavg()[0]:.2f}; 2 cores")
    assert all(math.isfinite(r["figure"]) for r in rows)
    return rows


if __name__ == "__main__":
    for r in run():
        print(f"{r['case']:<66} {r['figure']:12.4g} {r['unit']:<13} {r['note']}")
