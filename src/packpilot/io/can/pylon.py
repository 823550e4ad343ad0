"""The pack as ONE battery to an inverter: the Pylontech-compatible low-voltage frames.

Byte layouts from ``shared/spec/protocols.md`` (little-endian, 11-bit identifiers, 500 kbit/s,
every frame once a second). This encoder packs bytes with :mod:`struct` on purpose: the
shipped ``pylon.dbc`` decoded by cantools is the second, independent decoder the tests compare
it with. **Current is positive when charging** here (Pylontech), the opposite of PackPilot;
the sign flips in :func:`encode_measurements` and nowhere else.
"""

from __future__ import annotations

import functools
import math
import struct
from dataclasses import dataclass
from importlib import resources
from typing import cast

import can
import cantools
from cantools.database.can import Database

LIMITS_ID = 0x351
SOC_ID = 0x355
MEAS_ID = 0x356
ALARMS_ID = 0x359
REQUEST_ID = 0x35C
NAME_ID = 0x35E
KEEPALIVE_ID = 0x305
PERIOD_S = 1.0

# 0x359 bit positions (byte 0 and byte 1 as one little-endian 16-bit word; warnings likewise
# in bytes 2-3).
OVER_VOLTAGE = 1 << 1
UNDER_VOLTAGE = 1 << 2
OVER_TEMP = 1 << 3
UNDER_TEMP = 1 << 4
DISCHARGE_OVER_CURRENT = 1 << 7
CHARGE_OVER_CURRENT = 1 << 8
SYSTEM_ERROR = 1 << 11

CHARGE_ENABLE = 1 << 7
DISCHARGE_ENABLE = 1 << 6
FULL_CHARGE_REQUEST = 1 << 3

DEFAULT_NAME = "PACKPLT"


@dataclass(frozen=True, slots=True)
class PackAsBattery:
    """What the inverter is told, SI units, PackPilot's current sign (+ = discharging)."""

    charge_voltage_v: float
    charge_current_a: float
    discharge_current_a: float
    discharge_voltage_v: float
    soc_pct: float
    soh_pct: float
    voltage_v: float
    current_a: float
    temp_c: float
    protection: int = 0
    """0x359 protection bits (the constants above)."""
    warning: int = 0
    modules: int = 1
    name: str = DEFAULT_NAME


def _u16(x: float, scale: float) -> int:
    return 0 if not math.isfinite(x) else min(max(round(x * scale), 0), 0xFFFF)


def _s16(x: float, scale: float) -> int:
    return 0 if not math.isfinite(x) else min(max(round(x * scale), -0x8000), 0x7FFF)


def _msg(frame_id: int, data: bytes, t: float) -> can.Message:
    return can.Message(timestamp=t, arbitration_id=frame_id, is_extended_id=False, data=data)


def encode_limits(p: PackAsBattery, t: float = 0.0) -> can.Message:
    """0x351: CVL, CCL, DCL (magnitudes, never negative), DVL."""
    data = struct.pack(
        "<HhhH",
        _u16(p.charge_voltage_v, 10),
        _s16(max(p.charge_current_a, 0.0), 10),
        _s16(max(p.discharge_current_a, 0.0), 10),
        _u16(p.discharge_voltage_v, 10),
    )
    return _msg(LIMITS_ID, data, t)


def encode_soc(p: PackAsBattery, t: float = 0.0) -> can.Message:
    return _msg(SOC_ID, struct.pack("<HH", _u16(p.soc_pct, 1), _u16(p.soh_pct, 1)), t)


def encode_measurements(p: PackAsBattery, t: float = 0.0) -> can.Message:
    """0x356: voltage, current **positive when charging**, temperature."""
    data = struct.pack("<hhh", _s16(p.voltage_v, 100), _s16(-p.current_a, 10), _s16(p.temp_c, 10))
    return _msg(MEAS_ID, data, t)


def encode_alarms(p: PackAsBattery, t: float = 0.0) -> can.Message:
    data = struct.pack("<HHB", p.protection & 0xFFFF, p.warning & 0xFFFF, min(p.modules, 255))
    return _msg(ALARMS_ID, data + b"PN\x00", t)


def encode_request(p: PackAsBattery, t: float = 0.0) -> can.Message:
    """0x35C: charge enable while some charge current is allowed, discharge likewise."""
    flags = (CHARGE_ENABLE if p.charge_current_a > 0 else 0) | (
        DISCHARGE_ENABLE if p.discharge_current_a > 0 else 0
    )
    return _msg(REQUEST_ID, bytes((flags, 0)), t)


def encode_name(p: PackAsBattery, t: float = 0.0) -> can.Message:
    name = p.name.encode("ascii", "replace")[:8].ljust(8, b" ")
    return _msg(NAME_ID, name, t)


def encode_all(p: PackAsBattery, t: float = 0.0) -> list[can.Message]:
    """The six frames, in identifier order."""
    return [f(p, t) for f in (encode_limits, encode_soc, encode_measurements, encode_alarms,
                              encode_request, encode_name)]  # fmt: skip


@functools.cache
def database() -> Database:
    """The shipped ``pylon.dbc`` (the second decoder)."""
    text = resources.files("packpilot.io.can").joinpath("pylon.dbc").read_text("utf-8")
    return cast(Database, cantools.database.load_string(text, database_format="dbc"))


__all__ = [
    "ALARMS_ID",
    "KEEPALIVE_ID",
    "LIMITS_ID",
    "MEAS_ID",
    "NAME_ID",
    "REQUEST_ID",
    "SOC_ID",
    "PackAsBattery",
    "database",
    "encode_alarms",
    "encode_all",
    "encode_limits",
    "encode_measurements",
    "encode_name",
    "encode_request",
    "encode_soc",
]
