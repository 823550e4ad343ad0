"""Staged charging of a multi-battery pack on one busbar (``spec/staged_charging.md``)."""

from packpilot.config.charging import REFERENCE_SERIES, ChargingConfig
from packpilot.control.charging.controller import (
    METHOD,
    ChargingController,
    Stage,
    Volts,
    series_cells,
)

__all__ = [
    "METHOD",
    "REFERENCE_SERIES",
    "ChargingConfig",
    "ChargingController",
    "Stage",
    "Volts",
    "series_cells",
]
