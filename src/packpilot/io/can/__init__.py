"""CAN I/O: the TC/Elcon charger protocol (packaged DBC), a BMS-side charger client, a
charger emulator node, the closed loop's CAN charger link, bus opening and BLF/ASC logging."""

from packpilot.io.can.bus import LOG_SUFFIXES, SIM_EPOCH_S, FrameLog, open_bus
from packpilot.io.can.client import ChargerClient, FrameCounters
from packpilot.io.can.codec import (
    FLAG_NAMES,
    REQUEST_ID,
    STATUS_ID,
    ChargerFlags,
    ChargerRequest,
    FaultFlags,
    FrameError,
    database,
    decode_request,
    decode_status,
    encode_request,
    encode_status,
)
from packpilot.io.can.emulator import ChargerEmulator, ChargerPlant
from packpilot.io.can.link import CanChargerLink

__all__ = [
    "FLAG_NAMES",
    "LOG_SUFFIXES",
    "REQUEST_ID",
    "SIM_EPOCH_S",
    "STATUS_ID",
    "CanChargerLink",
    "ChargerClient",
    "ChargerEmulator",
    "ChargerFlags",
    "ChargerPlant",
    "ChargerRequest",
    "FaultFlags",
    "FrameCounters",
    "FrameError",
    "FrameLog",
    "database",
    "decode_request",
    "decode_status",
    "encode_request",
    "encode_status",
    "open_bus",
]
