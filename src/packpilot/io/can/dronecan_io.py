"""DroneCAN ``uavcan.equipment.power.BatteryInfo`` (data type 1092) to and from CAN frames.

Serialisation is the ``dronecan`` package's own (DSDL, float16, multi-frame transfers with
tail bytes and CRC), so a flight controller reading these frames reads what the package
writes. float16 rounds (49.8 V → 49.8125 V). Current keeps PackPilot's sign (positive =
discharging), as ArduPilot reads a battery monitor's current.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import can
import dronecan

BATTERY_INFO_ID = 1092

IN_USE = 1
CHARGING = 2
CHARGED = 4
TEMP_HOT = 8
TEMP_COLD = 16
OVERLOAD = 32
BAD_BATTERY = 64
NEED_SERVICE = 128
BMS_ERROR = 256
"""``status_flags`` bits of the DSDL."""

SOH_UNKNOWN = 127
KELVIN = 273.15


@dataclass(frozen=True, slots=True)
class BatteryInfo:
    """One BatteryInfo message in SI units (temperatures in degC here, K on the wire)."""

    battery_id: int
    voltage_v: float
    current_a: float
    temp_c: float
    soc_pct: float
    soh_pct: float = math.nan
    remaining_wh: float = math.nan
    full_wh: float = math.nan
    status_flags: int = 0
    model_name: str = "PackPilot"


def _f(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def _pct(x: float, unknown: int) -> int:
    return unknown if not math.isfinite(x) else min(max(round(x), 0), 127)


def encode(
    info: BatteryInfo, node_id: int, transfer_id: int, priority: int = 16, t: float = 0.0
) -> list[can.Message]:
    """The frames of one BatteryInfo broadcast from ``node_id`` (29-bit identifiers)."""
    msg = dronecan.uavcan.equipment.power.BatteryInfo(
        temperature=_f(info.temp_c + KELVIN),
        voltage=_f(info.voltage_v),
        current=_f(info.current_a),
        remaining_capacity_wh=_f(info.remaining_wh),
        full_charge_capacity_wh=_f(info.full_wh),
        status_flags=info.status_flags & 0x7FF,
        state_of_health_pct=_pct(info.soh_pct, SOH_UNKNOWN),
        state_of_charge_pct=_pct(info.soc_pct, 0),
        battery_id=info.battery_id & 0xFF,
        model_name=info.model_name[:31],
    )
    transfer = dronecan.transport.Transfer(
        payload=msg,
        source_node_id=node_id,
        transfer_id=transfer_id & 0x1F,
        transfer_priority=priority,
        service_not_message=False,
    )
    return [
        can.Message(timestamp=t, arbitration_id=f.message_id, is_extended_id=True,
                    data=bytes(f.bytes))
        for f in transfer.to_frames()
    ]  # fmt: skip


def decode(frames: Sequence[can.Message]) -> BatteryInfo:
    """One transfer's frames back into a :class:`BatteryInfo` (``dronecan`` checks the tail
    bytes, toggles and CRC; a wrong transfer raises ``dronecan.transport.TransferError``)."""
    fr = [dronecan.transport.Frame(m.arbitration_id, bytes(m.data)) for m in frames]
    transfer = dronecan.transport.Transfer()
    transfer.from_frames(fr)
    p: Any = transfer.payload
    if transfer.data_type_id != BATTERY_INFO_ID:
        raise ValueError(f"data type {transfer.data_type_id}, expected {BATTERY_INFO_ID}")
    return BatteryInfo(
        battery_id=int(p.battery_id),
        voltage_v=float(p.voltage),
        current_a=float(p.current),
        temp_c=float(p.temperature) - KELVIN,
        soc_pct=float(p.state_of_charge_pct),
        soh_pct=math.nan if p.state_of_health_pct == SOH_UNKNOWN else float(p.state_of_health_pct),
        remaining_wh=float(p.remaining_capacity_wh),
        full_wh=float(p.full_charge_capacity_wh),
        status_flags=int(p.status_flags),
        model_name=bytes(int(x) for x in p.model_name).decode("ascii", "replace"),
    )


__all__ = [
    "BAD_BATTERY",
    "BATTERY_INFO_ID",
    "BMS_ERROR",
    "CHARGED",
    "CHARGING",
    "IN_USE",
    "OVERLOAD",
    "TEMP_COLD",
    "TEMP_HOT",
    "BatteryInfo",
    "decode",
    "encode",
]
