"""DroneCAN ``uavcan.equipment.power.BatteryInfo`` (data type 1092) and ArduPilot's
``BatteryInfoAux`` (20004, cell voltages) to and from CAN frames.

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
BATTERY_INFO_AUX_ID = 20004
"""ArduPilot's ``ardupilot.equipment.power.BatteryInfoAux``: per-cell voltages, cycles."""
BATTERY_PERIODIC_ID = 20011
"""ArduPilot's ``ardupilot.equipment.power.BatteryPeriodic``: design facts and the pack's
current limits (continuous, 30 s burst, charge)."""

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
    soc_stdev_pct: float = math.nan
    """``state_of_charge_pct_stdev`` (percentage points, 0..127; NaN: 0 on the wire)."""


def _f(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def ah_from_wh(wh: float, nominal_voltage_v: float) -> float:
    """Wh → Ah by the nominal voltage, as the BatteryInfoAux DSDL says ("if the value of
    this field is 0, the conversion should be omitted": NaN then, and for an unknown Wh)."""
    ok = math.isfinite(wh) and wh >= 0.0 and math.isfinite(nominal_voltage_v)
    return wh / nominal_voltage_v if ok and nominal_voltage_v > 0.0 else math.nan


def _pct(x: float, unknown: int) -> int:
    return unknown if not math.isfinite(x) else min(max(round(x), 0), 127)


def _stdev(x: float) -> int:
    """A deviation rounded *up* to whole percent (at least 1: 0 would claim a perfect SOC)."""
    return 0 if not math.isfinite(x) else min(max(math.ceil(x - 1e-9), 1), 127)


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
        state_of_charge_pct_stdev=_stdev(info.soc_stdev_pct),
        battery_id=info.battery_id & 0xFF,
        model_name=info.model_name[:31],
    )
    return _transfer(msg, node_id, transfer_id, priority, t)


@dataclass(frozen=True, slots=True)
class BatteryCells:
    """One BatteryInfoAux message: the cell voltages (float16 on the wire), cycles and the
    nominal voltage that converts BatteryInfo's Wh to Ah (0: unknown, no conversion)."""

    battery_id: int
    cell_v: tuple[float, ...]
    cycle_count: int = 0
    nominal_voltage_v: float = 0.0


def _transfer(payload: Any, node_id: int, transfer_id: int, priority: int, t: float) -> list[
    can.Message
]:
    transfer = dronecan.transport.Transfer(
        payload=payload, source_node_id=node_id, transfer_id=transfer_id & 0x1F,
        transfer_priority=priority, service_not_message=False,
    )  # fmt: skip
    return [
        can.Message(timestamp=t, arbitration_id=f.message_id, is_extended_id=True,
                    data=bytes(f.bytes))
        for f in transfer.to_frames()
    ]  # fmt: skip


def encode_cells(
    cells: BatteryCells, node_id: int, transfer_id: int, priority: int = 20, t: float = 0.0
) -> list[can.Message]:
    msg = dronecan.ardupilot.equipment.power.BatteryInfoAux(
        voltage_cell=[_f(x) for x in cells.cell_v[:255]],
        cycle_count=max(0, min(cells.cycle_count, 0xFFFF)),
        nominal_voltage=_f(cells.nominal_voltage_v),
        battery_id=cells.battery_id & 0xFF,
    )
    return _transfer(msg, node_id, transfer_id, priority, t)


@dataclass(frozen=True, slots=True)
class BatteryPeriodic:
    """The fields of one BatteryPeriodic message PackPilot fills (0 = not provided, as the
    DSDL says): per-cell voltage limits and the pack's current limits."""

    name: str
    design_capacity_ah: float
    cells_in_series: int
    nominal_voltage_v: float
    discharge_minimum_voltage_v: float
    charging_maximum_voltage_v: float
    charging_maximum_current_a: float
    discharge_maximum_current_a: float
    discharge_maximum_burst_current_a: float
    """The largest discharge current for 30 s (the state of power's 30 s figure)."""
    full_charge_capacity_ah: float = math.nan


def encode_periodic(
    info: BatteryPeriodic, node_id: int, transfer_id: int, priority: int = 24, t: float = 0.0
) -> list[can.Message]:
    msg = dronecan.ardupilot.equipment.power.BatteryPeriodic(
        name=list(info.name.encode("ascii", "replace")[:50]),
        design_capacity=_f(info.design_capacity_ah),
        cells_in_series=max(0, min(info.cells_in_series, 255)),
        nominal_voltage=_f(info.nominal_voltage_v),
        discharge_minimum_voltage=_f(info.discharge_minimum_voltage_v),
        charging_maximum_voltage=_f(info.charging_maximum_voltage_v),
        charging_maximum_current=_f(info.charging_maximum_current_a),
        discharge_maximum_current=_f(info.discharge_maximum_current_a),
        discharge_maximum_burst_current=_f(info.discharge_maximum_burst_current_a),
        full_charge_capacity=info.full_charge_capacity_ah,
        cycle_count=0xFFFF,
        state_of_health=0xFF,
    )
    return _transfer(msg, node_id, transfer_id, priority, t)


def _periodic(p: Any) -> BatteryPeriodic:
    return BatteryPeriodic(
        name=bytes(int(x) for x in p.name).decode("ascii", "replace"),
        design_capacity_ah=float(p.design_capacity), cells_in_series=int(p.cells_in_series),
        nominal_voltage_v=float(p.nominal_voltage),
        discharge_minimum_voltage_v=float(p.discharge_minimum_voltage),
        charging_maximum_voltage_v=float(p.charging_maximum_voltage),
        charging_maximum_current_a=float(p.charging_maximum_current),
        discharge_maximum_current_a=float(p.discharge_maximum_current),
        discharge_maximum_burst_current_a=float(p.discharge_maximum_burst_current),
        full_charge_capacity_ah=float(p.full_charge_capacity),
    )  # fmt: skip


def data_type(msg: can.Message) -> int:
    """The DroneCAN message data type id of a 29-bit frame (bits 8..23)."""
    return (msg.arbitration_id >> 8) & 0xFFFF if msg.is_extended_id else -1


class Assembler:
    """Multi-frame transfers put back together, per (source node, data type, transfer id);
    ``take`` returns the decoded message once a transfer's last frame arrived."""

    def __init__(self, types: tuple[int, ...] = (BATTERY_INFO_ID, BATTERY_INFO_AUX_ID)) -> None:
        self.types = types
        self.errors = 0
        self._parts: dict[tuple[int, int, int], list[can.Message]] = {}

    def wants(self, msg: can.Message) -> bool:
        return data_type(msg) in self.types

    def take(self, msg: can.Message) -> BatteryInfo | BatteryCells | None:
        """:meth:`take_any` for the battery messages (a BatteryPeriodic counts as nothing)."""
        x = self.take_any(msg)
        return None if isinstance(x, BatteryPeriodic) else x

    def take_any(self, msg: can.Message) -> BatteryInfo | BatteryCells | BatteryPeriodic | None:
        if not msg.data:
            self.errors += 1
            return None
        tail = msg.data[-1]
        key = (msg.arbitration_id & 0x7F, data_type(msg), tail & 0x1F)
        if tail & 0x80:  # start of transfer
            self._parts[key] = []
        parts = self._parts.get(key)
        if parts is None:
            self.errors += 1
            return None
        parts.append(msg)
        if not tail & 0x40:  # not the end yet
            if len(parts) > 64:  # a transfer longer than any battery message: drop it
                del self._parts[key]
                self.errors += 1
            return None
        del self._parts[key]
        try:
            return decode_any(parts)
        except Exception:  # dronecan raises several kinds on a bad transfer
            self.errors += 1
            return None


def decode_any(frames: Sequence[can.Message]) -> BatteryInfo | BatteryCells | BatteryPeriodic:
    """A BatteryInfo, BatteryInfoAux or BatteryPeriodic transfer, decoded."""
    fr = [dronecan.transport.Frame(m.arbitration_id, bytes(m.data)) for m in frames]
    transfer = dronecan.transport.Transfer()
    transfer.from_frames(fr)
    if transfer.data_type_id == BATTERY_PERIODIC_ID:
        return _periodic(transfer.payload)
    if transfer.data_type_id == BATTERY_INFO_AUX_ID:
        p: Any = transfer.payload
        return BatteryCells(
            battery_id=int(p.battery_id),
            cell_v=tuple(float(x) for x in p.voltage_cell),
            cycle_count=int(p.cycle_count),
            nominal_voltage_v=float(p.nominal_voltage),
        )
    return decode(frames)


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
        soc_stdev_pct=float(p.state_of_charge_pct_stdev),
        soh_pct=math.nan if p.state_of_health_pct == SOH_UNKNOWN else float(p.state_of_health_pct),
        remaining_wh=float(p.remaining_capacity_wh),
        full_wh=float(p.full_charge_capacity_wh),
        status_flags=int(p.status_flags),
        model_name=bytes(int(x) for x in p.model_name).decode("ascii", "replace"),
    )


__all__ = [
    "BAD_BATTERY",
    "BATTERY_INFO_ID",
    "BATTERY_PERIODIC_ID",
    "BMS_ERROR",
    "CHARGED",
    "CHARGING",
    "IN_USE",
    "OVERLOAD",
    "TEMP_COLD",
    "TEMP_HOT",
    "BatteryCells",
    "BatteryInfo",
    "BatteryPeriodic",
    "ah_from_wh",
    "decode",
    "encode",
    "encode_periodic",
]
