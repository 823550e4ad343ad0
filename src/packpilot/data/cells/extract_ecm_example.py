"""Extract PyBaMM's ``ECM_Example`` parameter set into ``ecm_example.json`` (run once).

Usage: ``python src/packpilot/data/cells/extract_ecm_example.py [PYBAMM_ECM_DATA_DIR]``

The tables are read from the CSV files shipped in the installed PyBaMM package
(``pybamm/input/parameters/ecm/data``) exactly as ``pybamm.parameters.process_*_data_csv``
does (grid axes = sorted unique values, values reshaped in C order), so PyBaMM is not imported
(packpilot never imports PyBaMM at run time). The scalar values are those of
``pybamm/input/parameters/ecm/example_set.py``; ``tests/test_cell_params.py`` checks the result
against ``pybamm.ParameterValues("ECM_Example")``. PyBaMM is BSD-3-Clause licensed,
Copyright (c) 2018-2025, the PyBaMM team.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

from packpilot.model.cell import CellParams, write_parameter_file
from packpilot.model.thermal import ThermalParams

HERE = Path(__file__).resolve().parent

PROVENANCE = (
    "PyBaMM 26.10 ParameterValues('ECM_Example') (pybamm/input/parameters/ecm, BSD-3-Clause, "
    "(c) the PyBaMM team): tables copied verbatim from its CSV files by "
    "extract_ecm_example.py. PyBaMM's description: 100 Ah cell; 100 A DCIR at 25 degC / 50 % "
    "SoC of 1 mOhm, quadratic in SoC (1.2 mOhm at 0 and 100 %), Arrhenius in temperature "
    "(Ea = 20 kJ/mol), +0.01 mOhm per 100 A; R0 = 40 % and R1 = 60 % of the DCIR; "
    "C1 = 30 s / R1; OCV and dU/dT from an undisclosed literature source. For demonstration "
    "only: it does not describe a particular cell."
)


def default_data_dir() -> Path:
    spec = importlib.util.find_spec("pybamm")
    if spec is None or spec.origin is None:
        raise SystemExit("pybamm is not installed; pass the ECM data directory explicitly")
    return Path(spec.origin).parent / "input" / "parameters" / "ecm" / "data"


def read_3d(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    data = np.genfromtxt(path, delimiter=",", skip_header=1)
    x1, x2, x3 = (np.unique(data[:, c]) for c in range(3))
    return x1, x2, x3, data[:, 3].reshape(len(x1), len(x2), len(x3), order="C")


def build(data_dir: Path) -> CellParams:
    ocv = np.genfromtxt(data_dir / "ecm_example_ocv.csv", delimiter=",", comments="#")
    du = np.genfromtxt(data_dir / "ecm_example_dudt.csv", delimiter=",", skip_header=1)
    du_x, du_t = np.unique(du[:, 0]), np.unique(du[:, 1])
    du_y = du[:, 2].reshape(len(du_x), len(du_t), order="C")
    t, i, s, r0 = read_3d(data_dir / "ecm_example_r0.csv")
    t1, i1, s1, r1 = read_3d(data_dir / "ecm_example_r1.csv")
    t2, i2, s2, c1 = read_3d(data_dir / "ecm_example_c1.csv")
    for a, b in ((t, t1), (t, t2), (i, i1), (i, i2), (s, s1), (s, s2)):
        if not np.array_equal(a, b):
            raise SystemExit("ECM_Example tables do not share their axes")
    return CellParams(
        name="ecm_example",
        capacity_ah=100.0,
        ocv_soc=ocv[:, 0],
        ocv_table_v=ocv[:, 1],
        ocv_ref_temp_c=None,
        dudt_axis="ocv_v",
        dudt_x=du_x,
        dudt_temp_c=du_t,
        dudt_v_per_k=du_y,
        rc_temp_c=t,
        rc_current_a=i,
        rc_soc=s,
        r0_ohm=r0,
        r1_ohm=r1,
        c1_f=c1,
        thermal=ThermalParams(
            cell_heat_capacity_j_per_k=1000.0,
            jig_heat_capacity_j_per_k=500.0,
            cell_jig_w_per_k=10.0,
            jig_air_w_per_k=10.0,
            nodes=2,
        ),
        v_min_v=3.2,
        v_max_v=4.2,
        provenance=PROVENANCE,
        extrapolation="clamp",
    )


def main(argv: list[str]) -> None:
    data_dir = Path(argv[1]) if len(argv) > 1 else default_data_dir()
    out = HERE / "ecm_example.json"
    write_parameter_file(build(data_dir), out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(sys.argv)
