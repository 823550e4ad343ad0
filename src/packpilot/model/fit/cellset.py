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

from packpilot.model.cell import CellParams, load_parameter_set, params_to_dict
from packpilot.model.fit.validate import Validation

LAW_TEMPS_C = np.arange(-20.0, 61.0, 10.0)
"""Temperature axis of a fitted resistance-temperature law (clamped outside)."""


def fitted_params(v: Validation, name: str, chemistry: str) -> CellParams:
    """A :class:`CellParams` of the fitted values on the chemistry's template."""
    r = v.result
    base = load_parameter_set(chemistry)
    vals = r.values
    temps, f = temperature_law(vals.b_k, vals.t_ref_c, base)

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
        r0_ohm=table(vals.r0_ohm), r1_ohm=table(r1),
        c1_f=table(tau1 / r1) / f[:, None, None] ** 2, provenance=_provenance(v, chemistry),
        **extra,
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
        f"Fitted by packpilot fit to {logs}; {ocv}dU/dT, thermal data and voltage limits from "
        f"{chemistry}; verdict: {v.verdict}. See notes."
    )


def fit_notes(v: Validation, chemistry: str) -> dict[str, Any]:
    """The fit's account, stored in the file's ``notes`` (read by people, ignored by the
    loader)."""
    r = v.result
    return {
        "verdict": v.verdict,
        "reasons": v.reasons,
        "parameters": {k: asdict(p) for k, p in r.params.items()},
        "initial_soc": {k: asdict(p) for k, p in r.soc0.items()},
        "not_identifiable": r.flags(),
        "window": asdict(r.window),
        "ocv": _ocv_notes(v, chemistry),
        "reference_temp_c": r.values.t_ref_c,
        "assumptions": [
            *r.assumptions,
            f"OCV: {r.ocv_note}",
            f"template set for what logs cannot tell: {chemistry}",
            *_law_note(v, chemistry),
            "per series cell: the battery's voltage / series cells (the average cell); "
            "capacity and resistances are those of one series element (its parallel cells "
            "together)",
        ],
        "notes": r.notes,
        "validation": [
            {"log": c.name, "split_t_s": c.split_t_s, "heldout_rmse_v": c.rmse_v,
             "heldout_max_err_v": c.max_err_v, "noise_floor_v": c.noise_floor_v,
             "baseline_rmse_v": c.baseline_rmse_v, "skill": c.skill, "soc_swing": c.soc_swing,
             "time_to_v": {f"{lv:g}": list(mp) for lv, mp in c.crossings.items()}}
            for c in v.checks
        ],
        "fit_cpu_s": r.fit_time_s,
        "rmse_train_v": r.rmse_v,
        "n_rc": r.n_rc,
    }


def cellset_dict(v: Validation, name: str, chemistry: str) -> dict[str, Any]:
    """The JSON structure to write: the parameter set and its ``notes``."""
    out = params_to_dict(fitted_params(v, name, chemistry))
    out["notes"] = fit_notes(v, chemistry)
    return out


__all__ = ["cellset_dict", "fit_notes", "fitted_params", "temperature_law"]
