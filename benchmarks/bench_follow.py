"""How far behind a dashboard attached to a running `packpilot run` is (issue #16 §1).

A writer thread records one sample every ``--period`` s through the real ``SQLiteRecorder``
(default commit: every 1 s), as ``packpilot run --db`` does; the dashboard's ``Recording``
follows the file, polled every 0.5 s as its ``Follower`` does. A sample's lag is the wall time
it is first seen by the reader minus the wall time it was recorded. Reported: p50 / p99 / max
lag and the samples followed (all of them must arrive, in order).

Run: ``python benchmarks/bench_follow.py [--seconds 30] [--period 0.01]``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from packpilot.contract.record import BATTERY_CHANNELS, StepSample
from packpilot.io.telemetry import SQLiteRecorder
from packpilot.web.recorded import POLL_S, Recording


def _sample(k: int, period_s: float) -> StepSample:
    return StepSample(
        step=k, t_s=period_s * k, bus_v=22.0, load_demand_a=5.0, load_a=5.0, charger_v=0.0,
        charger_a=0.0, battery=np.full((2, len(BATTERY_CHANNELS)), 3.7),
        group_v=np.full((2, 6), 3.7), status={"mode": ("discharge", "discharge")},
    )  # fmt: skip


class Writer(threading.Thread):
    """Records a sample every period on its own clock until stopped (SQLite: its own thread)."""

    def __init__(self, db: Path, period_s: float) -> None:
        super().__init__(daemon=True)
        self.db, self.period_s = db, period_s
        self.stamps: dict[int, float] = {}
        self.ready, self.stop = threading.Event(), threading.Event()

    def run(self) -> None:
        rec = SQLiteRecorder(self.db)
        rec.start({"pack": {"name": "follow"}, "sim": {"dt_s": self.period_s}}, ["A", "B"])
        k, due = 0, time.monotonic()
        while not self.stop.is_set():
            self.stamps[k] = time.monotonic()
            rec.record(_sample(k, self.period_s))
            if k == 0:
                rec.flush()
                self.ready.set()
            k += 1
            due += self.period_s
            time.sleep(max(0.0, due - time.monotonic()))
        rec.finish({})
        rec.close()


def measure(seconds: float, period_s: float) -> dict[str, float]:
    db = Path(tempfile.mkdtemp()) / "follow.sqlite"
    w = Writer(db, period_s)
    w.start()
    w.ready.wait(10.0)
    rec = Recording(db)
    seen, lags = rec.n_samples, []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        time.sleep(POLL_S)
        rec.poll()
        now = time.monotonic()
        lags += [now - w.stamps[k] for k in range(seen, rec.n_samples)]
        seen = rec.n_samples
    w.stop.set()
    w.join()
    ordered = [rec.sample(k).step for k in range(rec.n_samples)] == list(range(rec.n_samples))
    lags.sort()
    return {
        "period_s": period_s,
        "samples_followed": len(lags),
        "in_order": float(ordered),
        "lag_p50_s": round(statistics.median(lags), 3),
        "lag_p99_s": round(lags[int(0.99 * (len(lags) - 1))], 3),
        "lag_max_s": round(lags[-1], 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--period", type=float, nargs="+", default=[0.1, 0.01])
    args = ap.parse_args()
    for p in args.period:
        print(json.dumps(measure(args.seconds, p)), flush=True)


if __name__ == "__main__":
    main()
