"""``[plausibility]``: thresholds and delays of the sensor and switch plausibility monitor."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import (
    CELL_V_MAX_V,
    DETECT_DELAY_MAX_S,
    GROUP_DV_MAX_V,
    MAX_TIME_S,
    Strict,
    load_section_model,
)


def _finite(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


ENVELOPE: dict[str, tuple[float, float]] = {
    "cell_v_range": (0.0, 2 * CELL_V_MAX_V),
    "temp_range_c": (-100.0, 300.0),
    "current_range_c": (-1000.0, 1000.0),
    "soc_range": (-1.0, 2.0),
}
"""Where each plausibility range may lie: beyond this no sensor reading is physical."""

UPPER: dict[str, float] = {
    "nonfinite_delay_s": DETECT_DELAY_MAX_S,
    "range_delay_s": DETECT_DELAY_MAX_S,
    "max_sample_age_s": DETECT_DELAY_MAX_S,
    "sum_delay_s": DETECT_DELAY_MAX_S,
    "switch_delay_s": DETECT_DELAY_MAX_S,
    "stuck_time_s": 3600.0,
    "stuck_temp_time_s": 86_400.0,
    "stuck_current_c": 10.0,
    "sum_tolerance_v_per_group": GROUP_DV_MAX_V,
    "clear_after_s": MAX_TIME_S,
}
"""The physical range's upper end of each delay and threshold (docs/safety.md, "Physical
ranges"): a detection delay beyond a minute, a stuck window beyond an hour (a day for the
slow temperature), a stuck current beyond 10 C or a sum tolerance beyond 1 V per group means
the check never fires. A long clear time only keeps a fault latched (safe)."""


class PlausibilityConfig(Strict):
    """Thresholds and delays of the plausibility checks (defaults: Li-ion, see docs/safety.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    cell_v_range: tuple[float, float] = Field(
        default=(0.5, 5.0),
        description="Plausible cell voltage (V); groups and batteries scale it by their series "
        "cells. Below: a broken sense wire; above: impossible for Li-ion.",
    )
    temp_range_c: tuple[float, float] = Field(
        default=(-40.0, 125.0), description="Plausible temperature (degC): NTC open / short."
    )
    current_range_c: tuple[float, float] = Field(
        default=(-60.0, 120.0),
        description="Plausible battery current in C (positive = discharge): sensor saturation.",
    )
    soc_range: tuple[float, float] = Field(
        default=(-0.1, 1.1), description="Plausible reported SOC (0..1 with a margin)."
    )
    nonfinite_delay_s: float = Field(
        default=0.5, description="A NaN / inf must persist this long to be a fault (s)."
    )
    range_delay_s: float = Field(
        default=0.5, description="An out-of-range value must persist this long (s)."
    )
    stuck_time_s: float | None = Field(
        default=60.0,
        description="A voltage unchanged this long under current is stuck (s; None = off).",
    )
    stuck_temp_time_s: float | None = Field(
        default=900.0,
        description="A temperature unchanged this long under current is stuck (s; None = off). "
        "Long, because a quantised sensor at thermal equilibrium may legitimately not move.",
    )
    stuck_current_c: float = Field(
        default=0.5,
        description="Battery current (C, either sign) above which its voltages must move.",
    )
    max_sample_age_s: float = Field(
        default=2.0,
        description="Stale when a measurement's sample_age_s exceeds this (s), if reported.",
    )
    sum_tolerance_v_per_group: float = Field(
        default=0.05,
        description="Allowed |battery V - sum of group V| per series group (V): sense-wire and "
        "interconnect drops.",
    )
    sum_delay_s: float = Field(default=1.0, description="A sum mismatch must persist (s).")
    switch_delay_s: float = Field(
        default=0.5,
        description="Switch feedback may lag its command this long before it is a fault (s): "
        "relay bounce and actuation time, one control period.",
    )
    clear_after_s: float = Field(
        default=5.0,
        description="A latched sensor fault clears after this long of plausible data (s).",
    )

    @model_validator(mode="after")
    def _check(self) -> PlausibilityConfig:
        for name, (least, most) in ENVELOPE.items():
            lo, hi = getattr(self, name)
            if not (_finite(lo) and _finite(hi) and lo < hi):
                raise ValueError(f"{name} must be (low, high) finite with low < high, got {lo, hi}")
            if not least <= lo < hi <= most:
                raise ValueError(
                    f"{name} ({lo:g}, {hi:g}) must lie within {least:g}..{most:g}: a wider "
                    "range calls every reading plausible"
                )
        for name, most in UPPER.items():
            v = getattr(self, name)
            if name in ("stuck_time_s", "stuck_temp_time_s"):
                if v is not None and not (_finite(v) and 0.0 < v <= most):
                    raise ValueError(
                        f"{name} must be > 0 s and <= {most:g} s, or omitted to switch it off; "
                        f"got {v}"
                    )
                continue
            if not (_finite(v) and 0.0 <= v <= most):
                raise ValueError(f"{name} must be a finite value >= 0 and <= {most:g}, got {v}")
        return self

    @classmethod
    def load(
        cls, data: Mapping[str, Any] | None, source: str = "<plausibility>"
    ) -> PlausibilityConfig:
        return load_section_model(cls, data, "plausibility", source)


__all__ = ["PlausibilityConfig"]
