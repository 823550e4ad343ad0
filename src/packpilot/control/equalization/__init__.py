"""Equalization of series battery groups by the Newton-iterated unit balancing Ah."""

from packpilot.config.equalization import EqualizationConfig
from packpilot.control.equalization.controller import (
    EVENT_RESOLUTION_AH,
    METHOD,
    AhUpdate,
    EqualizationController,
    SampleResult,
    StringView,
    balancing_time_s,
    equalizer_current_a,
    formula1,
    formula2,
    lower_median,
    method_for,
    sample_groups,
)

__all__ = [
    "EVENT_RESOLUTION_AH",
    "METHOD",
    "AhUpdate",
    "EqualizationConfig",
    "EqualizationController",
    "SampleResult",
    "StringView",
    "balancing_time_s",
    "equalizer_current_a",
    "formula1",
    "formula2",
    "lower_median",
    "method_for",
    "sample_groups",
]
