"""Peak memory of reading a long run back (issue #26 §3; the review measured 1.3 GB for a
1-day run and 8.2 GB for 7 days, the dashboard 0.93 GB for 1 day; goal: <= 1 GB whatever the
run's length): a synthetic recording of ``--days`` of a two-battery pack at 0.1 s periods (six
series groups, a handful of status channels), written row by row with the telemetry writer (no
simulation), then, each in its own child process whose peak RSS (``wait4``'s ``ru_maxrss``) is
the figure:

- ``packpilot report`` on it;
- ``packpilot dashboard`` on it, serving the run's page and API (``/``, ``/api/status``,
  ``/api/samples``, ``/api/events``, ``/api/at`` at 20 times across the run), then stopped.

    PYTHONPATH=src python benchmarks/bench_report_memory.py --days 1 [--keep DIR | --db FILE]

``--db`` reuses a recording made before (``--keep``): a 7-day one takes ~8 min to write.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

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


def _env() -> dict[str, str]:
    return {**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true"}


def _wait_peak(proc: subprocess.Popen[bytes]) -> tuple[int, float]:
    """(exit code, peak RSS in MB) of one child, by ``wait4`` (not the max over children)."""
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    return proc.returncode, usage.ru_maxrss / 1024


def report_peak_mb(db: Path) -> tuple[float, float, int]:
    """(peak RSS of ``packpilot report`` in MB, its wall time in s, its exit code)."""
    out = db.with_suffix(".html")
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "packpilot.cli", "report", str(db), "--out", str(out)], env=_env()
    )
    code, peak = _wait_peak(proc)
    return peak, time.monotonic() - t0, code


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _get(url: str) -> bytes:
    with urllib.request.urlopen(url, timeout=60) as r:  # 127.0.0.1 only
        return bytes(r.read())


def dashboard_peak_mb(db: Path, ready_s: float = 3600.0) -> tuple[float, float, int, int]:
    """(peak RSS of ``packpilot dashboard DB`` in MB after serving the run's pages, the wall
    time until it served them, its exit code, bytes served)."""
    port = _free_port()
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [sys.executable, "-m", "packpilot.cli", "dashboard", str(db), "--port", str(port)],
        env=_env(),
        stderr=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"
    served = 0
    try:
        while True:  # the recording is read before the server listens
            if proc.poll() is not None or time.monotonic() - t0 > ready_s:
                raise RuntimeError(f"dashboard exited or never listened ({proc.returncode})")
            try:
                status: dict[str, Any] = json.loads(_get(f"{base}/api/status"))
                break
            except OSError:
                time.sleep(0.5)
        t_end = float(status.get("t_s") or status.get("duration_s") or 0.0)
        for path in ("/", "/api/samples", "/api/events", "/api/status"):
            served += len(_get(base + path))
        for k in range(20):
            served += len(_get(f"{base}/api/at?t_s={t_end * k / 19:.3f}"))
        wall = time.monotonic() - t0
    finally:
        proc.send_signal(signal.SIGINT)
    code, peak = _wait_peak(proc)
    return peak, wall, code, served


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=1.0)
    ap.add_argument("--keep", type=Path, default=None, help="write the recording here")
    ap.add_argument("--db", type=Path, default=None, help="measure this recording instead")
    ap.add_argument("--no-dashboard", action="store_true", help="measure the report only")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        if args.db is not None:
            db, n, made = args.db, -1, 0.0
        else:
            folder = args.keep or Path(tmp)
            db = folder / f"synthetic_{args.days:g}d.sqlite"
            t0 = time.monotonic()
            n = make_recording(db, args.days)
            made = time.monotonic() - t0
        size = db.stat().st_size / 1e6
        peak, wall, code = report_peak_mb(db)
        print(f"| {db.name} | {n:,} steps | {size:.0f} MB file, written in {made:.0f} s "
              f"| report peak RSS {peak:.0f} MB | {wall:.0f} s | exit {code} |",
              flush=True)  # fmt: skip
        if not args.no_dashboard:
            d_peak, d_wall, d_code, served = dashboard_peak_mb(db)
            print(f"| {db.name} | dashboard peak RSS {d_peak:.0f} MB | pages served after "
                  f"{d_wall:.0f} s ({served / 1e3:.0f} kB) | exit {d_code} |",
                  flush=True)  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
