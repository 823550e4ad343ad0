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

# Thermal network of one cell in a 6S1P stacked pouch pack (physical estimate, not scaled from
# ECM_Example; sources in README.md). Node "cell" = the cell's mean temperature, node "jig" =
# the pack's outer skin (wrap) next to it; every cell gets the same per-cell share.
UAV_CELL_MASS_KG = 0.115  # 18.5 Wh at ~160 Wh/kg (high-rate LiPo: 150-185 Wh/kg cell level)
UAV_CELL_CP_J_PER_KG_K = 1050.0  # pouch / 18650 Li-ion cells: 0.96-1.25 J/(g K) measured
UAV_CELL_DIMS_M = (0.144, 0.050, 0.009)  # length, width, thickness of the cell body
UAV_STACK_CELLS = 6  # cells stacked face to face (6S1P), wrapped as one block
UAV_K_THROUGH_W_PER_M_K = 0.5  # cross-plane conductivity (0.47-0.52 measured on pouch cells)
UAV_K_INPLANE_W_PER_M_K = 26.6  # in-plane conductivity (current collectors; 20 Ah pouch)
UAV_EDGE_GAP_M = 2.0e-3  # electrode-stack edge to pouch wall: separator overhang + seal fold
UAV_EDGE_GAP_K_W_PER_M_K = 0.3  # polymer / electrolyte-wet separator, laminate
UAV_AIR_SPEED_M_S = 2.0  # air speed along the pack in flight (partly shrouded battery bay)
UAV_AIR_AT_0C = (0.0243, 1.35e-5, 0.71)  # air at 0 degC: k [W/(m K)], nu [m^2/s], Pr
UAV_EMISSIVITY = 0.9  # PVC shrink wrap
UAV_RADIATION_T_K = 273.15  # linearisation temperature of the radiative exchange
UAV_PACK_HARDWARE_KG = 0.045  # 6S pack: leads, connectors, balance lead, wrap, end boards
UAV_PACK_HARDWARE_CP_J_PER_KG_K = 800.0  # copper 385, PVC ~1000, silicone ~1300: mixed


def _trilinear(p: CellParams, tab: F64, temp: float, cur: float, soc: float) -> float:
    """Table value at one point (axis nodes or in between) with plain NumPy."""
    out = tab
    for axis, x in ((p.rc_temp_c, temp), (p.rc_current_a, cur), (p.rc_soc, soc)):
        i = int(np.clip(np.searchsorted(axis, x, side="right") - 1, 0, axis.size - 2))
        t = (x - axis[i]) / (axis[i + 1] - axis[i])
        out = out[i] * (1 - t) + out[i + 1] * t
    return float(out)


def uav_thermal() -> tuple[ThermalParams, dict[str, float]]:
    """Per-cell thermal network of the uav_5ah pack from mass x cp and h x A (see README.md).

    Cell node: mass x specific heat. Cell -> skin: conduction, in parallel (a) through the stack
    to its two large faces (uniformly heated slab cooled on both faces: mean-to-surface
    conductance 6 k A / a, a = half the stack thickness, shared by the cells of the stack) and
    (b) in-plane to the cell's own two long edges (same slab formula across the width) in series
    with the edge gap to the pouch wall (tabs, short edges neglected). Skin -> air: h x (the
    pack's outer surface / number of cells), h = laminar flat-plate forced convection along the
    pack length plus linearised radiation. Jig node: the per-cell share of the pack hardware.
    """
    length, width, thick = UAV_CELL_DIMS_M
    n = UAV_STACK_CELLS
    c_cell = UAV_CELL_MASS_KG * UAV_CELL_CP_J_PER_KG_K
    face = length * width
    g_faces = 6.0 * UAV_K_THROUGH_W_PER_M_K * face / (0.5 * n * thick) / n
    g_spread = 6.0 * UAV_K_INPLANE_W_PER_M_K * (length * thick) / (0.5 * width)
    g_gap = UAV_EDGE_GAP_K_W_PER_M_K / UAV_EDGE_GAP_M * (2.0 * length * thick)
    g_edges = 1.0 / (1.0 / g_spread + 1.0 / g_gap)
    g_cj = g_faces + g_edges
    k_air, nu, pr = UAV_AIR_AT_0C
    re = UAV_AIR_SPEED_M_S * length / nu
    h_conv = 0.664 * re**0.5 * pr ** (1.0 / 3.0) * k_air / length
    h_rad = 4.0 * UAV_EMISSIVITY * 5.670374419e-8 * UAV_RADIATION_T_K**3
    area = (2.0 * face + n * 2.0 * (length + width) * thick) / n
    g_ja = (h_conv + h_rad) * area
    c_jig = UAV_PACK_HARDWARE_KG * UAV_PACK_HARDWARE_CP_J_PER_KG_K / n
    thermal = ThermalParams(
        cell_heat_capacity_j_per_k=c_cell,
        jig_heat_capacity_j_per_k=c_jig,
        cell_jig_w_per_k=g_cj,
        jig_air_w_per_k=g_ja,
        nodes=2,
    )
    info = {
        "g_faces": g_faces,
        "g_edges": g_edges,
        "h_conv": h_conv,
        "h_rad": h_rad,
        "area": area,
        "re": re,
    }
    return thermal, info


def derive_uav(ecm: CellParams) -> CellParams:
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

    c, ti = uav_thermal()
    dims = "x".join(f"{d * 1e3:g}" for d in UAV_CELL_DIMS_M) + " mm"

    provenance = (
        "Derived from ecm_example (PyBaMM ECM_Example, BSD-3-Clause) by derive_sets.py to stand "
        f"for a 5 Ah high-rate UAV pouch cell: capacity {UAV_CAPACITY_AH} Ah; current axis x "
        f"{UAV_CURRENT_AXIS_FACTOR} (-24C..42C); R0 and R1 x {k_r:.6f} so that R0+R1 = "
        f"{UAV_DCIR_OHM * 1e3:.1f} mOhm at 25 degC / 50 % SoC / {i_ref:g} A (a 6S string is "
        f"~18 mOhm plus interconnects); C1 / {k_r:.6f} (tau = 30 s kept); OCV mapped affinely "
        f"V' = {lo} + (V - {v0:.4f}) x {gain:.6f} so that OCV(0 %) = {lo} V and OCV(100 %) = "
        f"{hi} V, shape kept; dU/dT values kept on the same affinely mapped OCV axis (so dU/dT "
        "as a function of SoC is unchanged) and applied to the OCV about 25 degC; thermal "
        "network estimated physically for a cell in a stacked 6S1P pouch pack (sources in "
        f"README.md): cell {c.cell_heat_capacity_j_per_k:.2f} J/K = {UAV_CELL_MASS_KG * 1e3:g} g "
        f"x {UAV_CELL_CP_J_PER_KG_K:g} J/(kg K); cell-skin {c.cell_jig_w_per_k:.3f} W/K = "
        f"through-plane to the stack faces {ti['g_faces']:.3f} (k {UAV_K_THROUGH_W_PER_M_K:g} "
        f"W/(m K)) + in-plane to the long edges and across a {UAV_EDGE_GAP_M * 1e3:g} mm gap "
        f"{ti['g_edges']:.3f} (k {UAV_K_INPLANE_W_PER_M_K:g} / {UAV_EDGE_GAP_K_W_PER_M_K:g} "
        f"W/(m K)), cell body {dims}; skin-air {c.jig_air_w_per_k:.4f} W/K = h "
        f"{ti['h_conv'] + ti['h_rad']:.1f} W/(m^2 K) (laminar forced convection at "
        f"{UAV_AIR_SPEED_M_S:g} m/s along the pack {ti['h_conv']:.1f} + radiation "
        f"{ti['h_rad']:.1f}) x {ti['area'] * 1e4:.1f} cm^2 (pack surface / {UAV_STACK_CELLS}); "
        f"jig {c.jig_heat_capacity_j_per_k:.2f} J/K = pack hardware "
        f"{UAV_PACK_HARDWARE_KG * 1e3:g} g x {UAV_PACK_HARDWARE_CP_J_PER_KG_K:g} J/(kg K) / "
        f"{UAV_STACK_CELLS}. Illustrative, not a measured cell."
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
        thermal=c,
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
