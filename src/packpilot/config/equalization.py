"""``[equalization]``: the Newton-iterated unit-balancing-Ah equalizer of series groups."""

from __future__ import annotations

import math
from typing import Literal, Self

from pydantic import (
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from packpilot.config.base import GROUP_DV_MAX_V, MAX_CURRENT_A, Strict

MIN_PERIOD_S = 1e-4
"""Shortest T1, T2 or sampling period: the shortest control period (``sim.dt_s``); a shorter
one only multiplies the work per step."""

TimeMode = Literal["string_current", "fixed_current"]
Equalizer = Literal["unidirectional", "bidirectional"]
AhPer = Literal["cell", "group"]


class EqualizationConfig(Strict):
    """Settings of the Newton-iterated unit-balancing-Ah equalizer (TOML section
    ``[equalization]``). The patent gives no values except N ∈ [0, 1] Ah and T1 > T2; the
    defaults are the spec's placeholders."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dv_set_v: float = Field(
        0.005,
        gt=0.0,
        le=GROUP_DV_MAX_V,
        description="Preset group voltage difference ΔV_set (V). A group lags when "
        "V_avg − V_g exceeds it; must be > 0 so that at least one group always decays.",
    )
    t1_s: float = Field(
        120.0,
        description="First set time T1 (s): how long ΔV_g > ΔV_set must persist before formula "
        "1 raises AH_g; repeats every T1 while it persists. Must be longer than t2_s.",
    )
    t2_s: float = Field(
        60.0,
        description="Second set time T2 (s): how long ΔV_g < ΔV_set must persist before "
        "formula 2 halves AH_g; repeats every T2 while it persists.",
    )
    n_ah: float = Field(
        0.5,
        ge=0.0,
        le=1.0,
        description="Newton iteration value N (Ah), 0..1: the ceiling and fixed point of AH_g "
        "under formula 1, i.e. the most extra charge one update can grant a group.",
    )
    sample_period_s: float = Field(
        1.0,
        le=3600.0,
        description="Sampling period Ts (s) of the group voltages; steps shorter than this "
        "accumulate until a sample is due.",
    )
    time_mode: TimeMode = Field(
        "string_current",
        description="Balancing-time formula: 'string_current' t = 3600·AH/|I_string| "
        "(equalizer current follows the string current, clamped to equalizer_max_a); "
        "'fixed_current' t = 3600·AH/fixed_current_a.",
    )
    min_current_a: float = Field(
        0.5,
        ge=0.0,
        le=MAX_CURRENT_A,
        description="Minimum |string current| (A) for balancing (charging or discharging); "
        "below it the equalizers idle and their remaining time is held.",
    )
    equalizer_max_a: float = Field(
        2.0,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="Rated output current of one group equalizer (A); the string current is "
        "clamped to it in string_current mode.",
    )
    fixed_current_a: float = Field(
        1.0,
        gt=0.0,
        le=MAX_CURRENT_A,
        description="Fixed equalizer output current I_eq (A) used in fixed_current mode.",
    )
    balance_at_rest: bool = Field(
        False,
        description="fixed_current mode only: balance even when |I_string| < min_current_a "
        "(equalizer powered independently of the string current).",
    )
    max_balance_time_s: float | None = Field(
        None,
        description="Removed (issue #15): a balancing time is no longer clamped; what one "
        "update period cannot deliver is owed and carried over. Must be unset.",
    )
    ah_per: AhPer = Field(
        "cell",
        description="Where the unit balancing Ah is kept: 'cell' (the claims: every cell of "
        "every series group, updated from its group's voltage difference, S41 over all cells) "
        "or 'group' (one per group, the spec's earlier [REC]). With group voltages and one "
        "equalizer per group (this plant) both give the same commands: the cells of a group "
        "share its ΔV and, in series, its equalizer's charge.",
    )
    equalizer: Equalizer = Field(
        "unidirectional",
        description="Equalizer hardware. 'bidirectional' shifts a string's currents by their "
        "median so that, when most groups would be charged, the few leading groups are "
        "discharged instead: same relative charge per group, less converter throughput.",
    )

    @field_validator("dv_set_v")
    @classmethod
    def _dv_positive(cls, v: float) -> float:
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"dv_set_v must be a positive voltage in V (got {v})")
        return v

    @field_validator("t1_s", "t2_s", "sample_period_s")
    @classmethod
    def _time_positive(cls, v: float, info: ValidationInfo) -> float:
        name = info.field_name
        if not (math.isfinite(v) and v >= MIN_PERIOD_S):
            raise ValueError(f"{name} must be a time of at least {MIN_PERIOD_S:g} s (got {v})")
        return v

    @field_validator("n_ah")
    @classmethod
    def _n_range(cls, v: float) -> float:
        if not (math.isfinite(v) and 0.0 <= v <= 1.0):
            raise ValueError(f"n_ah (Newton iteration value) must be within 0..1 Ah (got {v})")
        return v

    @field_validator("min_current_a")
    @classmethod
    def _min_current(cls, v: float) -> float:
        if not (math.isfinite(v) and v >= 0.0):
            raise ValueError(f"min_current_a must be >= 0 A (got {v})")
        return v

    @field_validator("equalizer_max_a", "fixed_current_a")
    @classmethod
    def _current_positive(cls, v: float, info: ValidationInfo) -> float:
        name = info.field_name
        if not (math.isfinite(v) and v > 0.0):
            raise ValueError(f"{name} must be a positive current in A (got {v})")
        return v

    @field_validator("max_balance_time_s")
    @classmethod
    def _clamp_removed(cls, v: float | None) -> float | None:
        if v is not None:
            raise ValueError(
                f"max_balance_time_s (got {v}) was removed: balancing times are no longer "
                "clamped, the charge one update period cannot deliver is owed and carried "
                "over (issue #15, docs/equalization.md); leave it unset"
            )
        return v

    @model_validator(mode="after")
    def _cross_checks(self) -> Self:
        if self.t1_s <= self.t2_s:
            raise ValueError(
                f"t1_s ({self.t1_s}) must be longer than t2_s ({self.t2_s}): the method "
                "requires T1 > T2 so that AH grows slowly and decays fast"
            )
        if self.fixed_current_a > self.equalizer_max_a:
            raise ValueError(
                f"fixed_current_a ({self.fixed_current_a}) must not exceed equalizer_max_a "
                f"({self.equalizer_max_a})"
            )
        if self.balance_at_rest and self.time_mode != "fixed_current":
            raise ValueError(
                "balance_at_rest requires time_mode = 'fixed_current' (in string_current mode "
                "the equalizer current is the string current, zero at rest)"
            )
        return self


__all__ = ["AhPer", "EqualizationConfig", "Equalizer", "TimeMode"]
