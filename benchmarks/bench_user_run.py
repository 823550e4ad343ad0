"""The user's run against the core (issue #25 §4): ``packpilot simulate uav_mission`` per step.

What a user pays per simulated step is not ``ClosedLoop.step``: the command also records the
trace (every step), renders it, computes the verdict, and with ``--db`` streams every step to
SQLite. Measured **at the margin**, so start-up (import, build, loading the kernels) cancels:
the child CPU time (``resource`` usage of the finished child process) of ``packpilot simulate
uav_mission --duration 1500`` minus that of ``--duration 300``, divided by the 6,000 steps
between them; plain (trace only) and with ``--db``. Beside them, in the same run and in
alternation: ``ClosedLoop.step`` alone over the same 6,000 steps (in process) and PyBaMM's
Thevenin ``Simulation.step`` (as ``bench_core``). Medians of repeats; the kernels must be in
the cache already (a warm-up child runs first).

Run: ``python benchmarks/bench_user_run.py [--repeat N]``; ``run()`` for ``make bench``.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:
    sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")

SHORT_S, LONG_S = 300.0, 1500.0
GOAL_TRACE_X = 20.0
GOAL_DB_X = 15.0


def _env() -> dict[str, str]:
    # PACKPILOT_START=compiled: the figure is the user's steady state (every run after the
    # first on a machine). Without it a child that finds no cached kernels runs interpreted and
    # starts the background compile (coldstart.py), so the warm-up and the next repeats ran
    # interpreted, 2.3 ms/step (2026-11-28: medians of 3 ranged 33.5-2400 us).
    env = dict(os.environ, PYBAMM_DISABLE_TELEMETRY="true", PACKPILOT_START="compiled")
    extra = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), *extra])
    return env


def child_cpu_s(duration_s: float, db: bool) -> float:
    """CPU seconds (user + system) of one ``packpilot simulate uav_mission`` process."""
    with tempfile.TemporaryDirectory(prefix="packpilot-user-run-") as tmp:
        cmd = [sys.executable, "-m", "packpilot.cli", "simulate", "uav_mission",
               "--duration", str(duration_s), "--json", "--no-progress"]  # fmt: skip
        if db:
            cmd += ["--db", str(Path(tmp) / "run.sqlite")]
        proc = subprocess.Popen(cmd, env=_env(), cwd=ROOT, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE)  # fmt: skip
        _, status, usage = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        err = proc.stderr.read().decode() if proc.stderr else ""
        if proc.returncode != 0:
            raise RuntimeError(f"simulate failed ({proc.returncode}): {err[-2000:]}")
        return usage.ru_utime + usage.ru_stime


def loop_cpu_us() -> float:
    """CPU per ``ClosedLoop.step`` of uav_mission between t = 300 s and t = 1500 s."""
    from bench_core import _cfg, _loop

    cfg = _cfg()
    dt = cfg.sim.dt_s
    k0, k1 = round(SHORT_S / dt), round(LONG_S / dt)
    loop = _loop(cfg)
    step = loop.step
    for k in range(k0):
        step(k, dt)
    t0 = time.process_time()
    for k in range(k0, k1):
        step(k, dt)
    us = (time.process_time() - t0) / (k1 - k0) * 1e6
    loop.close()
    return us


def margin(repeat: int = 3) -> dict[str, Any]:
    from bench_core import _pybamm_cpu_us

    n = round((LONG_S - SHORT_S) / 0.2)
    child_cpu_s(1.0, False)  # warm-up: the kernels into the cache, if they were not
    _pybamm_cpu_us(20)
    loop_cpu_us()
    rows: dict[str, list[float]] = {"trace": [], "db": [], "loop": [], "pybamm": []}
    for _ in range(repeat):  # alternate, so every figure sees the same machine
        rows["pybamm"].append(_pybamm_cpu_us())
        for key, db in (("trace", False), ("db", True)):
            short = child_cpu_s(SHORT_S, db)
            long = child_cpu_s(LONG_S, db)
            rows[key].append((long - short) / n * 1e6)
        rows["loop"].append(loop_cpu_us())
    med = {k: statistics.median(v) for k, v in rows.items()}
    return {"median_us": med, "all_us": rows}


def run() -> list[dict[str, Any]]:
    r = margin()
    med, every = r["median_us"], r["all_us"]
    pyb = med["pybamm"]

    def rng(key: str) -> str:
        return f"median of {len(every[key])} ({min(every[key]):.1f}-{max(every[key]):.1f})"

    return [
        {
            "case": "packpilot simulate uav_mission (trace), CPU per step at the margin",
            "figure": med["trace"],
            "unit": "us",
            "goal": f">= {GOAL_TRACE_X:g}x faster than PyBaMM step",
            "verdict": "met" if pyb / med["trace"] >= GOAL_TRACE_X else "MISSED",
            "reference": f"PyBaMM Simulation.step {pyb:.0f} us CPU: {pyb / med['trace']:.1f}x",
            "note": f"(--duration {LONG_S:g} minus {SHORT_S:g}) / 6,000 steps; {rng('trace')}",
        },
        {
            "case": "packpilot simulate uav_mission --db, CPU per step at the margin",
            "figure": med["db"],
            "unit": "us",
            "goal": f">= {GOAL_DB_X:g}x faster than PyBaMM step",
            "verdict": "met" if pyb / med["db"] >= GOAL_DB_X else "MISSED",
            "reference": f"PyBaMM Simulation.step {pyb:.0f} us CPU: {pyb / med['db']:.1f}x",
            "note": rng("db"),
        },
        {
            "case": "ClosedLoop.step alone, same 6,000 steps, CPU per step",
            "figure": med["loop"],
            "unit": "us",
            "note": f"{rng('loop')}; the command costs {med['trace'] / med['loop']:.2f}x "
            f"(trace) / {med['db'] / med['loop']:.2f}x (--db) of it",
        },
        {
            "case": "PyBaMM Thevenin Simulation.step (1 cell, dt 0.1 s), CPU, same run",
            "figure": pyb,
            "unit": "us",
            "note": rng("pybamm"),
        },
    ]


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    repeat = int(sys.argv[sys.argv.index("--repeat") + 1]) if "--repeat" in sys.argv else 3
    for row in run() if repeat == 3 else [margin(repeat)]:
        print(row, flush=True)
