"""``[supervisor]``: mode thresholds and the relay join limit of the supervised BMS."""

from __future__ import annotations

import math

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import DETECT_DELAY_MAX_S, DETECT_MAX_A, SPREAD_MAX_V, Strict


class SupervisorConfig(Strict):
    """Mode thresholds and the relay join limit (per ~100 V battery; scale with series count)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    init_time_s: float = Field(
        0.5, ge=0, le=DETECT_DELAY_MAX_S, description="plausible samples needed before IDLE"
    )
    discharge_current_a: float = Field(
        0.5, gt=0, le=DETECT_MAX_A, description="pack discharge current that means DISCHARGE mode"
    )
    idle_after_s: float = Field(5.0, ge=0, description="quiet time before DISCHARGE → IDLE")
    join_limit_v: float = Field(
        3.0,
        gt=0,
        le=SPREAD_MAX_V,
        description="largest voltage difference across which a relay may join batteries",
    )
    fault_hold_s: float = Field(
        10.0, ge=0, description="FAULT holds this long after the last fault event"
    )
    shutdown_when_all_tripped: bool = Field(
        True, description="open every path once every traction battery has tripped, undocked"
    )

    @model_validator(mode="after")
    def _check(self) -> SupervisorConfig:
        if not math.isfinite(self.join_limit_v):
            raise ValueError("join_limit_v must be finite")
        return self


__all__ = ["SupervisorConfig"]
