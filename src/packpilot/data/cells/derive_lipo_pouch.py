"""Derive the ``lipo_pouch`` parameter set (run once; the result is committed).

Usage: ``PYBAMM_DISABLE_TELEMETRY=true python src/packpilot/data/cells/derive_lipo_pouch.py``
(needs PyBaMM, the ``pybamm`` extra; reads ``uav_5ah.json`` beside it).

The OCV is the full-cell open-circuit voltage of PyBaMM's ``Ecker2015`` set (Ecker et al., J.
Electrochem. Soc. 162 (2015) A1836: a Kokam SLPB 75106100 LiPo pouch cell, graphite / NCO):
the positive minus the negative electrode OCP at 25 degC along the stoichiometry path between
the set's 2.5 V and 4.2 V limits (PyBaMM's electrode-SOH solver), so that SoC 0 = 2.5 V and
SoC 1 = 4.2 V. Everything else (capacity, resistance and capacitance tables, thermal data,
dU/dT as a function of SoC, limits) is uav_5ah's: only the curve's shape changes. Nothing here
is fitted to a log.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.model.cell import CellParams, load_parameter_file, write_parameter_file

HERE = Path(__file__).resolve().parent
F64 = NDArray[np.float64]
SOC = np.round(np.linspace(-0.05, 1.05, 111), 10)  # uav_5ah's uniform 1 % grid
T_K = 298.15


def ecker_ocv(soc: F64) -> F64:
    """Ecker2015's full-cell OCV at ``soc`` (0..1.05: the negative electrode's stoichiometry
    leaves its table below SoC 0, so the caller extrapolates there)."""
    import pybamm  # type: ignore[import-untyped]

    pv = pybamm.ParameterValues("Ecker2015")
    param = pybamm.LithiumIonParameters()
    x0, x100, y100, y0 = pybamm.lithium_ion.ElectrodeSOHSolver(
        pv, param
    ).get_min_max_stoichiometries()
    xs, ys = x0 + soc * (x100 - x0), y0 + soc * (y100 - y0)
    up = pv.evaluate(param.p.prim.U(pybamm.Vector(ys), T_K)).ravel()
    un = pv.evaluate(param.n.prim.U(pybamm.Vector(xs), T_K)).ravel()
    return np.asarray(up - un, dtype=np.float64)


def derive_lipo(uav: CellParams) -> CellParams:
    inside = SOC >= 0.0
    ocv = np.empty_like(SOC)
    ocv[inside] = ecker_ocv(SOC[inside])
    slope = (ocv[inside][1] - ocv[inside][0]) / 0.01  # the curve's slope over its first 1 %
    ocv[~inside] = ocv[inside][0] + SOC[~inside] * slope
    # uav_5ah's dU/dT is tabled on its OCV axis; carried over as a function of SoC, on a
    # uniform 5 % grid (O(1) lookup in the kernels): uav_5ah's value at its own OCV(SoC)
    dudt_soc = np.round(np.linspace(-0.05, 1.05, 23), 10)
    at_v = np.interp(dudt_soc, uav.ocv_soc, uav.ocv_table_v)
    dudt = np.stack([np.interp(at_v, uav.dudt_x, uav.dudt_v_per_k[:, k])
                     for k in range(uav.dudt_temp_c.size)], axis=1)  # fmt: skip
    provenance = (
        "OCV: PyBaMM 26.10 ParameterValues('Ecker2015') (BSD-3-Clause; Ecker et al., J. "
        "Electrochem. Soc. 162 (2015) A1836, Kokam SLPB 75106100 LiPo pouch cell, graphite / "
        "NCO): positive minus negative electrode OCP at 25 degC along the electrode-SOH "
        "stoichiometry path between the set's 2.5 V (SoC 0) and 4.2 V (SoC 1) limits, on a "
        "uniform 1 % grid to SoC 1.05; below SoC 0 (where the negative stoichiometry leaves its "
        f"table) extended linearly with the first 1 %'s slope ({slope:.2f} V per unit SoC). "
        "Everything else is uav_5ah's (capacity 5 Ah, R0/R1/C1 tables, thermal data, limits "
        "2.5 / 4.2 V; dU/dT carried over as a function of SoC on a uniform 5 % grid). Built by "
        "derive_lipo_pouch.py; a template for LiPo packs' OCV shape, not a measured cell."
    )
    # uav_5ah but for the OCV and dU/dT (and what says so): its capacity, R0/R1/C1 tables,
    # thermal data and limits as they are
    return replace(
        uav, name="lipo_pouch", ocv_soc=SOC, ocv_table_v=ocv, ocv_ref_temp_c=25.0,
        dudt_axis="soc", dudt_x=dudt_soc, dudt_v_per_k=dudt, provenance=provenance,
        extrapolation="clamp",
    )  # fmt: skip


def main() -> None:
    params = derive_lipo(load_parameter_file(HERE / "uav_5ah.json"))
    out = HERE / f"{params.name}.json"
    write_parameter_file(params, out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
