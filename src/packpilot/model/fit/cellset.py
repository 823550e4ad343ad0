"""The fitted model as a cell parameter file (``packpilot-cell/1``) that a scenario's
``[pack] cell = "fitted.json"`` accepts, with the fit's account in its ``notes`` field: each
parameter's value, uncertainty and identifiability, the data window the set holds for, what
was assumed, and the validation verdict.

What the logs cannot tell comes from the chemistry's template set (a shipped set): the OCV
curve (corrected from the data over the SOC window they cover when they ask for it; the
``notes.ocv`` block says which, where, and what holds outside), dU/dT, the thermal data and
the voltage limits. The resistances are constant in current and SOC; in temperature they
follow the fitted Arrhenius law when the logs spanned temperatures, else the template's R0
temperature dependence normalised at the reference temperature (borrowed, recorded as an
assumption).
"""

from __future__ import annotations

from dataclasses import asdict, replace
from typing import Any

import numpy as np

from packpilot.errors import InputError
from packpilot.model.cell import CellParams, load_parameter_set, params_to_dict
from packpilot.model.fit.fit import NOMINAL_CELL_V
from packpilot.model.fit.validate import Validation
from packpilot.model.thermal import ThermalParams

LAW_TEMPS_C = np.arange(-20.0, 61.0, 10.0)
"""Temperature axis of a fitted resistance-temperature law (clamped outside)."""

# The fitted cell's thermal data: estimated for THAT cell from its fitted capacity (#27: the
# template's, uav_5ah's 50 + 25 J/K and 0.25 W/K for a 5 Ah cell, heated underpowered.log's
# 4 Ah pack to 64.5 degC in a 430 s hover). The same reasoning as fit.py's floors
# (MIN_HEAT_J_PER_K_AH, MIN_HEAT_G_W_PER_K_AH23), with typical values in place of extremes.
SPECIFIC_HEAT_J_PER_G_K = 1.0
"""Specific heat of a Li-ion / LiPo cell with its wrap: measured 0.8-1.3 J/(g K) (fit.py's
floor takes the low end, 0.8); 1.0 is the middle for pouch cells."""
PACK_WH_PER_KG = 150.0
"""Specific energy of a UAV pack, counting what warms with its cells (wrap, tabs, leads): hobby
high-rate LiPo packs are 130-150 Wh/kg (a 3S 4000 mAh pack, 44 Wh, weighs 300-340 g), a bare
high-rate pouch cell up to ~190 (the 95-100 g of a 5 Ah cell). With SPECIFIC_HEAT_J_PER_G_K:
1.0 x 3.7 V / 150 Wh/kg = 24.7 J/(K Ah) (uav_5ah: 75 J/K / 5 Ah = 15 J/(K Ah))."""
PACK_WH_PER_L = 250.0
"""Energy per volume of a UAV pouch pack (a real 3S 2650 mAh pack, 135 x 43 x 22 mm: 230 Wh/L;
fit.py's floor takes the densest cells, 600 Wh/L, for the least surface)."""
PACK_SHAPE_FACTOR = 1.27
"""Outer surface of a pouch pack over that of a cube of its volume: a 6 : 2 : 1 brick (135 x 43
x 22 mm) has 2 (12 + 2 + 6) / 12^(2/3) = 7.6 V^(2/3) against a cube's 6 (the floor's shape).
With PACK_WH_PER_L the real 3S 2650 mAh pack's 6.5e-3 m2 per cell comes out 6.1e-3."""
STILL_AIR_W_PER_M2K = 12.0
"""Heat transfer from the pack's surface to still air: natural convection ~6.5 W/(m2 K)
(1.32 (dT / L)^(1/4) for a ~4 cm body 25 K above ambient) plus radiation ~6 (4 eps sigma T^3,
emissivity 0.9 at 310 K). fit.py's floor takes 5 (convection's low end, no radiation). Airflow
(prop wash, forward flight: forced convection, 25-40 W/(m2 K) at 5-10 m/s) is left out: the
installation decides it, and still air is the hotter case."""
PACK_CELLS_DEFAULT = 4
"""Series cells of the pack whose surface the estimate shares out, when the fit was not told
(``--cells``): UAV packs are 3S-6S; a cell's share of the surface falls as n^(-1/3)."""
SURFACE_BIOT_RATIO = 10.0
"""The cell's conduction to its pack's surface over the surface's to air (Biot number
h t / 2 k ~ 12 x 0.005 / 0.8 < 0.1 for a pouch stack): the surface ("jig") sits at 10/11 of
the cell's rise; the cell-to-air conductance is the surface estimate."""


def thermal_estimate(capacity_ah: float, series_cells: int | None) -> ThermalParams:
    """A fitted cell's thermal data from its capacity: heat capacity = specific heat x pack mass
    per Ah, conductance to air = still air's coefficient x the cell's share of the outer surface
    of a brick-shaped pack of ``series_cells`` cells (one node: the cell and its wrap)."""
    n = series_cells or PACK_CELLS_DEFAULT
    heat_c = SPECIFIC_HEAT_J_PER_G_K * NOMINAL_CELL_V / PACK_WH_PER_KG * 1000.0 * capacity_ah
    volume_m3 = n * NOMINAL_CELL_V * capacity_ah / (PACK_WH_PER_L * 1000.0)
    area_m2 = PACK_SHAPE_FACTOR * 6.0 * volume_m3 ** (2.0 / 3.0) / n
    g = STILL_AIR_W_PER_M2K * area_m2
    surface = g * (1.0 + 1.0 / SURFACE_BIOT_RATIO)
    return ThermalParams(
        cell_heat_capacity_j_per_k=heat_c, jig_heat_capacity_j_per_k=0.0,
        cell_jig_w_per_k=SURFACE_BIOT_RATIO * surface, jig_air_w_per_k=surface, nodes=1,
    )  # fmt: skip


def series_share(v: Validation, series_ohm: float, series_cells: int | None) -> float:
    """Per series cell, the part of the fitted R0 that is the logged battery's leads,
    connectors and shunt (``series_ohm``, the battery's total, given by the user: the logs
    cannot tell it, see :func:`_series_note`); refused when it is not below the fitted R0."""
    s = series_ohm / (series_cells or 1)
    r0 = v.result.values.r0_ohm
    if s > 0.0 and s >= r0:
        raise InputError(
            f"--series-ohm {series_ohm:g} Ohm is {s * 1e3:.3g} mOhm per series cell, not below "
            f"the fitted R0 of {r0 * 1e3:.3g} mOhm (it is a share of the fitted resistance)"
        )
    return s


def fitted_params(
    v: Validation, name: str, chemistry: str, series_cells: int | None = None,
    series_ohm: float = 0.0,
) -> CellParams:  # fmt: skip
    """A :class:`CellParams` of the fitted values on the chemistry's template, with thermal
    data estimated for the fitted cell (:func:`thermal_estimate`), not the template's, and the
    user's share of R0 that heats no cell moved out of the cell (``series_ohm``, the logged
    battery's total; the set carries it per series cell)."""
    r = v.result
    base = load_parameter_set(chemistry)
    vals = r.values
    temps, f = temperature_law(vals.b_k, vals.t_ref_c, base)
    s = series_share(v, series_ohm, series_cells)

    def table(x: float) -> np.ndarray[Any, np.dtype[np.float64]]:
        return np.broadcast_to((x * f)[:, None, None], (len(temps), 2, 2)).copy()

    (r1, tau1), *rest = vals.rc
    extra: dict[str, Any] = {"r2_ohm": None, "c2_f": None}
    if rest:
        r2, tau2 = rest[0]
        extra = {"r2_ohm": table(r2), "c2_f": table(tau2 / r2) / f[:, None, None] ** 2}
    return replace(
        base, name=name, capacity_ah=vals.capacity_ah, ocv_soc=r.ocv_soc, ocv_table_v=r.ocv_v,
        rc_temp_c=temps, rc_current_a=np.array([-1000.0, 1000.0]), rc_soc=np.array([0.0, 1.0]),
        r0_ohm=table(vals.r0_ohm - s), r1_ohm=table(r1), series_ohm=s,
        c1_f=table(tau1 / r1) / f[:, None, None] ** 2, provenance=_provenance(v, chemistry),
        thermal=thermal_estimate(vals.capacity_ah, series_cells), **extra,
    )  # fmt: skip


def temperature_law(b_k: float, t_ref_c: float, template: CellParams) -> tuple[Any, Any]:
    """(temperatures, factor on the fitted resistances): the fitted Arrhenius law when the logs
    spanned temperatures; otherwise the template's R0 temperature dependence (at 50 % SOC and no
    current) below the reference temperature, normalised to 1 there, and 1 above it — borrowed
    and said so in the notes. A constant resistance made the same pack no worse at -10 degC
    than at 25 degC. Not lowered above the reference: the logged packs warmed in flight by an
    amount nobody logged, so the fitted value already holds for a warm pack; lowering it with
    the closed loop's own heating made the same flight's replay 204 mV/cell RMSE off the log
    (51 mV with the flat warm side) on underpowered.log."""
    if b_k > 0:
        f = np.exp(b_k * (1.0 / (LAW_TEMPS_C + 273.15) - 1.0 / (t_ref_c + 273.15)))
        return LAW_TEMPS_C, f
    i0 = int(np.argmin(np.abs(template.rc_current_a)))
    s0 = int(np.argmin(np.abs(template.rc_soc - 0.5)))
    temps = np.asarray(template.rc_temp_c, dtype=np.float64)
    r = np.asarray(template.r0_ohm, dtype=np.float64)[:, i0, s0]
    return temps, np.maximum(r / float(np.interp(t_ref_c, temps, r)), 1.0)


def _law_note(v: Validation, chemistry: str) -> list[str]:
    vals = v.result.values
    if vals.b_k > 0:
        return []
    temps, f = temperature_law(0.0, vals.t_ref_c, load_parameter_set(chemistry))
    at = ", ".join(f"x{float(np.interp(t, temps, f)):.2f} at {t:g} degC" for t in (-10.0, 0.0))
    return [
        f"temperature dependence: none in the logs; below {vals.t_ref_c:.1f} degC the file's "
        f"resistances follow {chemistry}'s R0 temperature law ({at}): borrowed, not fitted; "
        "above it they stay at the fitted values (the logged flights warmed their packs by an "
        "unlogged amount)"
    ]


def _ocv_notes(v: Validation, chemistry: str) -> dict[str, Any]:
    """What the file's OCV table is: the chemistry's default, or the default corrected over
    the SOC window the data covered (knots, correction, one sigma, whether the data set each
    knot) and what it does outside that window."""
    o = v.result.ocv_fit
    if o is None:
        return {"source": f"{chemistry} default", "note": v.result.ocv_note}
    return {
        "source": f"{chemistry} default, corrected from the data",
        "window_soc": list(o.window),
        "knots_soc": o.knots_soc, "correction_v": o.correction_v, "sigma_v": o.sigma_v,
        "resolved": o.resolved, "relaxed_rest_points": o.rest_points,
        "outside_window": "the correction held at its edge value: extrapolated, not fitted",
        "note": v.result.ocv_note,
    }  # fmt: skip


def _provenance(v: Validation, chemistry: str) -> str:
    logs = ", ".join(c.name for c in v.checks)
    o = v.result.ocv_fit
    ocv = (f"OCV {chemistry}'s corrected on SOC {o.window[0]:.2f}-{o.window[1]:.2f} (held at "
           "its edge value outside); " if o is not None else "OCV, ")  # fmt: skip
    return (
        f"Fitted by packpilot fit to {logs}; {ocv}dU/dT and voltage limits from {chemistry}; "
        f"thermal data estimated from the fitted capacity (notes.thermal); verdict: "
        f"{v.verdict}. See notes."
    )


def _thermal_notes(v: Validation, series_cells: int | None) -> dict[str, Any]:
    """The thermal estimate, its inputs, and what became of the fit's own self-heating C, G."""
    q = v.result.values.capacity_ah
    th = thermal_estimate(q, series_cells)
    n = series_cells or PACK_CELLS_DEFAULT
    out: dict[str, Any] = {
        "source": "estimated for the fitted cell from its capacity (not the template's)",
        "cell_heat_capacity_j_per_k": th.cell_heat_capacity_j_per_k,
        "cell_air_w_per_k": th.cell_air_w_per_k,
        "time_constant_s": th.cell_heat_capacity_j_per_k / th.cell_air_w_per_k,
        "specific_heat_j_per_g_k": SPECIFIC_HEAT_J_PER_G_K,
        "pack_wh_per_kg": PACK_WH_PER_KG,
        "pack_wh_per_l": PACK_WH_PER_L,
        "pack_shape_factor": PACK_SHAPE_FACTOR,
        "still_air_w_per_m2k": STILL_AIR_W_PER_M2K,
        "pack_series_cells": n,
        "airflow": "left out (still air, the hotter case): a scenario's [[pack.batteries]] "
        "cooling_scale adds it (2-3 for prop wash, forced convection 25-40 W/(m2 K))",
    }
    p = v.result.params
    if "heat_c_j_per_k" in p:
        out["self_heating_fit"] = {
            "heat_c_j_per_k": p["heat_c_j_per_k"].value,
            "heat_g_w_per_k": p["heat_g_w_per_k"].value,
            "used": False,
            "why": "effective values of the fit's warming term: without a logged temperature "
            "only B/C is seen (B borrowed), and the term also absorbs an unlogged start "
            "temperature and model error (the dronekit tlog's G sits on its floor with a "
            "modelled rise of 72 K); the what-if runs other ambients and durations, so it "
            "uses the physical estimate",
        }
    return out


def _thermal_assumption(v: Validation, series_cells: int | None) -> str:
    t = _thermal_notes(v, series_cells)
    return (
        f"thermal data estimated for this cell, not the template's: heat capacity "
        f"{t['cell_heat_capacity_j_per_k']:.0f} J/K ({SPECIFIC_HEAT_J_PER_G_K:g} J/(g K) x "
        f"3.7 V / {PACK_WH_PER_KG:g} Wh/kg x the fitted capacity), conductance to still air "
        f"{t['cell_air_w_per_k']:.3f} W/K ({STILL_AIR_W_PER_M2K:g} W/(m2 K) over the cell's "
        f"share of a {t['pack_series_cells']}-cell pouch pack at {PACK_WH_PER_L:g} Wh/L); "
        "airflow left out (cooling_scale in the scenario)"
        + ("; the fit's self-heating C and G are not used (notes.thermal)"
           if "self_heating_fit" in t else "")
    )  # fmt: skip


def _series_note(v: Validation, s: float, series_ohm: float) -> str:
    r0 = v.result.values.r0_ohm
    if s > 0.0:
        return (
            f"leads, connectors and shunt: {series_ohm:g} Ohm per battery (--series-ohm) taken "
            f"out of the fitted R0 ({r0 * 1e3:.2f} mOhm per cell): series_ohm "
            f"{s * 1e3:.3f} mOhm per cell drops the voltage but heats no cell; "
            f"{(r0 - s) * 1e3:.2f} mOhm stays in the cell"
        )
    return (
        f"series_ohm: not identifiable, left 0: the fitted R0 ({r0 * 1e3:.2f} mOhm per cell) "
        "includes the logged battery's leads, connectors and current shunt, which heat no "
        "cell; without a logged temperature the logs cannot tell them apart, so in a what-if "
        "all of it heats the cells (hotter by the wiring's share; 2 x 10 cm of 12 AWG lead "
        "alone is 1.0 mOhm per battery). Give --series-ohm (measured) to split it"
    )


def whatif_assumptions(
    v: Validation, series_cells: int | None = None, series_ohm: float = 0.0
) -> list[str]:
    """What the written set assumes for a what-if that the fit itself does not: its thermal
    data and the wiring share of R0 (the report lists them with the fit's assumptions)."""
    s = series_share(v, series_ohm, series_cells)
    return [_thermal_assumption(v, series_cells), _series_note(v, s, series_ohm)]


def fit_notes(
    v: Validation, chemistry: str, series_cells: int | None = None, series_ohm: float = 0.0
) -> dict[str, Any]:
    """The fit's account, stored in the file's ``notes`` (read by people, ignored by the
    loader)."""
    r = v.result
    s = series_share(v, series_ohm, series_cells)
    flags = r.flags() + ([] if s > 0.0 else [_series_note(v, s, series_ohm)])
    return {
        "verdict": v.verdict,
        "reasons": v.reasons,
        "parameters": {k: asdict(p) for k, p in r.params.items()},
        "initial_soc": {k: asdict(p) for k, p in r.soc0.items()},
        "not_identifiable": flags,
        "window": asdict(r.window),
        "ocv": _ocv_notes(v, chemistry),
        "thermal": _thermal_notes(v, series_cells),
        "series_ohm_per_cell": s,
        "reference_temp_c": r.values.t_ref_c,
        "assumptions": [
            *r.assumptions,
            f"OCV: {r.ocv_note}",
            f"template set for what logs cannot tell: {chemistry}",
            *_law_note(v, chemistry),
            *whatif_assumptions(v, series_cells, series_ohm),
            "per series cell: the battery's voltage / series cells (the average cell); "
            "capacity and resistances are those of one series element (its parallel cells "
            "together)",
        ],
        "notes": r.notes,
        "validation": [
            {"log": c.name, "mode": v.mode, "split_t_s": c.split_t_s,
             "held_out_t_s": [c.split_t_s, float(c.t_s[c.test.stop - 1])],
             "judged": v.mode == "time" or c.interior, "heldout_rmse_v": c.rmse_v,
             "heldout_max_err_v": c.max_err_v, "noise_floor_v": c.noise_floor_v,
             "baseline_rmse_v": c.baseline_rmse_v, "skill": c.skill, "soc_swing": c.soc_swing,
             "time_to_v": {f"{lv:g}": list(mp) for lv, mp in c.crossings.items()}}
            for c in v.checks
        ],
        "fit_cpu_s": r.fit_time_s,
        "rmse_train_v": r.rmse_v,
        "n_rc": r.n_rc,
    }


def cellset_dict(
    v: Validation, name: str, chemistry: str, series_cells: int | None = None,
    series_ohm: float = 0.0,
) -> dict[str, Any]:  # fmt: skip
    """The JSON structure to write: the parameter set and its ``notes``. ``series_cells``:
    the logged battery's (for the thermal estimate's pack surface and ``series_ohm``'s share);
    ``series_ohm``: its leads, connectors and shunt up to the logger's voltage sensor (Ohm,
    the battery's total; 0: not split, flagged)."""
    out = params_to_dict(fitted_params(v, name, chemistry, series_cells, series_ohm))
    out["notes"] = fit_notes(v, chemistry, series_cells, series_ohm)
    return out


__all__ = [
    "cellset_dict", "fit_notes", "fitted_params", "series_share", "temperature_law",
    "thermal_estimate", "whatif_assumptions",
]  # fmt: skip
