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
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import F64, BatterySeries, FlightLog, battery_name, need, quiet

TYPES = ("BAT", "BCL", "CURR", "CUR2")
CENTI_FORMATS = "hHiI"
"""Integer field formats whose voltage/current is in hundredths (old CURR: cV, cA)."""
NO_CELL = (0, 65535)


def _open(path: Path, text: bool) -> Any:
    need("pymavlink", "pymavlink", "an ArduPilot DataFlash log")
    from pymavlink import DFReader

    try:
        return DFReader.DFReader_text(str(path)) if text else DFReader.DFReader_binary(str(path))
    except Exception as err:  # the reader raises many kinds on a damaged file
        kind = "text" if text else "binary"
        raise InputError(
            f"{path}: not a readable DataFlash {kind} log ({type(err).__name__}: {err})"
        ) from None


def _time_s(m: Any) -> float:
    if "TimeUS" in m._fieldnames:
        return float(m.TimeUS) * 1e-6
    return float(m.TimeMS) * 1e-3


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


def _collect(
    log: Any, path: Path
) -> tuple[
    dict[tuple[str, int], list[dict[str, float]]], dict[int, list[tuple[float, list[float]]]]
]:
    bat: dict[tuple[str, int], list[dict[str, float]]] = defaultdict(list)
    bcl: dict[int, list[tuple[float, list[float]]]] = defaultdict(list)
    try:
        while (m := log.recv_match(type=list(TYPES))) is not None:
            kind = m.get_type()
            if kind == "BCL":
                cells = [
                    float(getattr(m, f"V{k}")) for k in range(1, 13) if f"V{k}" in m._fieldnames
                ]
                bcl[_instance(m)].append((_time_s(m), cells))
                continue
            inst = 1 if kind == "CUR2" else _instance(m)
            row = {"t_s": _time_s(m), "volt": _scaled(m, "Volt"), "curr": _scaled(m, "Curr")}
            if "Temp" in m._fieldnames:
                row["temp"] = float(m.Temp)
            if "RemPct" in m._fieldnames:
                row["rem"] = float(m.RemPct)
            bat[(kind if kind != "CUR2" else "CURR", inst)].append(row)
    except (AttributeError, KeyError, ValueError, struct.error, UnicodeDecodeError) as err:
        raise InputError(f"{path}: a BAT/BCL/CURR message is malformed ({err})") from None
    return bat, bcl


def read_dataflash(path: Path, *, text: bool) -> FlightLog:
    """Every battery instance of ``BAT`` (or, in a log without BAT, ``CURR``/``CUR2``)."""
    with quiet():  # DFReader prints "bad header …" per stray byte: our error says it once
        log = _open(path, text)
        try:
            bat, bcl = _collect(log, path)
        finally:
            log.close()
    kind = "BAT" if any(k == "BAT" for k, _ in bat) else "CURR"
    instances = sorted(i for k, i in bat if k == kind)
    if not instances:
        raise InputError(f"{path}: no BAT, BCL or CURR messages (no battery data)")
    fmt = f"ArduPilot DataFlash ({'text' if text else 'binary'})"
    notes = () if kind == "BAT" else ("an old (3.x) log: CURR / CUR2 carry no temperature",)
    batteries = [
        _battery(path, k, kind, inst, bat[(kind, inst)], bcl.get(inst, []))
        for k, inst in enumerate(instances)
    ]
    return FlightLog(path=path, format=fmt, batteries=batteries, notes=notes)


def _increasing(path: Path, t: F64, what: str) -> np.ndarray[Any, np.dtype[np.bool_]]:
    keep: np.ndarray[Any, np.dtype[np.bool_]] = np.append(np.diff(t) > 0, True)
    if np.any(np.diff(t[keep]) <= 0):
        raise InputError(f"{path}: {what} timestamps go backwards")
    return keep


def _battery(
    path: Path, k: int, kind: str, inst: int, rows: Sequence[Mapping[str, float]],
    bcl: Sequence[tuple[float, list[float]]],
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
