"""Condition-dependent discharge protection (US10868343B2; ``spec/discharge_protection.md``):
the cut-off and its sustainable time are looked up from the battery's status every tick, and
the time at or below the active cut-off is accumulated with weight m / t_max until it reaches
m (see ``rules.py``)."""

from packpilot.config.protection import (
    AXES,
    CUTOFF_MAX_V,
    CUTOFF_MIN_V,
    DEFAULT_PARAMETERS,
    DEFAULT_TABLE,
    AxisRange,
    ProtectionConfig,
    ProtectionParameter,
    TableRow,
    check_coverage,
)
from packpilot.control.protection.controller import (
    METHOD,
    BatteryView,
    CompiledTable,
    ProtectionController,
)
from packpilot.control.protection.rules import ProtectionParams, ProtectionState

__all__ = [
    "AXES",
    "CUTOFF_MAX_V",
    "CUTOFF_MIN_V",
    "DEFAULT_PARAMETERS",
    "DEFAULT_TABLE",
    "METHOD",
    "AxisRange",
    "BatteryView",
    "CompiledTable",
    "ProtectionConfig",
    "ProtectionController",
    "ProtectionParameter",
    "ProtectionParams",
    "ProtectionState",
    "TableRow",
    "check_coverage",
]
