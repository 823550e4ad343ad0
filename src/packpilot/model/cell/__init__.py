"""Thevenin equivalent-circuit cell model, vectorized over cells, with PyBaMM's conventions.

Per cell (current ``I`` positive on discharge, SoC as a fraction)::

    dSoC/dt   = -I / (3600 Q)
    deta_j/dt = (I R_j - eta_j) / (R_j C_j)            j = 1..n_rc   (eta_j = drop across RC j)
    V         = OCV(SoC, T) - sum_j eta_j - I R0
    Q_heat    = I^2 R0 + I sum_j eta_j - I (T + 273.15) dU/dT

``eta_j`` is the *drop* across RC branch j; PyBaMM's "Element-j overpotential [V]" is ``-eta_j``.
R0, R_j, C_j are trilinear tables on (cell temperature, current, SoC); dU/dT is a bilinear table on
(OCV or SoC, temperature), as in PyBaMM's ``ECM_Example`` where it is looked up by the OCV value.
The OCV table is the OCV at ``ocv_ref_temp_c``; when that is ``None`` (PyBaMM's convention) the
OCV does not depend on temperature and dU/dT only enters the reversible heat.

Discretization for a step of constant current (see docs/cell_model.md): SoC is advanced exactly;
the tables are read once per step at (T at step start, I, SoC at mid-step); each RC branch uses its
exact exponential solution; the heat (with the RC drop averaged exactly over the step) is held
constant and the thermal network is advanced exactly (:mod:`packpilot.model.thermal`).

The package, one job per module:

- :mod:`~packpilot.model.cell.params` — :class:`CellParams`, validation, parameter files;
- :mod:`~packpilot.model.cell.kernels` — the numba kernels (the hot loops);
- :mod:`~packpilot.model.cell.model` — :class:`CellState` and the public array functions;
- :mod:`~packpilot.model.cell.reference` — the plain NumPy reference (``*_numpy``) used in tests.
"""

from __future__ import annotations

from packpilot.model.cell.model import (
    CellState,
    CellTrace,
    advance,
    initial_state,
    ocv_v,
    simulate_current,
    step,
    thevenin,
)
from packpilot.model.cell.params import (
    FORMAT,
    PARAMETER_SETS,
    CellParams,
    load_parameter_file,
    load_parameter_set,
    parameter_set_path,
    params_from_dict,
    params_to_dict,
    write_parameter_file,
)
from packpilot.model.cell.reference import advance_numpy, thevenin_numpy
from packpilot.model.thermal import ThermalParams

__all__ = [
    "FORMAT",
    "PARAMETER_SETS",
    "CellParams",
    "CellState",
    "CellTrace",
    "ThermalParams",
    "advance",
    "advance_numpy",
    "initial_state",
    "load_parameter_file",
    "load_parameter_set",
    "ocv_v",
    "parameter_set_path",
    "params_from_dict",
    "params_to_dict",
    "simulate_current",
    "step",
    "thevenin",
    "thevenin_numpy",
    "write_parameter_file",
]
