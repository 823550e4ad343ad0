"""PackPilot smart-battery frames (``packpilot.dbc``): strict encode and decode with cantools.

Telemetry (battery → BMS), switch / balancer / aux commands (BMS → switch nodes), the
platform's bus voltage and dock contact, the protection state for the platform. The layout is
:mod:`packpilot.io.can.dbcgen`'s; values travel as integer counts (raw × factor = value).

A value that is not available travels as the field's all-ones count (unsigned) or its most
negative count (signed) and decodes to NaN; a finite value beyond the field is clamped one count
short of that sentinel, so an out-of-range reading stays visibly out of range for the
plausibility layer instead of wrapping around. Decoding is strict, as for the charger: a wrong
identifier format, a remote or error frame, a wrong DLC or undecodable content raise
:class:`~packpilot.io.can.codec.FrameError`, which the receivers count and drop.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from typing import cast

import can
import cantools
from cantools.database.can import Database, Message

from packpilot.io.can.codec import FrameError
from packpilot.io.can.dbcgen import (
    AUX_CMD,
    BALANCER_CMD,
    BATTERY_CAPACITY,
    BATTERY_CELLS,
    BATTERY_GROUPS,
    BATTERY_MEAS,
    BATTERY_STATE,
    GROUPS_PER_FRAME,
    MAX_BATTERIES,
    MAX_GROUPS,
    PLATFORM_MEAS,
    PROTECTION_STATE,
    STATE_OF_CHARGE,
    STATE_OF_POWER,
    SWITCH_CMD,
    SWITCH_STATE,
)

KINDS: dict[int, str] = {
    BATTERY_MEAS: "meas",
    BATTERY_STATE: "state",
    BATTERY_CAPACITY: "capacity",
    BATTERY_GROUPS: "groups",
    BATTERY_CELLS: "cells",
    SWITCH_CMD: "switch",
    BALANCER_CMD: "balancer",
    SWITCH_STATE: "switch_state",
}
"""Per-battery frame kinds by base identifier (battery ``i`` at ``base + i``)."""
SENTINEL_BITS = 16
"""Fields this wide carry "not available" as a sentinel count."""
SINGLE: dict[int, str] = {
    AUX_CMD: "aux", PLATFORM_MEAS: "platform", PROTECTION_STATE: "protection",
    STATE_OF_POWER: "power", STATE_OF_CHARGE: "soc",
}  # fmt: skip


@functools.cache
def database() -> Database:
    """The packaged ``packpilot.dbc``, parsed once."""
    text = resources.files("packpilot.io.can").joinpath("packpilot.dbc").read_text("utf-8")
    return cast(Database, cantools.database.load_string(text, database_format="dbc"))


@functools.cache
def _message(frame_id: int) -> Message:
    return database().get_message_by_frame_id(frame_id)


def classify(frame_id: int) -> tuple[str, int] | None:
    """(kind, battery index) of a PackPilot identifier (index -1 for pack frames), or None."""
    if frame_id in SINGLE:
        return SINGLE[frame_id], -1
    base, i = frame_id & ~0xF, frame_id & 0xF
    kind = KINDS.get(base)
    return None if kind is None or i >= MAX_BATTERIES else (kind, i)


# ----------------------------------------------------------------------------- raw counts
def _count(value: float, factor: float, length: int, signed: bool) -> int:
    """Physical value → raw count: rounded, clamped short of the sentinel; NaN → sentinel.
    Fields narrower than 16 bits (flags, counters, indices) have no sentinel."""
    if length < SENTINEL_BITS:
        top = (1 << length) - 1
        return top if not math.isfinite(value) else min(max(round(value / factor), 0), top)
    if signed:
        lo, hi, nan = -(1 << (length - 1)) + 1, (1 << (length - 1)) - 1, -(1 << (length - 1))
    else:
        lo, hi, nan = 0, (1 << length) - 2, (1 << length) - 1
    if not math.isfinite(value):
        if math.isinf(value):
            return hi if value > 0 else lo
        return nan
    return min(max(round(value / factor), lo), hi)


def _value(raw: int, factor: float, length: int, signed: bool) -> float:
    if length < SENTINEL_BITS:
        return raw * factor
    nan = -(1 << (length - 1)) if signed else (1 << length) - 1
    return math.nan if raw == nan else raw * factor


def _signal_spec(frame_id: int, name: str) -> tuple[float, int, bool]:
    sig = _message(frame_id).get_signal_by_name(name)
    return float(sig.scale), int(sig.length), bool(sig.is_signed)


@functools.cache
def _specs(frame_id: int) -> dict[str, tuple[float, int, bool]]:
    return {s.name: _signal_spec(frame_id, s.name) for s in _message(frame_id).signals}


def _frame(frame_id: int, values: Mapping[str, float], t: float) -> can.Message:
    specs = _specs(frame_id)
    raw = {k: _count(v, *specs[k]) for k, v in values.items()}
    data = _message(frame_id).encode(raw, scaling=False, strict=False)
    return can.Message(timestamp=t, arbitration_id=frame_id, is_extended_id=False, data=data)


# ----------------------------------------------------------------------------- encode
@dataclass(slots=True)
class BatteryReport:
    """What a smart battery reports (one battery, SI units, current + = discharging)."""

    voltage_v: float
    current_a: float
    min_cell_v: float
    max_cell_v: float
    temp_c: float
    min_temp_c: float
    soc: float
    chg_on: bool
    dsg_on: bool
    present: bool
    full_ah: float
    remaining_ah: float
    cycle_count: float
    group_v: tuple[float, ...]


def encode_battery(i: int, r: BatteryReport, counter: int, t: float = 0.0) -> list[can.Message]:
    """Every telemetry frame of battery ``i``: meas, cells, state, capacity, group blocks."""
    ng = min(len(r.group_v), MAX_GROUPS)
    out = [
        _frame(BATTERY_MEAS + i, {"Voltage": r.voltage_v, "Current": r.current_a,
                                  "Counter": counter & 0xFF}, t),
        _frame(BATTERY_CELLS + i, {"MinCellV": r.min_cell_v, "MaxCellV": r.max_cell_v}, t),
        _frame(BATTERY_STATE + i, {"TempMax": r.temp_c, "TempMin": r.min_temp_c, "SOC": r.soc,
                                   "ChgOn": r.chg_on, "DsgOn": r.dsg_on, "Present": r.present,
                                   "Counter": counter & 0xFF}, t),
        _frame(BATTERY_CAPACITY + i, {"FullAh": r.full_ah, "RemainingAh": r.remaining_ah,
                                      "CycleCount": r.cycle_count, "NGroups": ng}, t),
    ]  # fmt: skip
    for b in range(-(-ng // GROUPS_PER_FRAME)):
        vals: dict[str, float] = {"Block": b, "NGroups": ng}
        for j in range(GROUPS_PER_FRAME):
            g = b * GROUPS_PER_FRAME + j
            vals[f"GroupV{g}"] = r.group_v[g] if g < ng else math.nan
        out.append(_frame(BATTERY_GROUPS + i, vals, t))
    return out


def encode_switch(i: int, chg_on: bool, dsg_on: bool, seq: int, t: float = 0.0) -> can.Message:
    return _frame(SWITCH_CMD + i, {"ChgOn": chg_on, "DsgOn": dsg_on, "Seq": seq & 0xFF}, t)


def encode_switch_state(
    i: int, chg_on: bool, dsg_on: bool, timed_out: bool, seq: int, t: float = 0.0
) -> can.Message:
    vals = {"ChgOn": chg_on, "DsgOn": dsg_on, "TimedOut": timed_out, "Seq": seq & 0xFF}
    return _frame(SWITCH_STATE + i, vals, t)


def encode_balancer(
    i: int, currents_a: tuple[float, ...], seq: int, t: float = 0.0
) -> list[can.Message]:
    n = min(len(currents_a), MAX_GROUPS)
    out = []
    for b in range(-(-n // GROUPS_PER_FRAME)):
        vals: dict[str, float] = {"Block": b, "Seq": seq & 0xFF}
        for j in range(GROUPS_PER_FRAME):
            g = b * GROUPS_PER_FRAME + j
            vals[f"BalancerA{g}"] = currents_a[g] if g < n else 0.0
        out.append(_frame(BALANCER_CMD + i, vals, t))
    return out


def encode_aux(relay_on: bool, charge_a: float, seq: int, t: float = 0.0) -> can.Message:
    return _frame(AUX_CMD, {"AuxRelay": relay_on, "AuxChargeA": charge_a, "Seq": seq & 0xFF}, t)


def encode_platform(bus_v: float, docked: bool, counter: int, t: float = 0.0) -> can.Message:
    vals = {"BusV": bus_v, "Docked": docked, "Counter": counter & 0xFF}
    return _frame(PLATFORM_MEAS, vals, t)


@dataclass(frozen=True, slots=True)
class ProtectionReport:
    """The protection's platform interface (what the aircraft is told)."""

    mode: int
    active_param: int
    allowance_used: float
    time_to_trip_s: float
    time_to_empty_s: float


def encode_protection(p: ProtectionReport, t: float = 0.0) -> can.Message:
    def secs(x: float) -> float:
        return x if math.isfinite(x) and x >= 0 else math.nan  # none / beyond: the sentinel

    vals = {
        "Mode": p.mode, "ActiveParam": p.active_param, "AllowanceUsed": p.allowance_used,
        "TimeToTrip": secs(p.time_to_trip_s), "TimeToEmpty": secs(p.time_to_empty_s),
    }  # fmt: skip
    return _frame(PROTECTION_STATE, vals, t)


def encode_power(dcl_2s_a: float, dcl_10s_a: float, dcl_30s_a: float, ccl_10s_a: float,
                 t: float = 0.0) -> can.Message:  # fmt: skip
    """The pack's state of power (A; NaN: not known, the field's sentinel)."""
    vals = {"Dcl2s": dcl_2s_a, "Dcl10s": dcl_10s_a, "Dcl30s": dcl_30s_a, "Ccl10s": ccl_10s_a}
    return _frame(STATE_OF_POWER, vals, t)


@dataclass(frozen=True, slots=True)
class SocReport:
    """The pack's SOC as the core estimates it (0x232): percent, its standard deviation
    (NaN: not the observer's), the source's code (``contract/soc_source.py:SOURCES``) and how
    many batteries are on the observer and on its fallback."""

    soc_pct: float
    stdev_pct: float
    source: int
    observed: int
    fallback: int


def encode_soc(r: SocReport, t: float = 0.0) -> can.Message:
    vals = {"Soc": r.soc_pct, "SocStdev": r.stdev_pct, "Source": r.source,
            "Observed": r.observed, "Fallback": r.fallback, "Reserved": 0}  # fmt: skip
    return _frame(STATE_OF_CHARGE, vals, t)


# ----------------------------------------------------------------------------- decode
def decode(msg: can.Message) -> tuple[str, int, dict[str, float]]:
    """(kind, battery index or -1, physical values; NaN where not available) of a PackPilot
    frame. Anything else, or anything malformed, raises :class:`FrameError`."""
    if msg.is_error_frame or msg.is_remote_frame:
        raise FrameError(f"{'error' if msg.is_error_frame else 'remote'} frame")
    if msg.is_extended_id:
        raise FrameError(f"extended ID 0x{msg.arbitration_id:X} is not a PackPilot frame")
    which = classify(msg.arbitration_id)
    if which is None:
        raise FrameError(f"unknown ID 0x{msg.arbitration_id:X}")
    frame_id = msg.arbitration_id
    message = _message(frame_id)
    if msg.dlc != message.length or len(msg.data) != message.length:
        raise FrameError(f"0x{frame_id:X}: DLC {msg.dlc}, need {message.length}")
    try:
        raw = message.decode(bytes(msg.data), decode_choices=False, scaling=False)
    except (cantools.database.DecodeError, ValueError, KeyError) as err:
        raise FrameError(f"0x{frame_id:X}: undecodable ({err})") from None
    specs = _specs(frame_id)
    out: dict[str, float] = {}
    for name, value in cast(Mapping[str, int], raw).items():
        factor, length, signed = specs[name]
        out[name] = _value(int(value), factor, length, signed)
    return which[0], which[1], out


__all__ = [
    "KINDS",
    "SINGLE",
    "BatteryReport",
    "ProtectionReport",
    "SocReport",
    "classify",
    "database",
    "decode",
    "encode_aux",
    "encode_balancer",
    "encode_battery",
    "encode_platform",
    "encode_power",
    "encode_protection",
    "encode_soc",
    "encode_switch",
    "encode_switch_state",
]
