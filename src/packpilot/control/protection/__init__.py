"""Condition-dependent discharge protection (US10868343B2; ``spec/discharge_protection.md``):
the cut-off and its sustainable time are looked up from the battery's status every tick, and
the time at or below the active cut-off is accumulated with weight m / t_max until it reaches
m (see ``rules.py``)."""

from fractions import Fraction

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
from packpilot.control.protection import rules
from packpilot.control.protection.controller import (
    METHOD,
    BatteryView,
    CompiledTable,
    ProtectionController,
)
from packpilot.control.protection.rules import ProtectionParams, ProtectionState


def dt_to_ms(dt_s: float) -> Fraction:
    """Exact milliseconds of a tick as the rules count it, snapping float noise (0.1 s ->
    100 ms, 1/3 s -> 1000/3): ``Fraction(dt_s * 1000).limit_denominator(1000)`` for a finite
    ``dt_s >= 0`` below 2**62 ms."""
    dt = float(dt_s)
    if not (dt >= 0.0 and dt < float("inf")):
        raise ValueError(f"dt_s must be a finite number >= 0, got {dt_s}")
    n, d = rules.dt_ms(dt)
    if n < 0:
        raise OverflowError(f"dt_s = {dt_s} s is too long to count exactly")
    return Fraction(int(n), int(d))


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
    "dt_to_ms",
]
