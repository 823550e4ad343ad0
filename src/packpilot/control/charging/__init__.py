"""Staged charging of a multi-battery pack on one busbar (``spec/staged_charging.md``)."""

from packpilot.config.charging import REFERENCE_SERIES, ChargingConfig
from packpilot.control.charging.controller import (
    METHOD,
    ChargingController,
    Plan,
    Stage,
    Volts,
    cluster_levels,
    series_cells,
    stage_current_a,
)

__all__ = [
    "METHOD",
    "REFERENCE_SERIES",
    "ChargingConfig",
    "ChargingController",
    "Plan",
    "Stage",
    "Volts",
    "cluster_levels",
    "series_cells",
    "stage_current_a",
]
