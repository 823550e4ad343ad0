"""Synthetic flight logs made by the plant from known parameters: what the fit's acceptance
is measured on (tests and ``benchmarks/bench_fit.py``).

The plant is PackPilot's own cell model (:func:`packpilot.model.cell.simulate_current`) with the
OCV and thermal data of a shipped set and *constant* R0, R1, C1 (so the truth is one number
each). The log then gets what a real logger adds: voltage noise, a current-sensor gain error
(which also drives the charge counter, as on a real autopilot), a rest at the start, and the
logging rate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from packpilot.model.cell import CellParams, load_parameter_set, simulate_current
from packpilot.model.fit.profile import F64, Profile
from packpilot.model.thermal import ThermalParams


@dataclass(frozen=True)
class Truth:
    capacity_ah: float = 5.0
    r0_ohm: float = 0.012
    r1_ohm: float = 0.006
    tau1_s: float = 20.0
    soc0: float = 0.95


def plant_params(truth: Truth, base: str = "uav_5ah") -> CellParams:
    """A shipped set with constant resistances and capacitance (the known truth)."""
    p = load_parameter_set(base)
    shape = (2, 2, 2)
    return replace(
        p, name=f"synthetic_{base}", capacity_ah=truth.capacity_ah,
        rc_temp_c=np.array([-20.0, 60.0]), rc_current_a=np.array([-100.0, 100.0]),
        rc_soc=np.array([0.0, 1.0]), r0_ohm=np.full(shape, truth.r0_ohm),
        r1_ohm=np.full(shape, truth.r1_ohm), c1_f=np.full(shape, truth.tau1_s / truth.r1_ohm),
        r2_ohm=None, c2_f=None,
    )  # fmt: skip


def ocv_bump(soc: F64, height_v: float = 0.08, centre: float = 0.75, width: float = 0.1) -> F64:
    """A known departure from the default OCV for tests: a smooth bump of ``height_v`` at
    ``centre`` (the corrected curve stays increasing for heights up to ~0.1 V)."""
    out: F64 = height_v * np.exp(-(((soc - centre) / width) ** 2))
    return out


def ocv_plant_params(truth: Truth, correction_v: F64, base: str = "uav_5ah") -> CellParams:
    """The plant of :func:`plant_params` with its OCV table moved by ``correction_v`` (one
    value per point of the template's OCV table): a cell whose OCV is *not* the default."""
    p = plant_params(truth, base)
    v = np.asarray(p.ocv_table_v, np.float64) + correction_v
    if not np.all(np.diff(v) > 0):
        raise ValueError("the corrected plant OCV must increase with SOC")
    return replace(p, name=f"synthetic_ocv_{base}", ocv_table_v=v)


def heating_plant_params(truth: Truth, b_k: float, heat_c_j_per_k: float, heat_g_w_per_k: float,
                         t_ref_c: float = 25.0, base: str = "uav_5ah", *,
                         entropic: bool = True) -> CellParams:  # fmt: skip
    """The plant of :func:`plant_params` whose resistances follow an Arrhenius law about
    ``t_ref_c`` (time constants kept) and whose cell has one thermal node (heat capacity,
    conductance to ambient): a pack that warms in flight and whose resistance falls.
    ``entropic=False`` drops dU/dT (the OCV's own temperature shift and the reversible heat,
    which the fit's stepper does not model)."""
    p = plant_params(truth, base)
    if not entropic:
        p = replace(p, dudt_v_per_k=np.zeros_like(p.dudt_v_per_k))
    temps = np.arange(-20.0, 121.0, 5.0)
    f = np.exp(b_k * (1.0 / (temps + 273.15) - 1.0 / (t_ref_c + 273.15)))

    def table(x: F64) -> F64:
        out: F64 = np.broadcast_to(x[:, None, None], (len(temps), 2, 2)).copy()
        return out

    return replace(
        p, name=f"synthetic_heating_{base}", rc_temp_c=temps, r0_ohm=table(truth.r0_ohm * f),
        r1_ohm=table(truth.r1_ohm * f), c1_f=table(truth.tau1_s / (truth.r1_ohm * f)),
        thermal=ThermalParams(heat_c_j_per_k, 0.0, 2.0 * heat_g_w_per_k, 2.0 * heat_g_w_per_k,
                              nodes=1),
    )  # fmt: skip


def flight_current(capacity_ah: float, rest_s: int, seconds: int, seed: int) -> F64:
    """Per-second cell current: a rest, a 3C take-off, 1.2C hover with 2-8 s manoeuvre
    pulses up to 3C and short easy spells, a landing and a rest."""
    rng = np.random.default_rng(seed)
    c = capacity_ah
    cur = [np.zeros(rest_s), np.full(10, 3.0 * c)]
    t = 0
    while t < seconds:
        hover = int(rng.integers(10, 40))
        cur.append(np.full(hover, 1.2 * c) + rng.normal(0.0, 0.05 * c, hover))
        pulse = int(rng.integers(2, 9))
        cur.append(np.full(pulse, float(rng.uniform(0.3, 3.0)) * c))
        t += hover + pulse
    cur += [np.full(15, 0.8 * c), np.zeros(60)]
    out: F64 = np.concatenate(cur)
    return out


def synthetic_log(
    truth: Truth,
    rate_hz: float,
    *,
    noise_v: float = 0.010,
    gain: float = 1.01,
    rest_s: int = 30,
    seconds: int = 1500,
    seed: int = 1,
    ambient_c: float = 25.0,
    plant: CellParams | None = None,
    flights: int = 1,
) -> Profile:
    """A logged flight: the plant stepped at the logging period (the current held over each
    second), its voltage with Gaussian noise of ``noise_v`` (one sigma), its current times
    ``gain`` and the charge counter integrating that current. ``plant`` replaces the
    constant-resistance plant of ``truth`` (e.g. :func:`heating_plant_params`). ``flights``
    > 1: that many flights of ``seconds / flights`` each, every one with its rest before it
    (``rest_s``) and its landing and 60 s rest after it (leave one flight out's test log)."""
    per_s = np.concatenate([
        flight_current(truth.capacity_ah, rest_s, seconds // flights, seed + 100 * k)
        for k in range(flights)
    ])  # fmt: skip
    reps = round(rate_hz)
    cur = np.repeat(per_s, reps) if reps > 1 else per_s
    h = 1.0 / rate_hz
    cell = plant_params(truth) if plant is None else plant
    tr = simulate_current(cell, cur, h, truth.soc0, ambient_c)
    rng = np.random.default_rng(seed + 1000)
    measured_i = tr.current_a * gain
    counter = np.concatenate([[0.0], np.cumsum(cur * gain * h)]) / 3600.0
    return Profile(
        name=f"synthetic_{rate_hz:g}hz_seed{seed}", t_s=tr.t_s, current_a=measured_i,
        voltage_v=tr.voltage_v + rng.normal(0.0, noise_v, tr.voltage_v.size),
        charge_ah=counter, temp_c=None,
    )  # fmt: skip


__all__ = [
    "Truth", "flight_current", "heating_plant_params", "ocv_bump", "ocv_plant_params",
    "plant_params", "synthetic_log",
]
