"""Cell model speed and fidelity against PyBaMM, measured in the same run.

(a) the 1 h drone-like profile of ``tests/test_cell_pybamm.py`` on ECM_Example at 1 s steps:
    ``simulate_current`` vs PyBaMM build + solve (ratio), and the fidelity at 25 degC and 0 degC;
(b) one PyBaMM ``Simulation.step`` (0.1 s) vs one ``thevenin`` + ``advance`` on a 12-cell pack;
(c) fleet throughput: 10,000 cells, full tables + thermal, numba warmed up: ``advance`` alone,
    ``thevenin`` + ``advance`` (two kernels) and the fused closed-loop ``step`` (one kernel).

Run: ``python benchmarks/bench_cell.py``; ``run()`` returns the figures for ``make bench``.
The machine may be shared: every timing is the best of several repeats.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:
    sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")

from packpilot.model.cell import (  # noqa: E402
    advance,
    initial_state,
    load_parameter_set,
    simulate_current,
    step,
    thevenin,
)


def _oracle_module() -> ModuleType:
    """The profile and the PyBaMM runner live with the oracle test; load that file."""
    path = ROOT / "tests" / "test_cell_pybamm.py"
    spec = importlib.util.spec_from_file_location("_cell_oracle", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


def _best(fn: Callable[[], Any], repeat: int, number: int = 1) -> float:
    """Best wall time of one call (s) over ``repeat`` rounds of ``number`` calls."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        best = min(best, (time.perf_counter() - t0) / number)
    return best


def _best_cpu(fn: Callable[[], Any], repeat: int, number: int) -> float:
    """Like _best, in CPU seconds of this process (immune to time slicing on a busy host)."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.process_time()
        for _ in range(number):
            fn()
        best = min(best, (time.process_time() - t0) / number)
    return best


def fidelity(oracle: ModuleType, profile: np.ndarray, ambient_c: float) -> dict[str, float]:
    params = load_parameter_set("ecm_example")
    ref = oracle.run_pybamm(profile, 0.95, ambient_c)
    ours = simulate_current(params, profile, 1.0, 0.95, ambient_c)
    dv = ours.voltage_v - ref.voltage_v
    tag = f"{ambient_c:g}C"
    return {
        f"max_dV_mV_{tag}": float(np.abs(dv).max() * 1e3),
        f"rms_dV_mV_{tag}": float(np.sqrt(np.mean(dv**2)) * 1e3),
        f"max_dT_K_{tag}": float(np.abs(ours.temp_c - ref.temp_c).max()),
        f"max_dSOC_{tag}": float(np.abs(ours.soc - ref.soc).max()),
    }


def pybamm_step_us(pybamm: Any, repeat: int = 3, number: int = 100) -> float:
    """Mean time of one ``Simulation.step(dt=0.1 s)`` with the current as an input."""
    pv = pybamm.ParameterValues("ECM_Example")
    pv["Current function [A]"] = "[input]"
    sim = pybamm.Simulation(pybamm.equivalent_circuit.Thevenin(), parameter_values=pv)
    inputs = {"Current function [A]": 50.0}
    for _ in range(5):
        sim.step(dt=0.1, inputs=inputs, save=False)
    return _best(lambda: sim.step(dt=0.1, inputs=inputs, save=False), repeat, number) * 1e6


def run() -> dict[str, float]:
    out: dict[str, float] = {}
    params = load_parameter_set("ecm_example")
    oracle = _oracle_module()
    pybamm = oracle.pybamm
    profile = oracle.drone_profile()

    # (a) 1 h profile
    simulate_current(params, profile, 1.0, 0.95, 25.0)  # compile
    t_ours = _best(lambda: simulate_current(params, profile, 1.0, 0.95, 25.0), 5, 5)
    oracle.run_pybamm(profile, 0.95, 25.0)  # import/JIT warm-up of PyBaMM itself
    t_pybamm = _best(lambda: oracle.run_pybamm(profile, 0.95, 25.0, rtol=1e-6), 3)
    out["profile_1h_ours_ms"] = t_ours * 1e3
    out["profile_1h_pybamm_ms"] = t_pybamm * 1e3
    out["profile_speedup_x"] = t_pybamm / t_ours
    out.update(fidelity(oracle, profile, 25.0))
    out.update(fidelity(oracle, profile, 0.0))

    # (b) one step: PyBaMM Simulation.step vs thevenin + advance on a 12-cell pack
    out["pybamm_step_us"] = pybamm_step_us(pybamm)
    uav = load_parameter_set("uav_5ah")
    n = 12
    state = initial_state(uav, n, np.linspace(0.8, 0.9, n), 25.0)
    cur = np.full(n, 40.0)
    cap = np.full(n, 5.0)
    rs = np.ones(n)

    def pack_step() -> None:
        thevenin(uav, state, cur, cap, rs)
        advance(uav, state, cur, 0.1, 25.0, cap, rs)

    pack_step()
    out["pack12_thevenin_advance_us"] = _best(pack_step, 5, 2000) * 1e6
    out["step_speedup_x"] = out["pybamm_step_us"] / out["pack12_thevenin_advance_us"]

    # (c) fleet throughput
    n = 10_000
    rng = np.random.default_rng(0)
    fleet = initial_state(uav, n, rng.uniform(0.2, 0.95, n), rng.uniform(0.0, 40.0, n))
    cur = rng.uniform(-10.0, 150.0, n)
    cap = uav.capacity_ah * rng.uniform(0.95, 1.05, n)
    rs = rng.uniform(0.9, 1.2, n)
    amb = rng.uniform(0.0, 40.0, n)
    advance(uav, fleet, cur, 0.1, amb, cap, rs)
    t_adv = _best(lambda: advance(uav, fleet, cur, 0.1, amb, cap, rs), 7, 20)
    t_thev = _best(lambda: thevenin(uav, fleet, cur, cap, rs), 7, 20)
    out["fleet10k_advance_Mcell_steps_per_s"] = n / t_adv / 1e6
    out["fleet10k_thevenin_advance_Mcell_steps_per_s"] = n / (t_adv + t_thev) / 1e6
    # CPU time of this process: the per-core figure when the machine is shared
    c_adv = _best_cpu(lambda: advance(uav, fleet, cur, 0.1, amb, cap, rs), 5, 50)
    c_thev = _best_cpu(lambda: thevenin(uav, fleet, cur, cap, rs), 5, 50)
    out["fleet10k_advance_Mcell_steps_per_cpu_s"] = n / c_adv / 1e6
    out["fleet10k_thevenin_advance_Mcell_steps_per_cpu_s"] = n / (c_adv + c_thev) / 1e6
    # fused step: terminal voltage + state update in one pass (what a closed-loop step needs)
    step(uav, fleet, cur, 0.1, amb, cap, rs)
    t_step = _best(lambda: step(uav, fleet, cur, 0.1, amb, cap, rs), 7, 20)
    c_step = _best_cpu(lambda: step(uav, fleet, cur, 0.1, amb, cap, rs), 5, 50)
    out["fleet10k_step_fused_Mcell_steps_per_s"] = n / t_step / 1e6
    out["fleet10k_step_fused_Mcell_steps_per_cpu_s"] = n / c_step / 1e6
    return out


def main() -> None:
    res = run()
    width = max(len(k) for k in res)
    print(f"{'figure':<{width}}  value")
    for key, value in res.items():
        print(f"{key:<{width}}  {value:.4g}")


if __name__ == "__main__":
    main()
