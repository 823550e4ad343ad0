"""The same split fitted with PyBOP's CMA-ES (bench-only comparison for issue #27).

Run by ``bench_fit.py`` in the interpreter named by ``PACKPILOT_PYBOP_PYTHON`` (PyBOP 26.3
needs numpy < 2.4, so it lives in its own environment, see pyproject's ``bench`` extra):
``python pybop_cmaes.py IN.npz OUT.json``. IN holds one profile per cell (``t_s``,
``current_a``, ``voltage_v``), the split index, the OCV table and a start; OUT the fitted
values, the held-out RMSE and max error (same split, same OCV as PackPilot's fit).

The model is PyBaMM's Thevenin with one RC pair, thermal effects off (entropic change 0) and
the OCV of PackPilot's chemistry default as an interpolant; fitted: R0, R1, C1, capacity and
initial SOC. PyBaMM takes the logged current as an interpolant in time (its convention; the
logged samples are the same).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import pybamm
import pybop


def _values(d: dict[str, np.ndarray], start: dict[str, float]) -> pybamm.ParameterValues:
    def ocv(soc: pybamm.Symbol) -> pybamm.Symbol:
        return pybamm.Interpolant(d["ocv_soc"], d["ocv_v"], soc, name="ocv")

    return pybamm.ParameterValues({
        "chemistry": "ecm", "Initial SoC": start["soc0"],
        "Initial temperature [K]": 298.15, "Ambient temperature [K]": 298.15,
        "Cell capacity [A.h]": start["capacity_ah"], "Nominal cell capacity [A.h]": 5.0,
        "Current function [A]": 0.0, "Upper voltage cut-off [V]": 5.0,
        "Lower voltage cut-off [V]": 1.0, "Cell thermal mass [J/K]": 1e9,
        "Cell-jig heat transfer coefficient [W/K]": 10.0, "Jig thermal mass [J/K]": 1e9,
        "Jig-air heat transfer coefficient [W/K]": 10.0, "Open-circuit voltage [V]": ocv,
        "R0 [Ohm]": start["r0_ohm"], "Element-1 initial overpotential [V]": 0.0,
        "R1 [Ohm]": start["r1_ohm"], "C1 [F]": start["tau1_s"] / start["r1_ohm"],
        "Entropic change [V/K]": 0.0,
    })  # fmt: skip


def _simulate(d: dict[str, np.ndarray], vals: pybamm.ParameterValues, k: int) -> np.ndarray:
    t = d["t_s"][:k] - d["t_s"][0]
    vals = vals.copy()
    vals["Current function [A]"] = pybamm.Interpolant(t, d["current_a"][:k], pybamm.t)
    model = pybamm.equivalent_circuit.Thevenin()
    sol = pybamm.Simulation(model, parameter_values=vals).solve(t_eval=t, t_interp=t)
    return np.asarray(sol["Voltage [V]"](t))


def main(src: str, dst: str) -> None:
    d = dict(np.load(src))
    split = int(d["split"])
    start = {k: float(d[k]) for k in ("soc0", "capacity_ah", "r0_ohm", "r1_ohm", "tau1_s")}
    t = d["t_s"][:split] - d["t_s"][0]
    dataset = pybop.Dataset({
        "Time [s]": t, "Current [A]": d["current_a"][:split],
        "Voltage [V]": d["voltage_v"][:split],
    })  # fmt: skip
    vals = _values(d, start)
    bounds = {"R0 [Ohm]": (1e-4, 0.5), "R1 [Ohm]": (1e-5, 0.5), "C1 [F]": (1.0, 1e6),
              "Cell capacity [A.h]": (0.1 * start["capacity_ah"], 10 * start["capacity_ah"]),
              "Initial SoC": (0.0, 1.0)}  # fmt: skip
    init = {"R0 [Ohm]": start["r0_ohm"], "R1 [Ohm]": start["r1_ohm"],
            "C1 [F]": start["tau1_s"] / start["r1_ohm"],
            "Cell capacity [A.h]": start["capacity_ah"], "Initial SoC": start["soc0"]}  # fmt: skip
    for name, (lo, hi) in bounds.items():
        vals[name] = pybop.Parameter(
            bounds=(lo, hi), initial_value=float(np.clip(init[name], lo, hi)),
            transformation=None if name == "Initial SoC" else pybop.LogTransformation(),
        )
    simulator = pybop.pybamm.Simulator(
        pybamm.equivalent_circuit.Thevenin(), parameter_values=vals, protocol=dataset
    )
    problem = pybop.Problem(simulator, pybop.SumSquaredError(dataset))
    options = pybop.PintsOptions(
        max_iterations=1000, max_unchanged_iterations=60, relative_tolerance=1e-6,
        absolute_tolerance=1e-9, multistart=3,
    )
    optim = pybop.CMAES(problem, options=options)
    t0 = time.process_time()
    result = optim.run()
    cpu = time.process_time() - t0
    best = {k: float(np.asarray(v).ravel()[0]) for k, v in result.best_inputs.items()}
    full = _values(d, start)
    for k, v in best.items():
        full[k] = v
    pred = _simulate(d, full, len(d["t_s"]))
    err = pred[split:] - d["voltage_v"][split:]
    out = {"fitted": best, "fit_cpu_s": cpu, "heldout_rmse_v": float(np.sqrt(np.mean(err**2))),
           "heldout_max_v": float(np.max(np.abs(err)))}  # fmt: skip
    with open(dst, "w", encoding="utf-8") as fh:
        json.dump(out, fh)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
