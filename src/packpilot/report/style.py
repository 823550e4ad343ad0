"""The report's shared look: battery colours and units read from channel names.

Battery ``b`` has the same colour in every chart of the report and in ``--plot`` (matplotlib's
``C0``, ``C1``, ``C2``, ``C4``, … as hex, so the browser charts match the PNG). ``C3`` is the red
of trips and alarms, so no battery is drawn in it.
"""

from __future__ import annotations

import re

ALARM_COLOR = "#d62728"
"""Trips and alarms (matplotlib's ``tab:red``); no battery is drawn in it."""
BATTERY_COLORS: tuple[str, ...] = (
    "#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22",
    "#17becf",
)  # fmt: skip
"""matplotlib's C0, C1, C2, C4 … C9."""


def battery_color(b: int) -> str:
    """Battery ``b``'s colour, the same in every chart, never the alarm colour."""
    return BATTERY_COLORS[b % len(BATTERY_COLORS)]


_UNITS = (
    ("_mv", "mV"),
    ("_v", "V"),
    ("_a", "A"),
    ("_ah", "Ah"),
    ("_wh", "Wh"),
    ("_w", "W"),
    ("_j", "J"),
    ("_s", "s"),
    ("_c", "°C"),
    ("_ohm", "Ω"),
)


def unit_of(name: str) -> str:
    """The SI unit a name's suffix announces ('' when it has none)."""
    base = re.sub(r"_g\d+$", "", name)
    for suffix, unit in _UNITS:
        if base.endswith(suffix):
            return unit
    return ""


__all__ = ["ALARM_COLOR", "BATTERY_COLORS", "battery_color", "unit_of"]
