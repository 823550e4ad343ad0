"""MAVLink telemetry logs (``.tlog``): what a ground station (Mission Planner, QGroundControl,
MAVProxy) recorded of the autopilot's MAVLink stream, read for its battery data.

A ``.tlog`` is a sequence of records: an 8-byte big-endian timestamp (microseconds since 1970,
the ground station's receive time) and one MAVLink packet as received (v1: magic 0xFE, v2:
0xFD, possibly signed). Each record is walked by its own length, so a file cut inside a record
is refused as truncated and a record that is not a MAVLink packet as corrupted; a packet that
does not decode (a message the dialect does not know, a checksum broken on the radio link) is
skipped and counted. Decoding is ``pymavlink``'s (ArduPilot's dialect, a superset of common).

Battery data, per vehicle (system id whose HEARTBEAT names a real autopilot):

- ``BATTERY_STATUS`` per ``id`` when the vehicle sends it: voltage = the sum of the valid
  ``voltages[]`` entries (mV; 65535 = none) — true both for real cells and for ArduPilot's
  habit of putting the whole pack voltage in the first entries; the entries are cells only when
  each is within a cell's range; ``current_battery`` (cA, -1 = unknown), ``current_consumed``
  (mAh, the autopilot's charge counter, -1 = unknown), ``temperature`` (cdegC, 32767 = unknown),
  ``battery_remaining`` (%, -1 = unknown), ``charge_state`` (v2 extension) as the warning level;
- otherwise ``SYS_STATUS`` as one battery: ``voltage_battery`` (mV), ``current_battery`` (cA),
  ``battery_remaining``. It has no temperature, no cells and no charge counter: said so.

Time is the ground station's receive time from the log's first record (``t_s``), said so in a
note: it carries the radio link's latency and jitter, not the autopilot's clock. Flight modes
come from the vehicle's HEARTBEAT; the autopilot's battery messages from STATUSTEXT ("Low
Battery!") are carried as notes; BATT_CAPACITY (ArduPilot) / BAT1_CAPACITY (PX4) from
PARAM_VALUE as a note.
"""

from __future__ import annotations

import struct
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import F64, BatterySeries, FlightLog, battery_name, need

MAGIC_V1 = 0xFE
MAGIC_V2 = 0xFD
STAMP_BYTES = 8
NO_VOLTAGE = 65535
NO_TEMP = 32767
MAV_AUTOPILOT_INVALID = 8
"""HEARTBEAT.autopilot of a ground station or a component that is not a flight controller."""
CELL_RANGE_V = (1.5, 5.0)
"""A BATTERY_STATUS entry in this range is a cell; a larger one is (part of) the pack voltage."""
AUTOPILOT_NAMES = {"ARDUPILOTMEGA": "ArduPilot", "PX4": "PX4"}
CAPACITY_PARAMS = ("BATT_CAPACITY", "BAT1_CAPACITY", "BAT_CAPACITY")
MAX_TEXTS_NOTED = 8


def _packet_length(data: bytes, pos: int) -> int | None:
    """Length of the packet starting at ``pos`` (header + payload + checksum [+ signature])."""
    magic = data[pos]
    if magic == MAGIC_V1:
        return 6 + data[pos + 1] + 2
    if magic == MAGIC_V2:
        signed = 13 if data[pos + 2] & 0x01 else 0
        return 10 + data[pos + 1] + 2 + signed
    return None


def records(path: Path, data: bytes) -> tuple[list[tuple[float, bytes]], int]:
    """The (receive time in s, packet) records of a tlog, and how many bytes were read.
    Refuses a file that ends inside a record (truncated) or holds a record that is not a
    MAVLink packet (corrupted) in one line naming the byte."""
    out: list[tuple[float, bytes]] = []
    pos = 0
    n = len(data)
    while pos < n:
        head = pos + STAMP_BYTES
        if head + 3 > n:
            raise _truncated(path, n, len(out))
        length = _packet_length(data, head)
        if length is None:
            if not out:
                raise InputError(
                    f"{path}: not a MAVLink telemetry log: no MAVLink packet after the first "
                    "record's timestamp"
                )
            raise InputError(
                f"{path}: corrupted: no MAVLink packet at byte {head} (after {len(out)} whole "
                "packets)"
            )
        if head + length > n:
            raise _truncated(path, n, len(out))
        (stamp,) = struct.unpack_from(">Q", data, pos)
        out.append((stamp * 1e-6, data[head : head + length]))
        pos = head + length
    return out, pos


def _truncated(path: Path, n: int, whole: int) -> InputError:
    return InputError(
        f"{path}: truncated: the file ends inside a record at byte {n} (after {whole} whole "
        "packets)"
    )


@dataclass
class _Raw:
    """What the walk collected, per vehicle system id."""

    autopilots: dict[int, str] = field(default_factory=dict)
    sys_status: dict[int, list[tuple[float, Any]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    battery: dict[tuple[int, int], list[tuple[float, Any]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    modes: dict[int, list[tuple[float, str]]] = field(default_factory=lambda: defaultdict(list))
    texts: list[tuple[float, str]] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)
    undecoded: int = 0


def _parser() -> Any:
    need("pymavlink", "pymavlink", "a MAVLink telemetry log")
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    return mav


def _decode(mav: Any, packet: bytes) -> Any:
    try:
        msgs = mav.parse_buffer(packet)
    except Exception:  # pymavlink raises several kinds on a packet it cannot decode
        return None
    if not msgs:
        return None
    msg = msgs[0]
    return None if msg.get_type() == "BAD_DATA" else msg


def _collect(recs: list[tuple[float, bytes]]) -> _Raw:
    from pymavlink import mavutil

    mav = _parser()
    raw = _Raw()
    t0 = recs[0][0]
    for stamp, packet in recs:
        msg = _decode(mav, packet)
        if msg is None:
            raw.undecoded += 1
            continue
        t = stamp - t0
        kind = msg.get_type()
        src = msg.get_srcSystem()
        if kind == "HEARTBEAT":
            if msg.autopilot == MAV_AUTOPILOT_INVALID:
                continue
            raw.autopilots.setdefault(src, _autopilot_name(msg))
            mode = mavutil.mode_string_v10(msg)
            modes = raw.modes[src]
            if not modes or modes[-1][1] != mode:
                modes.append((t, mode))
        elif kind == "SYS_STATUS":
            raw.sys_status[src].append((t, msg))
        elif kind == "BATTERY_STATUS":
            raw.battery[(src, int(msg.id))].append((t, msg))
        elif kind == "STATUSTEXT":
            raw.texts.append((t, str(msg.text)))
        elif kind == "PARAM_VALUE":
            raw.params[str(msg.param_id)] = float(msg.param_value)
    return raw


def _autopilot_name(msg: Any) -> str:
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    ap = mavlink.enums["MAV_AUTOPILOT"].get(msg.autopilot)
    typ = mavlink.enums["MAV_TYPE"].get(msg.type)
    ap_name = ap.name.removeprefix("MAV_AUTOPILOT_") if ap else str(msg.autopilot)
    ap_name = AUTOPILOT_NAMES.get(ap_name, ap_name)
    typ_name = typ.name.removeprefix("MAV_TYPE_").lower() if typ else str(msg.type)
    return f"{ap_name} ({typ_name}; from its MAVLink HEARTBEAT)"


def read_tlog(path: Path) -> FlightLog:
    """Every battery a vehicle in the log reported (see the module's docstring)."""
    data = path.read_bytes()
    if not data:
        raise InputError(f"{path}: not a MAVLink telemetry log: the file is empty")
    recs, _ = records(path, data)
    raw = _collect(recs)
    vehicles = sorted(set(raw.sys_status) | {s for s, _ in raw.battery})
    found: list[BatterySeries | None] = []
    for sysid in vehicles:
        ids = sorted(i for s, i in raw.battery if s == sysid)
        if ids:
            found += [_from_battery_status(path, raw.battery[(sysid, i)], sysid, i) for i in ids]
        else:
            found.append(_from_sys_status(path, raw.sys_status[sysid], sysid))
    batteries = [b for b in found if b is not None]
    if not batteries:
        raise InputError(
            f"{path}: a valid MAVLink telemetry log without battery data: no SYS_STATUS or "
            f"BATTERY_STATUS with a voltage ({len(recs)} packets)"
        )
    batteries = [replace(b, name=battery_name(k)) for k, b in enumerate(batteries)]
    main = vehicles[0]
    return FlightLog(
        path=path, format="MAVLink telemetry log", batteries=batteries,
        notes=tuple(_notes(raw, len(recs))), modes=tuple(raw.modes.get(main, [])),
        autopilot=raw.autopilots.get(main),
        texts=tuple((t, s) for t, s in raw.texts if "batt" in s.lower()),
    )  # fmt: skip


def _notes(raw: _Raw, n: int) -> list[str]:
    notes = [
        "t_s is the ground station's receive time from the log's first packet (radio latency "
        "and jitter included), not the autopilot's clock"
    ]
    if raw.undecoded:
        notes.append(
            f"{raw.undecoded} of {n} packets did not decode (a message the dialect does not "
            "know, or a checksum broken on the link): skipped"
        )
    for name in CAPACITY_PARAMS:
        if name in raw.params:
            notes.append(f"the autopilot's {name} parameter: {raw.params[name]:.0f} mAh")
            break
    batt = [(t, s) for t, s in raw.texts if "batt" in s.lower()]
    if batt:
        shown = ", ".join(f"'{s}' at {t:.1f} s" for t, s in batt[:MAX_TEXTS_NOTED])
        more = len(batt) - MAX_TEXTS_NOTED
        notes.append("the autopilot said: " + shown + (f" and {more} more" if more > 0 else ""))
    return notes


def _times(path: Path, rows: list[tuple[float, Any]], what: str) -> tuple[F64, Any]:
    """Strictly increasing receive times (a repeated stamp keeps its last packet)."""
    t = np.array([r[0] for r in rows])
    keep = np.append(np.diff(t) > 0, True)
    if np.any(np.diff(t[keep]) <= 0):
        raise InputError(f"{path}: {what} receive times go backwards")
    return t[keep], keep


def _from_sys_status(path: Path, rows: list[tuple[float, Any]], sysid: int) -> BatterySeries | None:
    v = np.array([m.voltage_battery for _, m in rows], dtype=np.float64)
    if not np.any((v > 0) & (v != NO_VOLTAGE)):
        return None
    t, keep = _times(path, rows, f"SYS_STATUS of system {sysid}")
    v = np.where((v > 0) & (v != NO_VOLTAGE), v / 1000.0, np.nan)[keep]
    i = np.array([m.current_battery for _, m in rows], dtype=np.float64)[keep]
    rem = np.array([m.battery_remaining for _, m in rows], dtype=np.float64)[keep]
    notes = ["SYS_STATUS carries no temperature, no cell voltages, no cell count and no charge "
             "counter"]  # fmt: skip
    current = None if np.all(i < 0) else np.where(i < 0, np.nan, i / 100.0)
    if current is None:
        notes.append("current_battery is -1 throughout: no current measurement")
    soc = None if np.all(rem < 0) else np.where(rem < 0, np.nan, rem / 100.0)
    return BatterySeries(
        name="", source=f"SYS_STATUS of system {sysid}", t_s=t, voltage_v=v, current_a=current,
        soc=soc, notes=tuple(notes),
    )  # fmt: skip


def _from_battery_status(
    path: Path, rows: list[tuple[float, Any]], sysid: int, bid: int
) -> BatterySeries:
    t, keep = _times(path, rows, f"BATTERY_STATUS {bid} of system {sysid}")
    msgs = [m for (_, m), k in zip(rows, keep, strict=True) if k]
    entries = np.array(
        [list(m.voltages) + list(getattr(m, "voltages_ext", []) or []) for m in msgs], float
    )
    valid = (entries != NO_VOLTAGE) & (entries > 0)
    volts = np.where(valid, entries / 1000.0, 0.0)
    pack = np.where(valid.any(axis=1), volts.sum(axis=1), np.nan)
    lo, hi = CELL_RANGE_V
    cells_ok = valid.any(axis=1) & np.all(~valid | ((volts >= lo) & (volts <= hi)), axis=1)
    notes: list[str] = []
    cells = None
    if cells_ok.all():
        cells = np.where(valid, volts, np.nan)
    else:
        notes.append("voltages[] holds the pack voltage, not cells: no cell voltages")

    def col(name: str, scale: float, missing: float) -> F64 | None:
        x = np.array([getattr(m, name, missing) for m in msgs], dtype=np.float64)
        return None if np.all(x == missing) else np.where(x == missing, np.nan, x * scale)

    current = col("current_battery", 0.01, -1.0)
    temp = col("temperature", 0.01, float(NO_TEMP))
    state = np.array([getattr(m, "charge_state", 0) for m in msgs], dtype=np.float64)
    return BatterySeries(
        name="", source=f"BATTERY_STATUS id {bid} of system {sysid}", t_s=t, voltage_v=pack,
        current_a=current, temp_c=temp, cells_v=cells, soc=col("battery_remaining", 0.01, -1.0),
        notes=tuple(notes), discharged_mah=col("current_consumed", 1.0, -1.0),
        warning=np.maximum(state - 1.0, 0.0) if np.any(state > 1) else None,
    )  # fmt: skip


__all__ = ["read_tlog", "records"]
