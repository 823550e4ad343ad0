"""``[soc]``: the BMS's own state-of-charge estimate (coulomb counting + OCV after a rest)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import DETECT_MAX_A, MAX_TIME_S, Strict, load_section_model

VoltageSource = Literal["min", "avg"]


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


class SocConfig(Strict):
    """Settings of the SOC estimator (the OCV table itself comes from the cell set)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rest_current_a: float = Field(
        default=0.1, description="A battery rests while |current| is below this (A, > 0)."
    )
    rest_time_s: float = Field(
        default=600.0,
        description="Rest needed before an OCV correction, and between corrections (s, > 0); "
        "long enough for the RC overpotentials to decay (several time constants).",
    )
    blend: float = Field(
        default=1.0,
        description="Weight of the OCV reading in a correction (0..1; 1 = replace).",
    )
    voltage: VoltageSource = Field(
        default="min",
        description="Cell voltage read against the OCV table: 'min' (the weakest cell, which "
        "empties first in a series string) or 'avg' (battery voltage / series cells).",
    )

    @model_validator(mode="after")
    def _check(self) -> SocConfig:
        if not (_finite(self.rest_current_a) and 0.0 < self.rest_current_a <= DETECT_MAX_A):
            raise ValueError(
                f"rest_current_a must be > 0 and <= {DETECT_MAX_A:g} A, got {self.rest_current_a}"
            )
        if not (_finite(self.rest_time_s) and 0.0 < self.rest_time_s <= MAX_TIME_S):
            raise ValueError(f"rest_time_s must be > 0 s, got {self.rest_time_s}")
        if not (_finite(self.blend) and 0.0 <= self.blend <= 1.0):
            raise ValueError(f"blend must be within 0..1, got {self.blend}")
        return self

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<soc>") -> SocConfig:
        return load_section_model(cls, data, "soc", source)


__all__ = ["SocConfig", "VoltageSource"]
