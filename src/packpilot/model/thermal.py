"""Lumped thermal model of a cell: one node (cell to ambient) or two nodes (cell, jig, ambient).

The two-node network is the one of PyBaMM's ``pybamm.equivalent_circuit.Thevenin``::

    C_cell dT_cell/dt = Q - G_cj (T_cell - T_jig)
    C_jig  dT_jig/dt  = G_cj (T_cell - T_jig) - G_ja (T_jig - T_amb)

With the heat input ``Q`` and the ambient held constant over a step, the network is linear with
constant coefficients, so it is advanced *exactly* with the 2x2 matrix exponential (closed form,
real distinct eigenvalues). The one-node variant drops the jig's heat capacity: the cell sees
ambient through the series conductance ``G_cj G_ja / (G_cj + G_ja)`` (same steady state as the
two-node network), and the massless jig sits at the conductance divider between cell and ambient.

Both variants reduce to the same six coefficients per ``(ThermalParams, dt)`` so one kernel
serves both: with ``y = T - T_amb``::

    y_cell' = e11 y_cell + e12 y_jig + kc Q
    y_jig'  = e21 y_cell + e22 y_jig + kj Q
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from packpilot.errors import ConfigError

KELVIN = 273.15
"""Offset between degrees Celsius and kelvin (PyBaMM uses the same constant)."""


@dataclass(frozen=True)
class ThermalParams:
    """Lumped thermal parameters of one cell and its jig (the pack structure around it).

    ``nodes=2``: cell and jig have heat capacity (PyBaMM's Thevenin model).
    ``nodes=1``: the jig is massless; the cell exchanges heat with ambient through
    :attr:`cell_air_w_per_k`, the series combination of the two conductances.
    """

    cell_heat_capacity_j_per_k: float
    jig_heat_capacity_j_per_k: float
    cell_jig_w_per_k: float
    jig_air_w_per_k: float
    nodes: int = 2

    def __post_init__(self) -> None:
        for name in (
            "cell_heat_capacity_j_per_k",
            "cell_jig_w_per_k",
            "jig_air_w_per_k",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"thermal.{name}: must be a finite number > 0, got {value!r}")
        if self.nodes not in (1, 2):
            raise ConfigError(f"thermal.nodes: must be 1 or 2, got {self.nodes!r}")
        jig = self.jig_heat_capacity_j_per_k
        if not math.isfinite(jig) or jig < 0.0 or (self.nodes == 2 and jig <= 0.0):
            raise ConfigError(
                "thermal.jig_heat_capacity_j_per_k: must be finite and > 0 for nodes=2 "
                f"(>= 0 for nodes=1), got {jig!r}"
            )

    @property
    def cell_air_w_per_k(self) -> float:
        """Series conductance cell→jig→air: the one-node model's conductance to ambient."""
        g, h = self.cell_jig_w_per_k, self.jig_air_w_per_k
        return g * h / (g + h)

    @property
    def jig_weight(self) -> float:
        """Where a massless jig sits between ambient (0) and the cell (1)."""
        g, h = self.cell_jig_w_per_k, self.jig_air_w_per_k
        return g / (g + h)


@lru_cache(maxsize=256)
def step_coefficients(thermal: ThermalParams, dt_s: float) -> tuple[float, ...]:
    """Exact one-step coefficients ``(e11, e12, e21, e22, kc, kj)`` for constant heat over dt_s.

    ``E = expm(A dt)`` is built from the eigenvalues (Sylvester's formula), and the heat gains
    are ``(I - E) y_ss`` per watt, where ``y_ss`` is the steady-state rise per watt.
    """
    h = float(dt_s)
    g = thermal.cell_jig_w_per_k
    ga = thermal.jig_air_w_per_k
    cc = thermal.cell_heat_capacity_j_per_k
    if thermal.nodes == 1:
        geq = thermal.cell_air_w_per_k
        e11 = math.exp(-geq * h / cc)
        kc = (1.0 - e11) / geq
        w = thermal.jig_weight
        return (e11, 0.0, w * e11, 0.0, kc, w * kc)
    cj = thermal.jig_heat_capacity_j_per_k
    a, b = -g / cc, g / cc
    c, d = g / cj, -(g + ga) / cj
    m = 0.5 * (a + d)
    q = math.sqrt(0.25 * (a - d) ** 2 + b * c)  # > 0: b*c > 0, eigenvalues real and distinct
    l1, l2 = m + q, m - q
    x1, x2 = math.exp(l1 * h), math.exp(l2 * h)
    # E = [x1 (A - l2 I) - x2 (A - l1 I)] / (l1 - l2)
    inv = 1.0 / (l1 - l2)
    e11 = (x1 * (a - l2) - x2 * (a - l1)) * inv
    e12 = (x1 - x2) * b * inv
    e21 = (x1 - x2) * c * inv
    e22 = (x1 * (d - l2) - x2 * (d - l1)) * inv
    # steady-state rise per watt of cell heat: cell 1/g + 1/ga, jig 1/ga
    yc, yj = 1.0 / g + 1.0 / ga, 1.0 / ga
    kc = yc - (e11 * yc + e12 * yj)
    kj = yj - (e21 * yc + e22 * yj)
    return (e11, e12, e21, e22, kc, kj)
