"""``[charging]``: staged charging of a multi-battery pack (``spec/staged_charging.md``).

Voltages are per battery (``voltage_basis = "battery"``) or per series cell (``"cell"``); the
pack-dependent resolution (series count, battery volts) is done when the method is built
(:func:`packpilot.control.charging.controller.build`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import (
    CELL_V_FULL_MIN_V,
    CELL_V_MAX_V,
    DETECT_DELAY_MAX_S,
    MAX_CURRENT_A,
    MAX_VOLTAGE_V,
    OHM_MAX,
    SPREAD_MAX_V,
    Strict,
    load_section_model,
)

REFERENCE_SERIES = 30
"""Series cells of the ~100 V battery the battery-level defaults were written for; with
``voltage_basis = "cell"`` an unset voltage setting defaults to its battery value / 30."""

VOLTAGE_FIELDS: tuple[str, ...] = (
    "delta_v1_v",
    "d1_v",
    "vc1_margin_v",
    "vc2_margin_v",
    "vc3_margin_v",
    "step_v",
    "delta_v2_v",
    "eps_eq_v",
    "reach_tol_v",
    "v_sat_v",
    "overvoltage_margin_v",
    "s40_hysteresis_v",
)
"""Settings that scale with the series count when ``voltage_basis = "cell"``."""

SCALED_BY_DELTA_V1: dict[str, float] = {"d1_v": 1.0 / 3.0, "eps_eq_v": 1.0 / 6.0}
"""Unset, these default to min(their default, share × ΔV1): both must stay below ΔV1, and the
source lists ΔV1 = 1, 3, 5, 8, 10 or 0.5 V (spec/staged_charging.md, parameter table). At the
default ΔV1 = 3 V the shares give exactly the fixed defaults (d1 = 1 V, the example's 90 → 89 V;
eps_eq = 0.5 V), so every ΔV1 ≥ 3 V keeps them and only a smaller ΔV1 scales them down
(0.5 V → d1 = 0.167 V, eps_eq = 0.083 V) instead of being refused (issue #24 item 6)."""


class ChargingConfig(Strict):
    """Staged-charging settings. Voltages are per battery (``voltage_basis = "battery"``, the
    spec's ~100 V example values) or per series cell (``"cell"``, multiplied by each battery's
    series-group count)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    voltage_basis: Literal["battery", "cell"] = Field(
        default="battery",
        description="'battery': voltage settings are battery volts; 'cell': volts per series "
        "cell, multiplied by the battery's series count (unset ones default to the battery "
        "value / 30).",
    )
    delta_v1_v: float = Field(
        default=3.0,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="ΔV1, first voltage threshold: V2 − Vr1 stays below it.",
    )
    d1_v: float = Field(
        default=1.0,
        ge=0.0,
        le=SPREAD_MAX_V,
        description="Vr1 = V2 − d1 (first regulation voltage); d1 < ΔV1. Unset: min(1 V, ΔV1/3).",
    )
    vc1_margin_v: float = Field(
        default=3.0,
        ge=0.0,
        le=SPREAD_MAX_V,
        description="Vc1 = Vr1 + this (S20 charging voltage, ≥ Vr1).",
    )
    vc2_margin_v: float = Field(
        default=0.0,
        ge=0.0,
        le=SPREAD_MAX_V,
        description="Vc2 = Vt + this (S30 charging voltage, ≥ Vt).",
    )
    vc3_margin_v: float = Field(
        default=0.0,
        ge=0.0,
        le=SPREAD_MAX_V,
        description="Vc3 = Vr2 + this (S40 charging voltage, ≥ Vr2).",
    )
    target_mode: Literal["levels", "saturation"] = Field(
        default="levels",
        description="S30 target Vt when no third level exists: 'levels' = V2 + step_v, "
        "'saturation' = V_sat. With a third level, Vt is that level in both modes.",
    )
    step_v: float = Field(
        default=10.0, gt=0.0, le=SPREAD_MAX_V, description="Vt = V2 + step_v in 'levels' mode."
    )
    delta_v2_v: float = Field(
        default=10.0,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="ΔV2: all batteries equal and V_sat − V > ΔV2 → S40 step to V + ΔV2.",
    )
    s40_hysteresis_v: float = Field(
        default=0.0,
        ge=0.0,
        le=SPREAD_MAX_V,
        description="Hysteresis of the S40 test, added to ΔV2: S40 when V_sat − V > ΔV2 + this. "
        "Default 0: the source's test exactly (issue #15 §3). A CV step that ended within "
        "reach_tol of its Vr2 counts as at Vr2, so no extra tiny S40 step follows without it.",
    )
    eps_eq_v: float = Field(
        default=0.5,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="Equal-voltage tolerance: widest span of one level; < ΔV1. Unset: "
        "min(0.5 V, ΔV1/6).",
    )
    reach_tol_v: float = Field(
        default=0.5,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="A CV target counts as reached within this (CV approaches it only "
        "asymptotically); also the 'at V_sat' band.",
    )
    v_sat_v: float = Field(
        default=120.0,
        ge=CELL_V_FULL_MIN_V,
        le=MAX_VOLTAGE_V,
        description="V_sat, saturated battery voltage.",
    )
    overvoltage_margin_v: float = Field(
        default=1.0,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="Terminal voltage above V_sat + this opens the relay.",
    )
    charger_current_limit_a: float = Field(
        default=20.0,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="Current limit commanded to the charger (A).",
    )
    battery_current_limit_a: float | None = Field(
        default=None,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="Optional charge-current limit per connected battery (A): the charger is "
        "commanded min(charger_current_limit_a, n_connected x this), so a stage that charges "
        "few batteries does not push the whole charger current through them.",
    )
    current_law: Literal["constant", "sqrt"] = Field(
        default="constant",
        description="Charger current per stage. 'constant': charger_current_limit_a whatever "
        "the number of connected batteries. 'sqrt': min(charger_current_limit_a, "
        "I_full x sqrt(n/N)) with n batteries connected out of the N still to charge, so "
        "every stage heats the batteries at the same total I^2 R rate (the least I^2 R heat "
        "for a given charge time, see docs/staged_charging.md).",
    )
    full_current_a: float | None = Field(
        default=None,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="I_full of current_law = 'sqrt': the current when all N batteries still "
        "to charge are connected (A); default charger_current_limit_a. A value above the "
        "charger limit raises the current of the small stages, the charger limit still caps it.",
    )
    termination_current_a: float = Field(
        default=1.0,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="A battery at V_sat whose charge current has fallen to this is full (A).",
    )
    cell_v_limit_v: float = Field(
        default=4.2,
        ge=CELL_V_FULL_MIN_V,
        le=CELL_V_MAX_V,
        description="Max cell voltage (per cell, never scaled): opens relay.",
    )
    r_comp_initial_ohm: float = Field(
        default=0.0,
        ge=0.0,
        le=OHM_MAX,
        description="Initial internal-resistance estimate for IR compensation (Ω per battery).",
    )
    r_comp_adapt: bool = Field(
        default=True, description="Learn each battery's resistance from current steps."
    )
    r_est_min_step_a: float = Field(
        default=2.0,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="Smallest current step used to estimate resistance (A).",
    )
    r_est_gain: float = Field(
        default=0.5, gt=0.0, le=1.0, description="Filter gain of the resistance estimate (0..1]."
    )
    r_settle_s: float = Field(
        default=60.0,
        ge=0.0,
        description="Window of the settled R estimate (needs 2 windows of steady current after "
        "a step; about 2 RC time constants; 0 = step estimate only).",
    )
    r_settle_max_ratio: float = Field(
        default=4.0,
        ge=1.0,
        le=1000.0,
        description="A settled R above this multiple of the step R is rejected as corrupted.",
    )
    r_comp_max_ohm: float = Field(
        default=1.0,
        gt=0.0,
        le=OHM_MAX,
        description="Estimates above this are rejected as implausible (Ω).",
    )
    dock_rest_s: float = Field(
        default=2.0,
        ge=0.0,
        description="After docking, all relays stay open and the charger off this long so the "
        "first sort uses rest voltages (no I·R) and the relay opening teaches R.",
    )
    charger_status_timeout_s: float = Field(
        default=5.0,
        gt=0.0,
        le=DETECT_DELAY_MAX_S,
        description="Docked with no charger status this long → Fault.",
    )
    charger_fault_clear_s: float = Field(
        default=5.0,
        ge=0.0,
        description="Charger must report healthy this long after a fault before charging resumes.",
    )
    aux_soc_floor: float = Field(
        default=0.3,
        ge=0.0,
        lt=1.0,
        description="Aux battery is charged whenever below this (undocked only with "
        "aux_charge_from_bus).",
    )
    aux_soc_target: float = Field(
        default=0.9, gt=0.0, le=1.0, description="Aux battery is charged to this while docked."
    )
    aux_soc_hysteresis: float = Field(
        default=0.05, ge=0.0, lt=0.5, description="SOC hysteresis of aux charging start/stop."
    )
    aux_charge_current_a: float = Field(
        default=5.0, gt=0.0, le=MAX_CURRENT_A, description="DC/DC current into the aux battery (A)."
    )
    aux_charge_from_bus: bool = Field(
        default=False,
        description="Also charge the aux battery while undocked, from the traction bus, when "
        "its SOC is below aux_soc_floor. Off by default: the source charges battery 230 from "
        "the dock only (through its relay and module 140).",
    )
    aux_cv_v: float = Field(
        default=14.4,
        gt=0.0,
        le=MAX_VOLTAGE_V,
        description="CV limit of the aux battery's terminal voltage (V).",
    )
    aux_cv_band_v: float = Field(
        default=0.2,
        gt=0.0,
        le=SPREAD_MAX_V,
        description="Aux current tapers linearly to 0 over this band (V).",
    )

    @model_validator(mode="before")
    @classmethod
    def _defaults(cls, data: Any) -> Any:
        """Fill the unset voltage settings: per-cell basis → the battery default / 30; then
        ``d1_v`` and ``eps_eq_v`` scale down with a small ΔV1 (:data:`SCALED_BY_DELTA_V1`)."""
        if not isinstance(data, dict):
            return data
        out = dict(data)
        per_cell = out.get("voltage_basis") == "cell"
        for name in VOLTAGE_FIELDS:
            if name not in out and per_cell:
                default = cls.model_fields[name].default
                out[name] = float(default) / REFERENCE_SERIES
        dv1 = data.get("delta_v1_v")
        if isinstance(dv1, int | float) and not isinstance(dv1, bool) and dv1 > 0:
            for name, share in SCALED_BY_DELTA_V1.items():
                if name not in data:
                    base = float(cls.model_fields[name].default)
                    base /= REFERENCE_SERIES if per_cell else 1.0
                    out[name] = min(base, share * float(dv1))
        return out

    @model_validator(mode="after")
    def _check(self) -> ChargingConfig:
        for name in (*VOLTAGE_FIELDS, "charger_current_limit_a", "termination_current_a"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"{name} must be a finite number")
        if self.eps_eq_v >= self.delta_v1_v:
            raise ValueError(
                f"eps_eq_v ({self.eps_eq_v}) must be smaller than delta_v1_v ({self.delta_v1_v})"
            )
        if self.d1_v >= self.delta_v1_v:
            raise ValueError(
                f"d1_v ({self.d1_v}) must be smaller than delta_v1_v ({self.delta_v1_v}): "
                "the spec requires V2 − Vr1 < ΔV1"
            )
        per_battery = self.battery_current_limit_a
        if per_battery is not None and self.termination_current_a >= per_battery:
            raise ValueError(
                f"termination_current_a ({self.termination_current_a}) must be smaller than "
                f"battery_current_limit_a ({per_battery})"
            )
        full = self.full_current_a
        if full is not None and not math.isfinite(full):
            raise ValueError("full_current_a must be a finite number")
        if full is not None and self.termination_current_a >= full:
            raise ValueError(
                f"termination_current_a ({self.termination_current_a}) must be smaller than "
                f"full_current_a ({full})"
            )
        if self.termination_current_a >= self.charger_current_limit_a:
            raise ValueError(
                f"termination_current_a ({self.termination_current_a}) must be smaller than "
                f"charger_current_limit_a ({self.charger_current_limit_a})"
            )
        if self.aux_soc_floor >= self.aux_soc_target:
            raise ValueError(
                f"aux_soc_floor ({self.aux_soc_floor}) must be below aux_soc_target "
                f"({self.aux_soc_target})"
            )
        if self.r_comp_initial_ohm > self.r_comp_max_ohm:
            raise ValueError(
                f"r_comp_initial_ohm ({self.r_comp_initial_ohm}) must not exceed "
                f"r_comp_max_ohm ({self.r_comp_max_ohm})"
            )
        return self

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<charging>") -> ChargingConfig:
        return load_section_model(cls, data, "charging", source)


__all__ = ["REFERENCE_SERIES", "SCALED_BY_DELTA_V1", "VOLTAGE_FIELDS", "ChargingConfig"]
