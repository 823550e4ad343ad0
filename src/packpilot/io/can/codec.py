"""TC/Elcon charger protocol: frame layout from the packaged DBC, strict encode/decode.

Two 29-bit frames, 8 bytes, every multi-byte value big-endian (DBC Motorola ``@0``; cantools'
start bit for a big-endian signal is the *MSB's* bit in the sawtooth numbering, so bytes 0-1
start at bit 7 and bytes 2-3 at bit 23):

* ``0x1806E5F4`` BMS → charger: max voltage (0.1 V/bit), max current (0.1 A/bit), control
  (0 = on, 1 = off), mode (0 = charging), two reserved bytes.
* ``0x18FF50E5`` charger → BMS: output voltage, output current, status bits 0..4
  (hardware failure, over-temperature, input voltage fault, battery not detected/reversed,
  communication timeout), three reserved bytes.

Decoders validate everything a receiver relies on (frame kind, ID format, DLC, enumerations)
and raise :class:`FrameError`; callers count and drop such frames instead of crashing.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from typing import Protocol, cast

import can
import cantools
from cantools.database.can import Database, Message

from packpilot.contract.charger import ChargerCommand, ChargerStatus
from packpilot.errors import InputError

REQUEST_ID = 0x1806E5F4
"""BMS → charger request (extended ID)."""
STATUS_ID = 0x18FF50E5
"""Charger → BMS status (extended ID)."""
DLC = 8
PERIOD_S = 1.0
"""Both frames are sent once a second."""

CONTROL_ON = 0
CONTROL_OFF = 1
MODE_CHARGING = 0

FLAG_NAMES: tuple[str, ...] = (
    "hardware_failure",
    "over_temperature",
    "input_voltage_fault",
    "battery_not_detected",
    "communication_timeout",
)
"""Status byte 4, bit 0 upwards."""
_FLAG_SIGNALS: Mapping[str, str] = {
    "hardware_failure": "HardwareFailure",
    "over_temperature": "OverTemperature",
    "input_voltage_fault": "InputVoltageFault",
    "battery_not_detected": "BatteryNotDetected",
    "communication_timeout": "CommunicationTimeout",
}
_RAW_MAX = 0xFFFF
COUNTS_PER_UNIT = 10
"""Voltages and currents travel as 0.1 V / 0.1 A counts (the DBC's factor 0.1); integer
division by 10 decodes exactly (98.0, not 98.00000000000001)."""


class FrameError(InputError):
    """A CAN frame that does not match the protocol (wrong ID format, DLC, enumeration...)."""


class FlagAttrs(Protocol):
    """Any object with the five status bits as boolean attributes."""

    @property
    def hardware_failure(self) -> bool: ...
    @property
    def over_temperature(self) -> bool: ...
    @property
    def input_voltage_fault(self) -> bool: ...
    @property
    def battery_not_detected(self) -> bool: ...
    @property
    def communication_timeout(self) -> bool: ...


FaultFlags = Mapping[str, bool] | FlagAttrs
"""The five status bits as a mapping (missing keys = False) or as attributes."""


@dataclass(frozen=True, slots=True)
class ChargerFlags:
    """The five status bits of the charger's status frame."""

    hardware_failure: bool = False
    over_temperature: bool = False
    input_voltage_fault: bool = False
    battery_not_detected: bool = False
    communication_timeout: bool = False

    @classmethod
    def of(cls, flags: FaultFlags) -> ChargerFlags:
        """Normalise a mapping or an attribute object; unknown mapping keys are an error."""
        if isinstance(flags, Mapping):
            unknown = set(flags) - set(FLAG_NAMES)
            if unknown:
                raise ValueError(f"unknown charger flag(s) {sorted(unknown)}; known: {FLAG_NAMES}")
            return cls(**{name: bool(flags.get(name, False)) for name in FLAG_NAMES})
        return cls(**{name: bool(getattr(flags, name)) for name in FLAG_NAMES})


@dataclass(frozen=True, slots=True)
class ChargerRequest:
    """A decoded request frame."""

    voltage_v: float
    current_a: float
    enable: bool
    mode: int = MODE_CHARGING


@functools.cache
def database() -> Database:
    """The packaged DBC (``elcon.dbc``), parsed once."""
    text = resources.files("packpilot.io.can").joinpath("elcon.dbc").read_text(encoding="utf-8")
    return cast(Database, cantools.database.load_string(text, database_format="dbc"))


def _message(frame_id: int) -> Message:
    return database().get_message_by_frame_id(frame_id)


def _raw(value: float) -> int:
    """Physical value to an unsigned 16-bit raw count, rounded and clamped."""
    if not math.isfinite(value):
        return 0
    return min(max(round(value * COUNTS_PER_UNIT), 0), _RAW_MAX)


@functools.lru_cache(maxsize=4096)
def _encode_raw(frame_id: int, raw: tuple[tuple[str, int], ...]) -> bytes:
    """cantools encoding of raw counts, memoised: a heartbeat repeats the same few frames."""
    return bytes(_message(frame_id).encode(dict(raw), scaling=False))


def encode_request(cmd: ChargerCommand, timestamp: float = 0.0) -> can.Message:
    """Request frame for a charger command. A non-finite setpoint is sent as 0 V / 0 A / off,
    so a corrupted command can only switch the charger off."""
    finite = math.isfinite(cmd.voltage_v) and math.isfinite(cmd.current_a)
    data = _encode_raw(
        REQUEST_ID,
        (
            ("MaxChargeVoltage", _raw(cmd.voltage_v) if finite else 0),
            ("MaxChargeCurrent", _raw(cmd.current_a) if finite else 0),
            ("Control", CONTROL_ON if (cmd.enable and finite) else CONTROL_OFF),
            ("Mode", MODE_CHARGING),
        ),
    )
    return can.Message(
        timestamp=timestamp, arbitration_id=REQUEST_ID, is_extended_id=True, data=data
    )


def encode_status(
    output_v: float, output_a: float, flags: FaultFlags, timestamp: float = 0.0
) -> can.Message:
    """Status frame: present output and the five status bits."""
    f = ChargerFlags.of(flags)
    raw = [("OutputVoltage", _raw(output_v)), ("OutputCurrent", _raw(output_a))]
    raw += [(signal, int(getattr(f, name))) for name, signal in _FLAG_SIGNALS.items()]
    data = _encode_raw(STATUS_ID, tuple(raw))
    return can.Message(
        timestamp=timestamp, arbitration_id=STATUS_ID, is_extended_id=True, data=data
    )


def _check_frame(msg: can.Message, frame_id: int, what: str) -> None:
    if msg.is_error_frame or msg.is_remote_frame:
        raise FrameError(f"{what}: {'error' if msg.is_error_frame else 'remote'} frame")
    if msg.arbitration_id != frame_id or not msg.is_extended_id:
        kind = "extended" if msg.is_extended_id else "standard"
        raise FrameError(f"{what}: unexpected {kind} ID 0x{msg.arbitration_id:X}")
    if msg.dlc != DLC or len(msg.data) != DLC:
        raise FrameError(f"{what} 0x{frame_id:X}: DLC {msg.dlc} ({len(msg.data)} bytes), need 8")


def _decode_raw(msg: can.Message, frame_id: int, what: str) -> dict[str, int]:
    _check_frame(msg, frame_id, what)
    try:
        raw = _message(frame_id).decode(bytes(msg.data), decode_choices=False, scaling=False)
    except (cantools.database.DecodeError, ValueError, KeyError) as err:
        raise FrameError(f"{what} 0x{frame_id:X}: undecodable ({err})") from None
    if not isinstance(raw, Mapping):  # container (multiplexed) messages are not in this DBC
        raise FrameError(f"{what} 0x{frame_id:X}: unexpected container message")
    out: dict[str, int] = {}
    for name, value in raw.items():
        if not isinstance(value, int | float):
            raise FrameError(f"{what} 0x{frame_id:X}: signal {name} did not decode to a number")
        out[name] = int(value)
    return out


def decode_request(msg: can.Message) -> ChargerRequest:
    """Decode a BMS request; control other than 0/1 or mode other than 0 is a FrameError."""
    raw = _decode_raw(msg, REQUEST_ID, "request")
    if raw["Control"] not in (CONTROL_ON, CONTROL_OFF):
        raise FrameError(f"request: control byte {raw['Control']}, expected 0 (on) or 1 (off)")
    if raw["Mode"] != MODE_CHARGING:
        raise FrameError(f"request: mode byte {raw['Mode']}, only 0 (charging) is supported")
    return ChargerRequest(
        voltage_v=raw["MaxChargeVoltage"] / COUNTS_PER_UNIT,
        current_a=raw["MaxChargeCurrent"] / COUNTS_PER_UNIT,
        enable=raw["Control"] == CONTROL_ON,
        mode=raw["Mode"],
    )


def decode_status(msg: can.Message) -> ChargerStatus:
    """Decode a charger status frame (``online`` is True: the frame just arrived)."""
    raw = _decode_raw(msg, STATUS_ID, "status")
    return ChargerStatus(
        output_v=raw["OutputVoltage"] / COUNTS_PER_UNIT,
        output_a=raw["OutputCurrent"] / COUNTS_PER_UNIT,
        **{name: bool(raw[signal]) for name, signal in _FLAG_SIGNALS.items()},
        online=True,
    )


__all__ = [
    "CONTROL_OFF",
    "CONTROL_ON",
    "COUNTS_PER_UNIT",
    "DLC",
    "FLAG_NAMES",
    "MODE_CHARGING",
    "PERIOD_S",
    "REQUEST_ID",
    "STATUS_ID",
    "ChargerFlags",
    "ChargerRequest",
    "FaultFlags",
    "FlagAttrs",
    "FrameError",
    "database",
    "decode_request",
    "decode_status",
    "encode_request",
    "encode_status",
]
