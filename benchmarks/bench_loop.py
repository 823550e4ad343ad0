"""Closed-loop step time against PyBaMM's ``Simulation.step`` (measured in the same run).

PyBaMM steps one cell's ECM with its own solver; PackPilot's closed-loop step is measure →
controller → bus solve → advance every cell of a whole pack.
Run: ``python benchmarks/bench_loop.py``.
"""

from __future__ import annotations

import os
import time
from typing import Any

os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")


def _pybamm_step_us(n: int = 100) -> float:
    import pybamm

    sim = pybamm.Simulation(
        pybamm.equivalent_circuit.Thevenin(),
        parameter_values=pybamm.ParameterValues("ECM_Example"),
    )
    sim.step(dt=0.1)
    t0 = time.perf_counter()
    for _ in range(n):
        sim.step(dt=0.1)
    return (time.perf_counter() - t0) / n * 1e6


def _loop_step_us(example: str, steps: int = 3000) -> tuple[float, int]:
    from packpilot.config import load_config
    from packpilot.sim.runner import Runner

    cfg = load_config(os.path.join(os.path.dirname(__file__), "..", "examples", example))
    cfg = cfg.model_copy(
        update={
            "sim": cfg.sim.model_copy(
                update={"duration_s": steps * cfg.sim.dt_s, "progress": False}
            )
        }
    )
    Runner(cfg).run()  # warm-up (numba compile, caches)
    runner = Runner(cfg)
    t0 = time.perf_counter()
    runner.run()
    return (time.perf_counter() - t0) / steps * 1e6, runner.pack.n_cells


def run() -> list[dict[str, Any]]:
    py_us = _pybamm_step_us()
    rows: list[dict[str, Any]] = [
        {
            "case": "PyBaMM Thevenin Simulation.step (1 cell, dt 0.1 s)",
            "step_us": py_us,
            "ratio_vs_pybamm": 1.0,
        },
    ]
    for ex in ("smart_battery.toml", "uav_dual_parallel.toml"):
        us, cells = _loop_step_us(ex)
        rows.append(
            {
                "case": f"closed loop {ex} ({cells} cells)",
                "step_us": us,
                "ratio_vs_pybamm": py_us / us,
            }
        )
    return rows


if __name__ == "__main__":
    for r in run():
        print(f"{r['case']:<60} {r['step_us']:10.1f} us   x{r['ratio_vs_pybamm']:.1f}")
