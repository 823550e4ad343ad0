"""PX4 ULog: the ``battery_status`` topic, one instance (``multi_id``) per battery, read with
``pyulog``; and a minimal ULog writer for the sample logs PackPilot ships.

PX4's fields, as the reader takes them: ``voltage_v``; ``current_a`` (positive = discharge,
PackPilot's sign; -1 means unknown); ``temperature`` in degC (NaN when the battery has no
sensor); ``remaining`` 0..1 (negative = unknown); ``cell_count``; ``voltage_cell_v[]``, which
PX4 fills with voltage / cell_count for a battery that cannot measure cells (those are not
taken as cell voltages); ``connected``. Timestamps are microseconds since boot; ``t_s`` counts
from the log's start.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import F64, BatterySeries, FlightLog, battery_name, need, quiet

TOPIC = "battery_status"
STATUS_TOPIC = "vehicle_status"
FAKE_CELL_TOL_V = 2e-3
"""Cells within this of voltage_v / cell_count or of voltage_filtered_v / cell_count at every
sample are PX4's fill, not measurements (PX4 fills from the filtered voltage: 218 mV from
voltage_v / n on a real log)."""
NAV_STATES = {
    0: "MANUAL", 1: "ALTCTL", 2: "POSCTL", 3: "AUTO_MISSION", 4: "AUTO_LOITER", 5: "AUTO_RTL",
    6: "POSITION_SLOW", 10: "ACRO", 12: "DESCEND", 13: "TERMINATION", 14: "OFFBOARD",
    15: "STAB", 17: "AUTO_TAKEOFF", 18: "AUTO_LAND", 19: "AUTO_FOLLOW_TARGET",
    20: "AUTO_PRECLAND", 21: "ORBIT", 22: "AUTO_VTOL_TAKEOFF",
}  # fmt: skip
"""PX4's ``vehicle_status.nav_state`` names (numbers not listed are named by number)."""


def _load(path: Path) -> Any:
    pyulog: Any = need("pyulog", "pyulog", "a PX4 ULog")
    try:
        with quiet():
            return pyulog.ULog(str(path), [TOPIC, STATUS_TOPIC])
    except Exception as err:  # the parser raises many kinds on a damaged file
        raise InputError(
            f"{path}: not a readable ULog file ({type(err).__name__}: {err})"
        ) from None


def _check_whole(path: Path) -> None:
    """Walk the messages (uint16 size, uint8 type, body) after the 16-byte header: a file
    cut inside a message is refused in one line (pyulog reads such a file silently)."""
    data = path.read_bytes()
    pos = 16
    while pos + 3 <= len(data):
        (size,) = struct.unpack_from("<H", data, pos)
        pos += 3 + size
    if pos != len(data):
        raise InputError(
            f"{path}: truncated: the file ends inside a ULog message at byte {len(data)}"
        )


def read_ulog(path: Path) -> FlightLog:
    """Every ``battery_status`` instance of the log, in ``multi_id`` order."""
    ulog = _load(path)
    _check_whole(path)
    sets = sorted((d for d in ulog.data_list if d.name == TOPIC), key=lambda d: d.multi_id)
    if not sets:
        raise InputError(
            f"{path}: a valid ULog without battery data: it has no {TOPIC} topic "
            f"(topics: {', '.join(sorted({d.name for d in ulog.data_list})) or 'none read'})"
        )
    t0 = float(ulog.start_timestamp)
    batteries = [_battery(path, k, d.multi_id, d.data, t0) for k, d in enumerate(sets)]
    info = getattr(ulog, "msg_info_dict", {})
    who = " ".join(
        str(info[k]) for k in ("sys_name", "ver_hw", "ver_sw") if info.get(k) not in (None, "")
    )
    return FlightLog(
        path=path, format="PX4 ULog", batteries=batteries, modes=_modes(ulog, t0),
        autopilot=who or None,
    )  # fmt: skip


def _modes(ulog: Any, t0_us: float) -> tuple[tuple[float, str], ...]:
    """Each change of ``vehicle_status.nav_state``: when and to what."""
    for d in ulog.data_list:
        if d.name == STATUS_TOPIC and "nav_state" in d.data and d.multi_id == 0:
            t = (np.asarray(d.data["timestamp"], dtype=np.float64) - t0_us) / 1e6
            nav = np.asarray(d.data["nav_state"]).astype(int)
            keep = np.append(True, np.diff(nav) != 0)
            return tuple(
                (float(tt), NAV_STATES.get(int(n), f"nav_state {int(n)}"))
                for tt, n in zip(t[keep], nav[keep], strict=True)
            )
    return ()


def _field(data: Mapping[str, Any], name: str) -> F64 | None:
    if name not in data:
        return None
    with np.errstate(all="ignore"):  # a damaged record's bytes: checked downstream
        return np.asarray(data[name], dtype=np.float64)


def _unique_times(path: Path, t_us: F64) -> np.ndarray[Any, np.dtype[np.bool_]]:
    """Samples to keep: time strictly increasing (a repeated timestamp keeps the later)."""
    keep: np.ndarray[Any, np.dtype[np.bool_]] = np.append(np.diff(t_us) > 0, True)
    if np.any(np.diff(t_us[keep]) <= 0):
        raise InputError(f"{path}: {TOPIC} timestamps go backwards")
    return keep


def _battery(
    path: Path, k: int, multi_id: int, data: Mapping[str, Any], t0_us: float
) -> BatterySeries:
    if "timestamp" not in data or "voltage_v" not in data:
        raise InputError(f"{path}: {TOPIC} instance {multi_id} has no timestamp or voltage_v field")
    t_us = np.asarray(data["timestamp"], dtype=np.float64)
    keep = _unique_times(path, t_us)
    col = {name: x[keep] for name in data if (x := _field(data, name)) is not None}
    notes: list[str] = []
    v = col.get("voltage_v")
    if v is None:
        raise InputError(f"{path}: {TOPIC} instance {multi_id} has no voltage_v field")
    current = col.get("current_a")
    if current is not None and np.all((current == -1.0) | np.isnan(current)):
        notes.append("current_a is -1 (PX4: unknown) throughout: no current measurement")
        current = None
    elif current is not None:
        current = np.where(current == -1.0, np.nan, current)
    temp = col.get("temperature")
    if temp is not None and not np.isfinite(temp).any():
        notes.append("temperature is NaN throughout: the battery reports no temperature")
        temp = None
    soc = col.get("remaining")
    if soc is not None:
        soc = np.where(soc < 0, np.nan, soc)
        soc = soc if np.isfinite(soc).any() else None
    count, cells = _cells(col, v, notes)
    present = col.get("connected")
    serial = col.get("serial_number")
    sn = str(int(serial[-1])) if serial is not None and serial.size and serial[-1] > 0 else None
    return BatterySeries(
        name=battery_name(k), source=f"{TOPIC} instance {multi_id}",
        t_s=(t_us[keep] - t0_us) / 1e6, voltage_v=v, current_a=current, temp_c=temp,
        cells_v=cells, cell_count=count, soc=soc,
        present=None if present is None else (present != 0).astype(np.float64),
        notes=tuple(notes), discharged_mah=col.get("discharged_mah"),
        warning=col.get("warning"), serial_number=sn,
    )  # fmt: skip


def _cells(col: Mapping[str, F64], v: F64, notes: list[str]) -> tuple[int | None, F64 | None]:
    """(cell count, measured cell voltages or None): PX4's V / n fill is not a measurement."""
    raw = col.get("cell_count")
    count = int(np.max(raw)) if raw is not None and raw.size and np.max(raw) > 0 else None
    if count is None:
        notes.append("cell_count is 0: the log does not say how many cells")
        return None, None
    names = [f"voltage_cell_v[{k}]" for k in range(count)]
    if not all(n in col for n in names):
        notes.append(f"no voltage_cell_v for {count} cells")
        return count, None
    cells = np.column_stack([col[n] for n in names])
    ok = np.isfinite(cells) & (cells > 0)
    if not ok.any():
        notes.append("voltage_cell_v is empty: no per-cell voltages")
        return count, None
    filled = np.abs(cells - (v / count)[:, None]) <= FAKE_CELL_TOL_V
    vf = col.get("voltage_filtered_v")
    if vf is not None:
        filled |= np.abs(cells - (vf / count)[:, None]) <= FAKE_CELL_TOL_V
    if np.all(filled | ~ok):
        what = "voltage_v or voltage_filtered_v" if vf is not None else "voltage_v"
        notes.append(
            f"voltage_cell_v holds {what} / {count} in every cell (PX4 fills it so for a "
            "battery that cannot measure cells): not taken as cell voltages"
        )
        return count, None
    return count, np.where(ok, cells, np.nan)


# ----------------------------------------------------------------------------- writer

_TYPES = {"uint64_t": "Q", "float": "f", "uint8_t": "B", "int8_t": "b", "bool": "?",
          "uint16_t": "H", "int32_t": "i"}  # fmt: skip
BATTERY_STATUS_FIELDS: tuple[tuple[str, str, int], ...] = (
    ("uint64_t", "timestamp", 0),
    ("float", "voltage_v", 0),
    ("float", "current_a", 0),
    ("float", "current_average_a", 0),
    ("float", "discharged_mah", 0),
    ("float", "remaining", 0),
    ("float", "temperature", 0),
    ("float", "voltage_cell_v", 14),
    ("uint8_t", "cell_count", 0),
    ("bool", "connected", 0),
    ("uint8_t", "id", 0),
    ("uint8_t", "warning", 0),
)
"""The subset of PX4's ``battery_status`` the sample logs carry (same names, types and the
14-cell array; PX4 has more fields, which a reader looks up by name)."""


def _msg(kind: bytes, body: bytes) -> bytes:
    """One ULog message: uint16 size of the body, uint8 type, body."""
    return struct.pack("<HB", len(body), kind[0]) + body


def write_ulog(
    path: Path,
    instances: Sequence[Sequence[Mapping[str, Any]]],
    *,
    sys_name: str = "PackPilot",
    start_us: int | None = None,
) -> None:
    """A minimal ULog (format version 1): header, flag bits, the ``battery_status`` format, an
    info message naming the writer, one subscription per instance, then the data messages in
    time order; the header's start time is ``start_us`` (default: the first sample's).
    ``instances[k]`` is instance k's samples, each a dict of the fields of
    :data:`BATTERY_STATUS_FIELDS` (``voltage_cell_v`` a sequence of 14 floats). The layout
    follows PX4's ULog file format document; pyulog reads it back (tests do)."""
    fmt = "<" + "".join(_TYPES[t] * max(n, 1) for t, _, n in BATTERY_STATUS_FIELDS)
    spec = "".join(
        f"{t}[{n}] {name};" if n else f"{t} {name};" for t, name, n in BATTERY_STATUS_FIELDS
    )
    if start_us is None:
        start_us = min((int(s["timestamp"]) for inst in instances for s in inst), default=0)
    out = bytearray(b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", start_us))
    out += _msg(b"B", bytes(16) + struct.pack("<3Q", 0, 0, 0))
    out += _msg(b"F", f"{TOPIC}:{spec}".encode())
    key = f"char[{len(sys_name)}] sys_name".encode()
    out += _msg(b"I", bytes([len(key)]) + key + sys_name.encode())
    for k in range(len(instances)):
        out += _msg(b"A", struct.pack("<BH", k, k) + TOPIC.encode())
    stream = sorted(
        ((int(s["timestamp"]), k, s) for k, samples in enumerate(instances) for s in samples),
        key=lambda e: (e[0], e[1]),
    )
    for _, k, s in stream:
        values: list[Any] = []
        for _t, name, n in BATTERY_STATUS_FIELDS:
            values += list(s[name]) if n else [s[name]]
        out += _msg(b"D", struct.pack("<H", k) + struct.pack(fmt, *values))
    path.write_bytes(bytes(out))


__all__ = ["BATTERY_STATUS_FIELDS", "TOPIC", "read_ulog", "write_ulog"]


def write_battery_ulog(
    path: Path, t_s: Sequence[float], voltage_v: Sequence[float], current_a: Sequence[float],
    charge_ah: Sequence[float],
) -> None:
    """One battery's sampled flight as PX4 logs it when the battery reports no cells
    (``cell_count`` 1, no temperature, ``remaining`` not meaningful): what the fit's tests and
    benchmarks feed ``packpilot fit`` from a synthetic profile. Time starts at 0."""
    samples = [
        {"timestamp": round(t * 1e6), "voltage_v": float(v), "current_a": float(i),
         "current_average_a": float(i), "discharged_mah": 1000.0 * float(q),
         "remaining": 0.5, "temperature": float("nan"), "voltage_cell_v": [0.0] * 14,
         "cell_count": 1, "connected": True, "id": 0, "warning": 0}
        for t, v, i, q in zip(t_s, voltage_v, current_a, charge_ah, strict=True)
    ]  # fmt: skip
    write_ulog(path, [samples], start_us=0)
