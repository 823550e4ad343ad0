"""Discharge sequencing of parallel batteries behind charge/discharge MOSFET pairs."""

from packpilot.config.sequencing import SequencingConfig
from packpilot.control.sequencing.controller import (
    _EPS_S,
    METHOD,
    SeqMode,
    SeqState,
    SequencingController,
    battery_measurement,
)
from packpilot.control.sequencing.rules import SequencingParams, SequencingState

__all__ = [
    "METHOD",
    "_EPS_S",
    "SeqMode",
    "SeqState",
    "SequencingConfig",
    "SequencingController",
    "SequencingParams",
    "SequencingState",
    "battery_measurement",
]
