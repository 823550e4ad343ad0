"""Derive the ``uav_5ah`` and ``lfp_storage`` parameter sets (run once; results are committed).

Usage: ``python src/packpilot/data/cells/derive_sets.py`` (reads ``ecm_example.json`` beside it).

Both sets are documented transformations of PyBaMM's ``ECM_Example`` tables (see README.md in
this folder for the reasoning); nothing here is fitted to a measured cell.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.model.cell import CellParams, load_parameter_file, write_parameter_file
from packpilot.model.thermal import ThermalParams

HERE = Path(__file__).resolve().parent
F64 = NDArray[np.float64]

# --- uav_5ah ---------------------------------------------------------------------------------
UAV_CAPACITY_AH = 5.0
UAV_CURRENT_AXIS_FACTOR = 0.3  # = (5 Ah / 100 Ah) x 6: the -4C..7C axis becomes -24C..42C
UAV_DCIR_OHM = 3.0e-3  # R0 + R1 at 25 degC, 50 % SoC and the axis point mapped from 100 A
UAV_OCV_SPAN_V = (3.0, 4.2)  # OCV at 0 % and 100 % SoC after the affine map


def _trilinear(p: CellParams, tab: F64, temp: float, cur: float, soc: float) -> float:
    """Table value at one point (axis nodes or in between) with plain NumPy."""
    out = tab
    for axis, x in ((p.rc_temp_c, temp), (p.rc_current_a, cur), (p.rc_soc, soc)):
        i = int(np.clip(np.searchsorted(axis, x, side="right") - 1, 0, axis.size - 2))
        t = (x - axis[i]) / (axis[i + 1] - axis[i])
        out = out[i] * (1 - t) + out[i + 1] * t
    return float(out)


def derive_uav(ecm: CellParams) -> CellParams:
    cap_ratio = UAV_CAPACITY_AH / ecm.capacity_ah
    cur_axis = ecm.rc_current_a * UAV_CURRENT_AXIS_FACTOR
    i_ref = 100.0 * UAV_CURRENT_AXIS_FACTOR
    dcir_ecm = _trilinear(ecm, ecm.r0_ohm, 25.0, 100.0, 0.5) + _trilinear(
        ecm, ecm.r1_ohm, 25.0, 100.0, 0.5
    )
    k_r = UAV_DCIR_OHM / dcir_ecm
    v0 = float(np.interp(0.0, ecm.ocv_soc, ecm.ocv_table_v))
    v1 = float(np.interp(1.0, ecm.ocv_soc, ecm.ocv_table_v))
    lo, hi = UAV_OCV_SPAN_V
    gain = (hi - lo) / (v1 - v0)

    def vmap(v: F64) -> F64:
        return lo + (v - v0) * gain

    provenance = (
        "Derived from ecm_example (PyBaMM ECM_Example, BSD-3-Clause) by derive_sets.py to stand "
        f"for a 5 Ah high-rate UAV pouch cell: capacity {UAV_CAPACITY_AH} Ah; current axis x "
        f"{UAV_CURRENT_AXIS_FACTOR} (-24C..42C); R0 and R1 x {k_r:.6f} so that R0+R1 = "
        f"{UAV_DCIR_OHM * 1e3:.1f} mOhm at 25 degC / 50 % SoC / {i_ref:g} A (a 6S string is "
        f"~18 mOhm plus interconnects); C1 / {k_r:.6f} (tau = 30 s kept); OCV mapped affinely "
        f"V' = {lo} + (V - {v0:.4f}) x {gain:.6f} so that OCV(0 %) = {lo} V and OCV(100 %) = "
        f"{hi} V, shape kept; dU/dT values kept on the same affinely mapped OCV axis (so dU/dT "
        "as a function of SoC is unchanged) and applied to the OCV about 25 degC; thermal "
        f"masses and conductances x {cap_ratio} (thermal time constants kept). Illustrative, "
        "not a measured cell."
    )
    return CellParams(
        name="uav_5ah",
        capacity_ah=UAV_CAPACITY_AH,
        ocv_soc=ecm.ocv_soc,
        ocv_table_v=vmap(ecm.ocv_table_v),
        ocv_ref_temp_c=25.0,
        dudt_axis="ocv_v",
        dudt_x=vmap(ecm.dudt_x),
        dudt_temp_c=ecm.dudt_temp_c,
        dudt_v_per_k=ecm.dudt_v_per_k,
        rc_temp_c=ecm.rc_temp_c,
        rc_current_a=cur_axis,
        rc_soc=ecm.rc_soc,
        r0_ohm=ecm.r0_ohm * k_r,
        r1_ohm=ecm.r1_ohm * k_r,
        c1_f=ecm.c1_f / k_r,
        thermal=ThermalParams(
            cell_heat_capacity_j_per_k=ecm.thermal.cell_heat_capacity_j_per_k * cap_ratio,
            jig_heat_capacity_j_per_k=ecm.thermal.jig_heat_capacity_j_per_k * cap_ratio,
            cell_jig_w_per_k=ecm.thermal.cell_jig_w_per_k * cap_ratio,
            jig_air_w_per_k=ecm.thermal.jig_air_w_per_k * cap_ratio,
            nodes=2,
        ),
        v_min_v=2.5,
        v_max_v=4.2,
        provenance=provenance,
        extrapolation="clamp",
    )


# --- lfp_storage -------------------------------------------------------------------------------
# Knots of a typical LFP/graphite OCV at 25 degC (low-rate average of charge and discharge):
# steep rise below ~5 %, the two graphite-staging plateaus near 3.28-3.30 V and 3.32-3.34 V with
# the step around 60-65 % SoC, and the sharp end-of-charge rise. Generic shape, no particular cell.
LFP_OCV_KNOTS = (
    (-0.05, 2.50),
    (0.00, 3.000),
    (0.01, 3.080),
    (0.02, 3.130),
    (0.05, 3.195),
    (0.10, 3.235),
    (0.15, 3.255),
    (0.20, 3.265),
    (0.30, 3.278),
    (0.40, 3.287),
    (0.50, 3.293),
    (0.58, 3.298),
    (0.62, 3.310),
    (0.66, 3.322),
    (0.70, 3.327),
    (0.80, 3.332),
    (0.90, 3.336),
    (0.95, 3.345),
    (0.98, 3.370),
    (0.99, 3.395),
    (1.00, 3.450),
    (1.05, 3.650),
)
# dU/dT of LFP/graphite cells is small (|dU/dT| <~ 0.1-0.4 mV/K) and changes sign with SoC;
# representative values, constant in temperature.
LFP_DUDT_KNOTS_MV_PER_K = (
    (0.00, -0.40),
    (0.10, -0.15),
    (0.20, 0.05),
    (0.35, 0.10),
    (0.50, 0.05),
    (0.65, -0.05),
    (0.80, -0.10),
    (0.90, -0.10),
    (1.00, -0.15),
)


def derive_lfp(ecm: CellParams) -> CellParams:
    kx, ky = (np.array(v) for v in zip(*LFP_OCV_KNOTS, strict=True))
    soc = np.round(np.linspace(-0.05, 1.05, 221), 10)  # uniform 0.005 grid -> O(1) lookup
    ocv = np.interp(soc, kx, ky)
    kx, ky = (np.array(v) for v in zip(*LFP_DUDT_KNOTS_MV_PER_K, strict=True))
    dx = np.round(np.linspace(0.0, 1.0, 21), 10)  # uniform 5 % grid -> O(1) lookup
    dy = np.interp(dx, kx, ky)
    dudt_t = np.array([-20.0, 60.0])
    dudt = np.repeat((dy * 1e-3)[:, None], dudt_t.size, axis=1)
    provenance = (
        "Generic 100 Ah LFP/graphite storage cell, built by derive_sets.py: resistance and "
        "capacitance tables of ecm_example (PyBaMM ECM_Example, BSD-3-Clause) unchanged (DCIR "
        "~1 mOhm at 25 degC / 50 % SoC, typical of 100 Ah prismatic LFP cells); OCV from a "
        "generic LFP shape (knots in derive_sets.py: 3.00 V at 0 %, plateaus 3.26-3.34 V, "
        "3.45 V at 100 %) on a uniform 0.5 % grid; dU/dT a representative SoC-dependent "
        "profile within +-0.4 mV/K (knots in derive_sets.py, 5 % grid) applied about 25 degC; "
        "thermal: 2000 J/K cell (~2 kg prismatic), 1000 J/K rack share, 10 W/K cell-rack, "
        "5 W/K rack-air (still air). "
        "Assumptions, not a measured cell."
    )
    return CellParams(
        name="lfp_storage",
        capacity_ah=100.0,
        ocv_soc=soc,
        ocv_table_v=ocv,
        ocv_ref_temp_c=25.0,
        dudt_axis="soc",
        dudt_x=dx,
        dudt_temp_c=dudt_t,
        dudt_v_per_k=dudt,
        rc_temp_c=ecm.rc_temp_c,
        rc_current_a=ecm.rc_current_a,
        rc_soc=ecm.rc_soc,
        r0_ohm=ecm.r0_ohm,
        r1_ohm=ecm.r1_ohm,
        c1_f=ecm.c1_f,
        thermal=ThermalParams(
            cell_heat_capacity_j_per_k=2000.0,
            jig_heat_capacity_j_per_k=1000.0,
            cell_jig_w_per_k=10.0,
            jig_air_w_per_k=5.0,
            nodes=2,
        ),
        v_min_v=2.5,
        v_max_v=3.65,
        provenance=provenance,
        extrapolation="clamp",
    )


def main() -> None:
    ecm = load_parameter_file(HERE / "ecm_example.json")
    for params in (derive_uav(ecm), derive_lfp(ecm)):
        out = HERE / f"{params.name}.json"
        write_parameter_file(params, out)
        print(f"wrote {out}")


if __name__ == "__main__":
    main()
