"""Calibrate the discharge-protection table from a cell set (#15 §4; derivation in
docs/discharge_protection.md, "Calibrated table").

The source's table (spec §4) fixes three cut-offs for all cells. Here each cell of a finer
(current, temperature) grid gets the cut-off at which a cell of this set, discharged at the
cell's *worst corner* (the highest current and lowest temperature of the cell, i.e. the
largest I x R), is still above the SOC floor when the allowance at that cut-off is used up::

    s_c    = floor + I * t_max / (3600 * Q)           charge the allowance may still draw
    cutoff = OCV(s_c, T) - I * (R0 + R1)(T, I, s_c)   steady-state drop (the RC branch charged)

minimised over the cell's corners (the "worst corner"; with R decreasing in T and the drop
growing with I this is the corner of highest I and lowest T). With the worst corner a battery
anywhere inside the cell reaches the cut-off at an SOC no higher than at the corner, so the
trip never comes earlier than the floor plus the allowance needs at that corner; how far below
the floor it can go is bounded by the cell's width, hence the fine default grid. Above the last
current edge the cut-off is computed at that edge (the best corner there: a heavier load trips
early rather than deep). ``t_max`` is the source table's value for the cell (its row at the
cell's midpoint), so m and the weights are those of the source.

Pure: reads the cell set's tables (the NumPy reference of the model), writes nothing.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from packpilot.config.protection import (
    CUTOFF_MAX_V,
    CUTOFF_MIN_V,
    DEFAULT_PARAMETERS,
    DEFAULT_TABLE,
    ProtectionConfig,
    ProtectionParameter,
    TableRow,
)
from packpilot.errors import ConfigError
from packpilot.model.cell.params import CellParams
from packpilot.model.cell.reference import _np_interp3, _ocv_numpy

CURRENT_EDGES_A: tuple[float, ...] = (5, 10, 15, 20, 25, 30, 35, 40, 50, 60)
"""Default current edges (battery current, A): bands (-inf, 5], (5, 10], ..., (60, inf)
(upper edge included, as the spec's §10.1 boundaries)."""
TEMP_EDGES_C: tuple[float, ...] = (-10, -5, 0, 5, 10, 15, 20, 25, 30, 40)
"""Default temperature edges (degC): bands (-inf, -10), [-10, -5), ..., [40, inf)."""


@dataclass(frozen=True)
class CalibratedCell:
    """One cell of the calibrated grid and how its cut-off was derived."""

    current: str
    temp: str
    corner_current_a: float
    corner_temp_c: float
    soc_at_cutoff: float
    ocv_v: float
    drop_v: float
    cutoff_v: float
    t_max_s: float
    source_param: str


def _ocv(params: CellParams, soc: float, temp_c: float) -> float:
    return float(_ocv_numpy(params, np.array([soc]), np.array([temp_c]))[1][0])


def _r_dc(params: CellParams, temp_c: float, cell_a: float, soc: float) -> float:
    t, i, s = np.array([temp_c]), np.array([cell_a]), np.array([soc])
    r = _np_interp3(params, "r0_ohm", t, i, s) + _np_interp3(params, "r1_ohm", t, i, s)
    if params.r2_ohm is not None:
        r = r + _np_interp3(params, "r2_ohm", t, i, s)
    return float(r[0])


def cutoff_at(
    params: CellParams, soc_floor: float, current_a: float, temp_c: float, t_max_s: float,
    parallel: int = 1,
) -> tuple[float, float, float]:  # fmt: skip
    """(cutoff, soc at the cut-off, drop) for one operating point (battery current)."""
    cell_a = max(current_a, 0.0) / parallel
    s_c = soc_floor + cell_a * t_max_s / (3600.0 * params.capacity_ah)
    drop = cell_a * _r_dc(params, temp_c, cell_a, s_c)
    return _ocv(params, s_c, temp_c) - drop, s_c, drop


def _bands(edges: Sequence[float], upper_closed: bool) -> list[tuple[float, float, str]]:
    pts = [-math.inf, *edges, math.inf]
    out = []
    for lo, hi in pairwise(pts):
        lo_s = "-inf" if math.isinf(lo) else f"{lo:g}"
        hi_s = "inf" if math.isinf(hi) else f"{hi:g}"
        if upper_closed:
            text = f"({lo_s}, {hi_s}" + (")" if math.isinf(hi) else "]")
        else:
            text = ("(" if math.isinf(lo) else "[") + f"{lo_s}, {hi_s})"
        out.append((lo, hi, text))
    return out


def calibrate_protection(
    params: CellParams,
    soc_floor: float = 0.02,
    *,
    current_edges_a: Sequence[float] = CURRENT_EDGES_A,
    temp_edges_c: Sequence[float] = TEMP_EDGES_C,
    min_temp_c: float | None = None,
    parallel: int = 1,
    source: ProtectionConfig | None = None,
) -> tuple[ProtectionConfig, list[CalibratedCell]]:
    """The calibrated ``[protection]`` section and the derivation of each of its cells.

    ``min_temp_c`` is the corner of the coldest band (default: the set's lowest table
    temperature, below which its resistance is clamped); ``source`` supplies t_max per cell
    (default: the spec's table).
    """
    if not (math.isfinite(soc_floor) and 0.0 <= soc_floor < 0.5):
        raise ConfigError(f"calibrate: soc floor must be in [0, 0.5), got {soc_floor}")
    if parallel < 1:
        raise ConfigError(f"calibrate: parallel must be >= 1, got {parallel}")
    for name, edges in (("current", current_edges_a), ("temperature", temp_edges_c)):
        if not edges or any(b <= a for a, b in pairwise(edges)):
            raise ConfigError(f"calibrate: {name} edges must be strictly increasing")
    src = source or ProtectionConfig(parameters=DEFAULT_PARAMETERS, table=DEFAULT_TABLE)
    by_name = {p.name: p for p in src.parameters}
    t_cold = float(params.rc_temp_c[0]) if min_temp_c is None else float(min_temp_c)
    i_top = float(current_edges_a[-1])
    cells: list[CalibratedCell] = []
    out_params: list[ProtectionParameter] = []
    rows: list[TableRow] = []
    for ci, (ilo, ihi, itext) in enumerate(_bands(current_edges_a, upper_closed=True)):
        i_corners = [max(ilo, 0.0) if math.isfinite(ilo) else 0.0]
        i_corners.append(ihi if math.isfinite(ihi) else i_top)
        i_mid = (i_corners[0] + i_corners[1]) / 2.0 if math.isfinite(ihi) else i_top + 1.0
        for ti, (tlo, thi, ttext) in enumerate(_bands(temp_edges_c, upper_closed=False)):
            t_corners = [tlo if math.isfinite(tlo) else min(t_cold, thi)]
            t_corners.append(thi if math.isfinite(thi) else tlo)
            if math.isinf(tlo):
                t_mid = thi - 1.0
            elif math.isinf(thi):
                t_mid = tlo + 1.0
            else:
                t_mid = (tlo + thi) / 2.0
            hit = [
                r
                for r in src.table
                if all(
                    r.ranges[a].contains(x)
                    for a, x in (("current_a", i_mid), ("temp_c", t_mid))
                    if a in r.ranges
                )
            ]
            sp = by_name[hit[0].param]
            best: tuple[float, float, float, float, float] | None = None
            for ia in i_corners:
                for tc in t_corners:
                    cut, s_c, drop = cutoff_at(params, soc_floor, ia, tc, sp.t_max_s, parallel)
                    if best is None or cut < best[0]:
                        best = (cut, s_c, drop, ia, tc)
            assert best is not None
            cut, s_c, drop, ia, tc = best
            v = min(max(math.floor(cut * 1000.0) / 1000.0, CUTOFF_MIN_V), CUTOFF_MAX_V)
            name = f"C{ci:02d}_{ti:02d}"
            cells.append(
                CalibratedCell(itext, ttext, ia, tc, s_c, cut + drop, drop, v, sp.t_max_s, sp.name)
            )
            out_params.append(ProtectionParameter(name=name, cutoff_v=v, t_max_s=sp.t_max_s))
            rows.append(
                TableRow.model_validate(
                    {"param": name, "ranges": {"current_a": itext, "temp_c": ttext}}
                )
            )
    cfg = src.model_copy(update={"parameters": tuple(out_params), "table": tuple(rows)})
    return ProtectionConfig.model_validate(cfg.model_dump()), cells


def to_toml(cfg: ProtectionConfig, cells: Sequence[CalibratedCell], header: str = "") -> str:
    """``[protection]`` section (parameters and table) with the derivation as comments."""
    lines = [f"# {x}" for x in header.splitlines()]
    lines += ["[protection]", "parameters = ["]
    for p, c in zip(cfg.parameters, cells, strict=True):
        lines.append(
            f'  {{ name = "{p.name}", cutoff_v = {p.cutoff_v!r}, t_max_s = {p.t_max_s!r} }},'
            f"  # I {c.current} A, T {c.temp} degC: corner {c.corner_current_a:g} A / "
            f"{c.corner_temp_c:g} degC, SOC {c.soc_at_cutoff:.4f}, OCV {c.ocv_v:.4f} V - "
            f"{c.drop_v:.4f} V ({c.source_param})"
        )
    lines += ["]", "table = ["]
    for r in cfg.table:
        lines.append(
            f'  {{ param = "{r.param}", ranges = {{ current_a = "{r.ranges["current_a"]}", '
            f'temp_c = "{r.ranges["temp_c"]}" }} }},'
        )
    lines.append("]")
    return "\n".join(lines) + "\n"


__all__ = [
    "CURRENT_EDGES_A",
    "TEMP_EDGES_C",
    "CalibratedCell",
    "calibrate_protection",
    "cutoff_at",
    "to_toml",
]
