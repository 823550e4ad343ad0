"""Absolute safety limits: warn / derate / trip tiers with debounce, delay, hysteresis and latch,
and the published current limits (rules in :mod:`.rules`, config in
:mod:`packpilot.config.limits`)."""

from packpilot.config.limits import (
    DEFAULT_ROWS,
    QUANTITY_DIRECTION,
    TIER_RANK,
    CurveTable,
    DeratingConfig,
    LimitRow,
    LimitsConfig,
)
from packpilot.control.limits.controller import (
    METHOD,
    TIER_EVENT,
    LimitsController,
    method_for,
)

__all__ = [
    "DEFAULT_ROWS",
    "METHOD",
    "QUANTITY_DIRECTION",
    "TIER_EVENT",
    "TIER_RANK",
    "CurveTable",
    "DeratingConfig",
    "LimitRow",
    "LimitsConfig",
    "LimitsController",
    "method_for",
]
