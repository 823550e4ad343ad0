"""PyBaMM as the independent oracle for the cell model (ECM_Example, Thevenin, 1 RC, 2-node heat).

PyBaMM integrates the same ODEs with IDAKLU at tight tolerances; the current is a sum of
Heaviside steps so the solver restarts at every current change and returns both one-sided
limits there. Our samples are the left limits (end of each step, see ``CellTrace``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from packpilot.model.cell import (
    CellParams,
    advance,
    initial_state,
    load_parameter_set,
    simulate_current,
    thevenin,
)

os.environ["PYBAMM_DISABLE_TELEMETRY"] = "true"
pybamm = pytest.importorskip("pybamm")

F64 = NDArray[np.float64]


def drone_profile(seed: int = 7) -> F64:
    """A 1 h, 1 s resolution drone-like current for the 100 Ah ECM_Example cell (+ = discharge).

    Three flights (take-off bursts ~3C, climb, hover 1-1.5C with manoeuvre pulses up to 3.2C,
    descent, landing), rests, and a 1.2C charge between flights 1 and 2.
    """
    rng = np.random.default_rng(seed)
    segs: list[tuple[int, float]] = []

    def flight(hover_s: int) -> None:
        segs.extend([(15, 300.0), (25, 200.0)])
        t = 0
        while t < hover_s:
            dur = int(rng.integers(30, 90))
            segs.append((dur, float(rng.uniform(100.0, 150.0))))
            pulse = int(rng.integers(2, 8))
            segs.append((pulse, float(rng.uniform(220.0, 320.0))))
            t += dur + pulse
        segs.extend([(40, 60.0), (8, 160.0)])

    flight(700)
    segs.append((120, 0.0))
    segs.append((720, -120.0))  # charge
    segs.append((60, 0.0))
    flight(900)
    segs.append((90, 0.0))
    flight(400)
    cur = np.concatenate([np.full(d, c) for d, c in segs])
    if cur.size < 3600:
        cur = np.concatenate([cur, np.zeros(3600 - cur.size)])
    return cur[:3600]


@dataclass
class Oracle:
    t_s: F64
    voltage_v: F64
    soc: F64
    temp_c: F64
    jig_temp_c: F64
    current_a: F64


def run_pybamm(current: F64, soc0: float, ambient_c: float, rtol: float = 1e-9) -> Oracle:
    """Solve PyBaMM's Thevenin model on a piecewise-constant 1 s current; left-limit samples."""
    model = pybamm.equivalent_circuit.Thevenin()
    pv = pybamm.ParameterValues("ECM_Example")
    changes = np.flatnonzero(np.diff(current)) + 1

    def current_fn(t: Any) -> Any:
        expr = pybamm.Scalar(float(current[0]))
        for k in changes:
            expr = expr + float(current[k] - current[k - 1]) * (t >= float(k))
        return expr

    kelvin = ambient_c + 273.15
    pv.update(
        {
            "Current function [A]": current_fn,
            "Initial SoC": soc0,
            "Initial temperature [K]": kelvin,
            "Ambient temperature [K]": kelvin,
            "Lower voltage cut-off [V]": 2.0,
            "Upper voltage cut-off [V]": 5.0,
        }
    )
    solver = pybamm.IDAKLUSolver(rtol=rtol, atol=rtol * 1e-2)
    sim = pybamm.Simulation(model, parameter_values=pv, solver=solver)
    n = current.size
    sol = sim.solve(t_eval=[0.0, float(n)], t_interp=np.arange(n + 1, dtype=float))
    assert sol.termination == "final time"
    # at a current change PyBaMM stores t_k(1 - eps) then t_k: keep the first (left limit)
    _, idx = np.unique(np.round(sol.t, 6), return_index=True)
    assert idx.size == n + 1

    def get(name: str) -> F64:
        return np.asarray(sol[name].entries[idx], dtype=np.float64)

    return Oracle(
        t_s=np.asarray(sol.t[idx]),
        voltage_v=get("Voltage [V]"),
        soc=get("SoC"),
        temp_c=get("Cell temperature [degC]"),
        jig_temp_c=get("Jig temperature [degC]"),
        current_a=get("Current [A]"),
    )


@pytest.fixture(scope="module")
def ecm() -> CellParams:
    return load_parameter_set("ecm_example")


@pytest.fixture(scope="module")
def profile() -> F64:
    return drone_profile()


def test_profile_is_drone_like(profile: F64) -> None:
    assert profile.size == 3600
    assert profile.max() >= 300.0  # take-off ~3C
    assert (profile < 0).sum() >= 600  # a charge segment
    hover = profile[(profile >= 100) & (profile <= 150)]
    assert hover.size > 1500
    assert np.count_nonzero(np.diff(profile)) > 60  # many pulses


@pytest.mark.parametrize(
    ("ambient_c", "soc0", "max_dv", "rms_dv"),
    [(25.0, 0.95, 0.5e-3, 0.05e-3), (0.0, 0.95, 0.5e-3, 0.1e-3)],
)
def test_matches_pybamm_thevenin(
    ecm: CellParams, profile: F64, ambient_c: float, soc0: float, max_dv: float, rms_dv: float
) -> None:
    ref = run_pybamm(profile, soc0, ambient_c)
    ours = simulate_current(ecm, profile, 1.0, soc0, ambient_c)
    np.testing.assert_allclose(ours.t_s, ref.t_s, atol=1e-9)
    np.testing.assert_allclose(ours.current_a, ref.current_a, rtol=0, atol=1e-9)
    assert ref.soc.min() > 0.05 and ref.soc.max() < 1.0  # stayed inside the SoC table
    dv = ours.voltage_v - ref.voltage_v
    assert np.abs(dv).max() <= max_dv
    assert np.sqrt(np.mean(dv**2)) <= rms_dv
    assert np.abs(ours.temp_c - ref.temp_c).max() <= 0.01
    assert np.abs(ours.jig_temp_c - ref.jig_temp_c).max() <= 0.01
    assert np.abs(ours.soc - ref.soc).max() <= 1e-6
    assert ref.temp_c.max() - ambient_c > 1.0  # the thermal model was exercised


def test_pack_api_loop_matches_simulate_current(ecm: CellParams, profile: F64) -> None:
    """thevenin + advance, as the pack calls them, reproduce simulate_current exactly."""
    cur = profile[:600]
    trace = simulate_current(ecm, cur, 1.0, 0.9, 25.0)
    state = initial_state(ecm, 1, 0.9, 25.0)
    volts = []
    for k in range(cur.size):
        state, _ = advance(ecm, state, cur[k], 1.0, 25.0, ecm.capacity_ah, 1.0)
        e, r0 = thevenin(ecm, state, cur[k], ecm.capacity_ah, 1.0)
        volts.append(e[0] - r0[0] * cur[k])
    np.testing.assert_allclose(trace.voltage_v[1:], volts, rtol=0, atol=1e-12)
    np.testing.assert_allclose(trace.temp_c[-1], state.temp_c[0], rtol=0, atol=1e-12)


def _pybamm_interpolant_values(ecm_name: str, points: F64) -> F64:
    pv = pybamm.ParameterValues("ECM_Example")
    t, i, s = (pybamm.Vector(points[:, c]) for c in range(3))
    sym = pv[ecm_name](t, i, s)
    return np.asarray(sym.evaluate(), dtype=np.float64).ravel()


def test_table_lookup_matches_pybamm_interpolant(ecm: CellParams) -> None:
    """Inside the tables our trilinear lookup equals PyBaMM's Interpolant; outside we clamp
    where PyBaMM extrapolates linearly (and our 'linear' option then agrees with it)."""
    from dataclasses import replace

    from packpilot.model.cell.reference import _np_interp3

    rng = np.random.default_rng(3)
    inside = np.column_stack(
        [rng.uniform(-20, 50, 300), rng.uniform(-400, 700, 300), rng.uniform(0, 1, 300)]
    )
    outside = np.column_stack(
        [rng.uniform(-40, 70, 300), rng.uniform(-600, 900, 300), rng.uniform(-0.2, 1.2, 300)]
    )
    linear = replace(ecm, extrapolation="linear")
    for key, name in (("r0_ohm", "R0 [Ohm]"), ("r1_ohm", "R1 [Ohm]"), ("c1_f", "C1 [F]")):
        ref_in = _pybamm_interpolant_values(name, inside)
        ours = _np_interp3(ecm, key, inside[:, 0], inside[:, 1], inside[:, 2])
        np.testing.assert_allclose(ours, ref_in, rtol=1e-12)
        ref_out = _pybamm_interpolant_values(name, outside)
        ours_lin = _np_interp3(linear, key, outside[:, 0], outside[:, 1], outside[:, 2])
        np.testing.assert_allclose(ours_lin, ref_out, rtol=1e-10)
        clamped = _np_interp3(ecm, key, outside[:, 0], outside[:, 1], outside[:, 2])
        lo, hi = np.array([-20.0, -400.0, 0.0]), np.array([50.0, 700.0, 1.0])
        edge = np.clip(outside, lo, hi)
        np.testing.assert_allclose(clamped, _pybamm_interpolant_values(name, edge), rtol=1e-12)


def test_kernel_matches_pybamm_on_the_tables_with_linear_extrapolation(ecm: CellParams) -> None:
    """The numba thevenin kernel (O(1) lookup) reads R0 and OCV exactly like PyBaMM."""
    from dataclasses import replace

    linear = replace(ecm, extrapolation="linear")
    rng = np.random.default_rng(5)
    n = 200
    pts = np.column_stack(
        [rng.uniform(-30, 60, n), rng.uniform(-500, 800, n), rng.uniform(-0.04, 1.04, n)]
    )
    state = initial_state(linear, n, pts[:, 2], pts[:, 0])
    e, r0 = thevenin(linear, state, pts[:, 1], 100.0, 1.0)
    np.testing.assert_allclose(r0, _pybamm_interpolant_values("R0 [Ohm]", pts), rtol=1e-10)
    pv = pybamm.ParameterValues("ECM_Example")
    ocv = np.asarray(pv["Open-circuit voltage [V]"](pybamm.Vector(pts[:, 2])).evaluate())
    np.testing.assert_allclose(e, ocv.ravel(), rtol=1e-12)
