"""Moved to :mod:`packpilot.contract.record` (kept while callers migrate)."""

from packpilot.contract.record import (  # noqa: F401
    BATTERY_CHANNELS,
    Recorder,
    Result,
    StatusValue,
    StepSample,
    Trace,
)
