"""Peak memory of reading a long run back (issue #26 §3; the review measured 1.3 GB for a
1-day run and 8.2 GB for 7 days): a synthetic recording of ``--days`` of a two-battery pack at
0.1 s periods (six series groups, a handful of status channels), written row by row with the
telemetry writer (no simulation), then ``packpilot report`` on it in a child process whose
peak RSS (``ru_maxrss``) is the figure.

    PYTHONPATH=src python benchmarks/bench_report_memory.py --days 1 [--keep DIR]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DT_S = 0.1


def make_recording(path: Path, days: float) -> int:
    """``days`` of samples with plausible, slowly varying values; the number of steps."""
    from packpilot.contract.record import BATTERY_CHANNELS, StepSample
    from packpilot.io.telemetry import SQLiteRecorder

    n = int(days * 86_400 / DT_S)
    n_c = len(BATTERY_CHANNELS)
    rng = np.random.default_rng(0)
    with SQLiteRecorder(path, flush_every=5000) as rec:
        rec.start({"pack": {"name": "synthetic"}, "sim": {"dt_s": DT_S}}, ["A", "B"])
        for k in range(n):
            t = k * DT_S
            bat = np.empty((2, n_c))
            bat[:] = 3.7 + 0.3 * math.sin(t / 3600.0) + rng.normal(0, 0.001, (2, n_c))
            grp = np.full((2, 6), 3.7)
            status = {"seq_state": [k // 36_000 % 3, 1], "seq_mode": ["discharge", "discharge"]}
            rec.record(StepSample(k, t, 22.2, 10.0, 10.0, 0.0, 0.0, bat, grp, status))
        rec.finish({"steps": n})
    return n


def report_peak_mb(db: Path) -> tuple[float, float, int]:
    """(peak RSS of ``packpilot report`` in MB, its wall time in s, its exit code)."""
    out = db.with_suffix(".html")
    t0 = time.monotonic()
    code = subprocess.call(
        [sys.executable, "-m", "packpilot.cli", "report", str(db), "--out", str(out)],
        env={**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true"},
    )
    wall = time.monotonic() - t0
    return resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, wall, code


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, default=None, help="write the recording here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.keep or Path(tmp)
        db = folder / f"synthetic_{args.days:g}d.sqlite"
        t0 = time.monotonic()
        n = make_recording(db, args.days)
        made = time.monotonic() - t0
        size = db.stat().st_size / 1e6
        peak, wall, code = report_peak_mb(db)
        print(f"| {args.days:g} days | {n:,} steps | {size:.0f} MB file, written in {made:.0f} s "
              f"| report peak RSS {peak:.0f} MB | {wall:.0f} s | exit {code} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
