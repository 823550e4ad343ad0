"""Sensor and switch plausibility: detect lying measurements and failed switches, fail safe."""

from packpilot.config.plausibility import PlausibilityConfig
from packpilot.control.plausibility.controller import METHOD, PlausibilityMonitor
from packpilot.control.plausibility.rules import KINDS, SENSOR_KINDS, SWITCH_KINDS

__all__ = [
    "KINDS",
    "METHOD",
    "SENSOR_KINDS",
    "SWITCH_KINDS",
    "PlausibilityConfig",
    "PlausibilityMonitor",
]
