"""ArduPilot DataFlash logs, binary (.bin) and text (.log), read with ``pymavlink``'s
DFReader; and minimal writers for the sample logs PackPilot ships.

Messages read: ``BAT`` (4.x: ``Inst``, ``Volt``, ``Curr``, ``Temp``, ``RemPct``; ``Instance`` in
some versions), ``BCL`` per-cell voltages (``V1..V12`` in mV; 0 or 65535 = no such cell), and
in old 3.x logs ``CURR`` (battery 0) / ``CUR2`` (battery 1). ``Curr`` is positive when
discharging, PackPilot's sign. ArduPilot writes ``Temp`` 0 for a monitor without a temperature
sensor: a temperature that is exactly 0 throughout is read as "not measured". A voltage or
current stored as an integer field (``h``/``H``/``i``/``I``, old CURR) is in hundredths (cV,
cA); a float field is in V and A. Time is ``TimeUS`` (``TimeMS`` in the oldest) since boot.
"""

from __future__ import annotations

import math
import struct
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import F64, BatterySeries, FlightLog, battery_name, need, quiet

TYPES = ("BAT", "BCL", "CURR", "CUR2")
AUX_TYPES = ("GPS", "MODE", "MSG", "VER")
"""Read beside the battery messages: a clock for 3.x CURR, flight modes, the version."""
CENTI_FORMATS = "hHiI"
"""Integer field formats whose voltage/current is in hundredths (old CURR: cV, cA)."""
NO_CELL = (0, 65535)


def _open(path: Path, text: bool) -> Any:
    need("pymavlink", "pymavlink", "an ArduPilot DataFlash log")
    from pymavlink import DFReader

    class _NoClock(DFReader.DFReaderClock):  # type: ignore[misc]
        def set_message_timestamp(self, m: Any) -> None:
            m._timestamp = 0.0

    def no_clock(self: Any) -> None:
        """DFReader's clock guesses wall time from GPS and fails on 3.0 logs (GPS without
        Week); PackPilot reads each message's own time fields and derives the rest itself."""
        self._rewind()
        self.clock = _NoClock()

    base = DFReader.DFReader_text if text else DFReader.DFReader_binary
    reader = type("_Reader", (base,), {"init_clock": no_clock})
    try:
        return reader(str(path))
    except Exception as err:  # the reader raises many kinds on a damaged file
        kind = "text" if text else "binary"
        raise InputError(
            f"{path}: not a readable DataFlash {kind} log ({type(err).__name__}: {err})"
        ) from None


TIME_FIELDS = (("TimeUS", 1e-6), ("TimeMS", 1e-3))
"""A battery message's own time (since boot). Old 3.x CURR has neither: see _derive_times."""
GPS_TIME_FIELDS = (("TimeUS", 1e-6), ("T", 1e-3), ("TimeMS", 1e-3), ("GMS", 1e-3), ("Time", 1e-3))
"""GPS clocks in order of preference: boot time (4.x TimeUS, 3.1 T), then GPS time of week
(3.1 TimeMS, 3.0 Time); any of them is a steady clock to interpolate the other messages on."""
MIN_CURRENT_FOR_RATE_A = 1.0
"""Samples below this current are too small to read a logging interval off the charge counter."""


def _time_s(m: Any) -> float | None:
    for name, scale in TIME_FIELDS:
        if name in m._fieldnames:
            return float(getattr(m, name)) * scale
    return None


def _gps_time_s(m: Any) -> float | None:
    for name, scale in GPS_TIME_FIELDS:
        if name in m._fieldnames:
            value = float(getattr(m, name))
            return value * scale if value > 0 else None
    return None


def _scaled(m: Any, name: str) -> float:
    """A voltage or current in V / A whatever the field's storage (see module doc)."""
    value = float(getattr(m, name))
    fmt = m.fmt.format[m.fmt.colhash[name]]
    return value * 0.01 if fmt in CENTI_FORMATS else value


def _instance(m: Any) -> int:
    for name in ("Inst", "Instance", "I"):
        if name in m._fieldnames:
            return int(getattr(m, name))
    return 0


@dataclass
class _Raw:
    """What one pass over the log collected; ``ord`` counts the collected messages in file
    order (the clock of last resort for messages without a time field)."""

    bat: dict[tuple[str, int], list[dict[str, float]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    bcl: dict[int, list[tuple[float, list[float]]]] = field(
        default_factory=lambda: defaultdict(list)
    )
    gps: list[tuple[int, float]] = field(default_factory=list)
    modes: list[tuple[int, float | None, str | int]] = field(default_factory=list)
    version: str | None = None


def _mode_name(raw: str | int, version: str | None) -> str:
    """A 3.x text log names the mode; a binary log numbers it, per vehicle type."""
    if isinstance(raw, str):
        return raw
    from pymavlink import mavutil

    table = {
        "ArduCopter": mavutil.mode_mapping_acm, "ArduPlane": mavutil.mode_mapping_apm,
        "ArduRover": mavutil.mode_mapping_rover, "Rover": mavutil.mode_mapping_rover,
    }  # fmt: skip
    vehicle = (version or "").split(" ")[0]
    names: dict[int, str] = table.get(vehicle, {})
    return names.get(int(raw), f"mode {int(raw)}")


def _collect(log: Any, path: Path) -> _Raw:
    raw = _Raw()
    k = 0
    try:
        while (m := log.recv_match(type=list(TYPES + AUX_TYPES))) is not None:
            k += 1
            _one(raw, m, k)
    except (AttributeError, KeyError, ValueError, struct.error, UnicodeDecodeError) as err:
        raise InputError(f"{path}: a BAT/BCL/CURR message is damaged ({err})") from None
    return raw


def _one(raw: _Raw, m: Any, k: int) -> None:
    kind = m.get_type()
    names = m._fieldnames
    if kind == "GPS":
        t = _gps_time_s(m)
        if t is not None and (not raw.gps or t > raw.gps[-1][1]):
            raw.gps.append((k, t))
        return
    if kind in ("MSG", "VER"):
        text = str(getattr(m, "FWS" if kind == "VER" else "Message", ""))
        if raw.version is None and text.startswith(("Ardu", "Rover", "Blimp", "Antenna")):
            raw.version = text
        return
    if kind == "MODE":
        mode = m.Mode
        raw.modes.append((k, _time_s(m), mode if isinstance(mode, str) else int(mode)))
        return
    if kind == "BCL":
        cells = [float(getattr(m, f"V{j}")) for j in range(1, 13) if f"V{j}" in names]
        t = _time_s(m)
        if t is not None:
            raw.bcl[_instance(m)].append((t, cells))
        return
    inst = 1 if kind == "CUR2" else _instance(m)
    t = _time_s(m)
    row = {"t_s": math.nan if t is None else t, "ord": float(k),
           "volt": _scaled(m, "Volt"), "curr": _scaled(m, "Curr")}  # fmt: skip
    for src, dst in (("Temp", "temp"), ("RemPct", "rem"), ("CurrTot", "mah")):
        if src in names:
            row[dst] = float(getattr(m, src))
    raw.bat[(kind if kind != "CUR2" else "CURR", inst)].append(row)


def _check_whole(path: Path, log: Any, text: bool) -> None:
    """A log cut inside a message (a copy stopped early, power lost while writing) is refused
    in one line: what it holds up to there is intact, but its end is not the flight's end."""
    if text:
        with path.open("rb") as fh:
            fh.seek(max(0, path.stat().st_size - 1))
            last = fh.read(1)
        if last not in (b"\n", b""):
            raise InputError(f"{path}: truncated: the last line has no end (the file was cut)")
        return
    ends = [o[-1] + log.formats[t].len for t, o in enumerate(log.offsets) if o and t in log.formats]
    end = max(ends, default=int(log.data_len))
    if end != int(log.data_len):
        raise InputError(
            f"{path}: truncated: the file ends inside a message ({int(log.data_len)} bytes; "
            f"the last message needs {end - int(log.data_len)} more)"
            if end > int(log.data_len)
            else f"{path}: truncated: {int(log.data_len) - end} bytes after the last whole message"
        )


def _derive_times(path: Path, raw: _Raw, rows: list[dict[str, float]]) -> str | None:
    """Fill ``t_s`` of messages logged without a time field (ArduCopter 3.0/3.1 CURR:
    ``FMT, 9, 19, CURR, hIhhhf, ...``): interpolated on the GPS clock by the messages' order
    in the file when the log has GPS time, else at the logging interval the autopilot's own
    charge counter shows (CurrTot grows by I dt / 3.6 mAh). Returns how, for the notes."""
    if not rows or math.isfinite(rows[0]["t_s"]):
        return None
    ords = np.array([r["ord"] for r in rows])
    if len(raw.gps) >= 2:
        g_ord = np.array([g[0] for g in raw.gps], dtype=np.float64)
        g_t = np.array([g[1] for g in raw.gps])
        slope = (g_t[-1] - g_t[0]) / (g_ord[-1] - g_ord[0])
        t = np.interp(ords, g_ord, g_t)
        t = np.where(ords < g_ord[0], g_t[0] + (ords - g_ord[0]) * slope, t)
        t = np.where(ords > g_ord[-1], g_t[-1] + (ords - g_ord[-1]) * slope, t)
        how = (
            f"the battery message has no time field: times interpolated between {len(g_t)} "
            "GPS time stamps by message order"
        )
    else:
        dt = _interval_from_counter(rows)
        if dt is None:
            raise InputError(
                f"{path}: the battery message (CURR) has no time field, and the log has "
                "neither GPS time nor a charge counter (CurrTot) with current to derive it from"
            )
        t = np.arange(len(rows)) * dt
        how = (
            "the battery message has no time field and the log no GPS time: times at the "
            f"logging interval {dt:.3f} s that the charge counter CurrTot shows "
            "(median of 3.6 dmAh / I)"
        )
    t = t - t[0]
    for r, tt in zip(rows, t, strict=True):
        r["t_s"] = float(tt)
    return how


def _interval_from_counter(rows: list[dict[str, float]]) -> float | None:
    if not all("mah" in r for r in rows):
        return None
    mah = np.array([r["mah"] for r in rows])
    cur = np.array([r["curr"] for r in rows])
    i_mid = 0.5 * (cur[1:] + cur[:-1])
    ok = (i_mid > MIN_CURRENT_FOR_RATE_A) & (np.diff(mah) > 0)
    if ok.sum() < 5:
        return None
    return float(np.median(3.6 * np.diff(mah)[ok] / i_mid[ok]))


def _header_version(path: Path, text: bool) -> str | None:
    """A text log's banner (``ArduCopter V3.0.1``) before its first FMT line."""
    if not text:
        return None
    with path.open("rb") as fh:
        head = fh.read(4096).decode("ascii", "replace")
    for line in head.splitlines():
        if line.startswith(("Ardu", "Rover")) and " V" in line:
            return line.strip()
    return None


def read_dataflash(path: Path, *, text: bool) -> FlightLog:
    """Every battery instance of ``BAT`` (or, in a log without BAT, ``CURR``/``CUR2``)."""
    with quiet():  # DFReader prints "bad header …" per stray byte: our error says it once
        log = _open(path, text)
        try:
            raw = _collect(log, path)
            _check_whole(path, log, text)
        finally:
            log.close()
    bat = raw.bat
    kind = "BAT" if any(k == "BAT" for k, _ in bat) else "CURR"
    instances = sorted(i for k, i in bat if k == kind)
    if not instances:
        raise InputError(
            f"{path}: a DataFlash log without battery data: it has no BAT or CURR messages"
        )
    fmt = f"ArduPilot DataFlash ({'text' if text else 'binary'})"
    notes = () if kind == "BAT" else ("an old (3.x) log: CURR / CUR2 carry no temperature",)
    derived = {i: _derive_times(path, raw, bat[(kind, i)]) for i in instances}
    batteries = [
        _battery(path, k, kind, inst, bat[(kind, inst)], raw.bcl.get(inst, []), derived[inst])
        for k, inst in enumerate(instances)
    ]
    version = raw.version or _header_version(path, text)
    return FlightLog(
        path=path, format=fmt, batteries=batteries, notes=notes,
        modes=_mode_times(raw, bat[(kind, instances[0])]), autopilot=version,
    )  # fmt: skip


def _mode_times(raw: _Raw, rows: list[dict[str, float]]) -> tuple[tuple[float, str], ...]:
    """Mode changes on the battery's time base (a 3.x MODE has no time: placed by order)."""
    if not raw.modes or not rows:
        return ()
    ords = np.array([r["ord"] for r in rows])
    ts = np.array([r["t_s"] for r in rows])
    out: list[tuple[float, str]] = []
    for k, t, mode in raw.modes:
        name = _mode_name(mode, raw.version)
        tt = t if t is not None else float(np.interp(k, ords, ts))
        if not out or out[-1][1] != name:
            out.append((tt, name))
    return tuple(out)


def _increasing(path: Path, t: F64, what: str) -> np.ndarray[Any, np.dtype[np.bool_]]:
    keep: np.ndarray[Any, np.dtype[np.bool_]] = np.append(np.diff(t) > 0, True)
    if np.any(np.diff(t[keep]) <= 0):
        raise InputError(f"{path}: {what} timestamps go backwards")
    return keep


def _battery(
    path: Path, k: int, kind: str, inst: int, rows: Sequence[Mapping[str, float]],
    bcl: Sequence[tuple[float, list[float]]], derived: str | None = None,
) -> BatterySeries:  # fmt: skip
    t = np.array([r["t_s"] for r in rows])
    keep = _increasing(path, t, f"{kind} instance {inst}")

    def col(key: str) -> F64 | None:
        if not all(key in r for r in rows):
            return None
        values: F64 = np.array([r[key] for r in rows], dtype=np.float64)[keep]
        return values

    notes: list[str] = []
    temp = col("temp")
    if temp is None or np.all(temp == 0.0):
        notes.append(
            "Temp is 0 throughout (ArduPilot's value without a temperature sensor): no temperature"
            if temp is not None
            else f"{kind} has no temperature field"
        )
        temp = None
    rem = col("rem")
    soc = rem / 100.0 if rem is not None and np.any(rem != 0.0) else None
    t_kept = t[keep]
    cells = _cells(path, inst, bcl, t_kept, notes)
    source = f"{kind} instance {inst}" if kind == "BAT" else ("CURR" if inst == 0 else "CUR2")
    return BatterySeries(
        name=battery_name(k), source=source, t_s=t_kept, voltage_v=col("volt"),  # type: ignore[arg-type]
        current_a=col("curr"), temp_c=temp, cells_v=cells, soc=soc, notes=tuple(notes),
        discharged_mah=col("mah"), time_derived=derived,
    )  # fmt: skip


def _cells(
    path: Path, inst: int, bcl: Sequence[tuple[float, list[float]]], t: F64, notes: list[str]
) -> F64 | None:
    """BCL cell voltages (V) held onto the battery's sample times, or None with a note."""
    if not bcl:
        notes.append("no BCL messages: no per-cell voltages")
        return None
    bt = np.array([b[0] for b in bcl])
    raw = np.array([b[1] for b in bcl], dtype=np.float64)
    used = [j for j in range(raw.shape[1]) if np.any(~np.isin(raw[:, j], NO_CELL))]
    if not used:
        notes.append("BCL lists no cells: no per-cell voltages")
        return None
    keep = _increasing(path, bt, f"BCL instance {inst}")
    bt, mv = bt[keep], raw[keep][:, used]
    mv = np.where(np.isin(mv, NO_CELL), np.nan, mv)
    idx = np.searchsorted(bt, t, side="right") - 1
    if idx[0] < 0:
        notes.append(
            f"BCL starts {bt[0] - t[0]:.3g} s after BAT: earlier samples take the first BCL"
        )
    cells: F64 = mv[np.maximum(idx, 0)] / 1000.0
    return cells


# ----------------------------------------------------------------------------- writers

FORMATS: Mapping[str, tuple[int, str, str]] = {
    "BAT": (130, "QBfffffcfBB", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res,RemPct,H"),
    "BCL": (
        131,
        "QBfHHHHHHHHHHHH",
        "TimeUS,Instance,Volt," + ",".join(f"V{k}" for k in range(1, 13)),
    ),
    "CURR": (132, "QhhhHf", "TimeUS,Throttle,Volt,Curr,Vcc,CurrTot"),
}
"""Message layouts the writers use: BAT and BCL as ArduPilot 4.x logs them, CURR as 3.x."""

_STRUCT = {"Q": "Q", "B": "B", "f": "f", "c": "h", "H": "H", "h": "h", "I": "I", "i": "i",
           "n": "4s", "N": "16s", "Z": "64s"}  # fmt: skip
_FMT_FMT = ("BBnNZ", "Type,Length,Name,Format,Columns")


def _length(fmt: str) -> int:
    return 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))


def _stored(fmt: str, value: float) -> float | int:
    """The stored integer of a field (``c`` is hundredths) or the float itself."""
    if fmt == "c":
        return round(value * 100.0)
    if fmt == "f":
        return float(value)
    return round(value)


def write_bin(path: Path, messages: Iterable[tuple[str, Sequence[float]]]) -> None:
    """A minimal binary DataFlash log: the FMT of FMT, the FMT of each message used, then the
    messages; each message is 0xA3 0x95, its type id and its little-endian fields, the layout
    of ArduPilot's ``AP_Logger`` (pymavlink reads it back; tests do)."""
    msgs = list(messages)
    out = bytearray()

    def fmt_msg(type_id: int, name: str, fmt: str, cols: str) -> bytes:
        body = struct.pack(
            "<BB4s16s64s", type_id, _length(fmt), name.encode(), fmt.encode(), cols.encode()
        )
        return b"\xa3\x95\x80" + body

    out += fmt_msg(128, "FMT", *_FMT_FMT)
    for name in dict.fromkeys(n for n, _ in msgs):
        type_id, fmt, cols = FORMATS[name]
        out += fmt_msg(type_id, name, fmt, cols)
    for name, values in msgs:
        type_id, fmt, _ = FORMATS[name]
        st = "<" + "".join(_STRUCT[c] for c in fmt)
        out += bytes([0xA3, 0x95, type_id]) + struct.pack(
            st, *(_stored(c, v) for c, v in zip(fmt, values, strict=True))
        )
    path.write_bytes(bytes(out))


def _text_value(fmt: str, value: float) -> str:
    if fmt in "fc":
        return f"{value:.6g}" if math.isfinite(value) else "nan"
    return str(round(value))


def write_text(path: Path, messages: Iterable[tuple[str, Sequence[float]]]) -> None:
    """The same log as text, as ArduPilot's text logs and ``mavlogdump --format=...`` lines
    look: ``NAME, v1, v2, …`` after ``FMT`` lines (values in real units: Temp in degC)."""
    msgs = list(messages)
    lines = [f"FMT, 128, 89, FMT, {_FMT_FMT[0]}, {_FMT_FMT[1]}"]
    for name in dict.fromkeys(n for n, _ in msgs):
        type_id, fmt, cols = FORMATS[name]
        lines.append(f"FMT, {type_id}, {_length(fmt)}, {name}, {fmt}, {cols}")
    for name, values in msgs:
        fmt = FORMATS[name][1]
        lines.append(
            ", ".join([name, *(_text_value(c, v) for c, v in zip(fmt, values, strict=True))])
        )
    path.write_text("\n".join(lines) + "\n", encoding="ascii")


__all__ = ["FORMATS", "read_dataflash", "write_bin", "write_text"]
