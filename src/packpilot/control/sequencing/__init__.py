"""Discharge sequencing of parallel batteries behind charge/discharge MOSFET pairs."""

from packpilot.config.sequencing import SequencingConfig
from packpilot.control.sequencing.controller import (
    METHOD,
    SeqMode,
    SeqState,
    SequencingController,
    battery_measurement,
)
from packpilot.control.sequencing.rules import SequencingParams, SequencingState

__all__ = [
    "METHOD",
    "SeqMode",
    "SeqState",
    "SequencingConfig",
    "SequencingController",
    "SequencingParams",
    "SequencingState",
    "battery_measurement",
]
