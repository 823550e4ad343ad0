"""Battery data from flight logs: PX4 ULog (``battery_status``) and ArduPilot DataFlash
(``BAT``, ``BCL``, old ``CURR``), turned into PackPilot's log vocabulary.

What a log does not carry is said, never filled in silently: a log without temperature gives
no ``temp_c`` column unless the user states one (``--assume-temp-c``), a log without per-cell
voltages gives ``min_cell_v`` only as the average cell (pack voltage / cell count, said so), a
battery without a current sensor gives no ``current_a``. Each such gap is a note in the
:class:`Table` and, for a column that cannot be made, a hint naming what to give.

The parsers are optional (``pip install 'packpilot[logs]'``): ``pyulog`` for ULog,
``pymavlink`` for DataFlash.
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.errors import InputError

F64 = NDArray[np.float64]

MAX_ABS = 1e9
"""Largest magnitude a logged battery value may have (the CSV reader's bound too)."""


@dataclass(frozen=True)
class BatterySeries:
    """One battery's samples as the log has them; ``None`` = the log does not carry it."""

    name: str
    """PackPilot's name for it: A, B, … in the log's instance order."""
    source: str
    """Where it came from, e.g. ``battery_status instance 0``."""
    t_s: F64
    voltage_v: F64
    current_a: F64 | None = None
    temp_c: F64 | None = None
    cells_v: F64 | None = None
    """(samples, cells) measured cell voltages, when the log has real ones."""
    cell_count: int | None = None
    soc: F64 | None = None
    present: F64 | None = None
    notes: tuple[str, ...] = ()
    discharged_mah: F64 | None = None
    """The autopilot's own charge counter (PX4 ``discharged_mah``, ArduPilot ``CurrTot``)."""
    warning: F64 | None = None
    """The autopilot's battery warning level per sample (PX4 ``warning``: 0 none, 1 low,
    2 critical, 3 emergency, 4 failed)."""
    serial_number: str | None = None
    """The battery's serial number when the log has one (0 / empty = none)."""
    time_derived: str | None = None
    """How ``t_s`` was derived when the log's battery message has no time field."""


@dataclass(frozen=True)
class Table:
    """A flight log in the column vocabulary, on one time base."""

    columns: dict[str, F64]
    notes: list[str]
    hints: dict[str, str] = field(default_factory=dict)
    assumed: list[str] = field(default_factory=list)
    """What the user stated in place of what the log lacks (``--assume-temp-c``, ``--cells``)."""

    @property
    def n_rows(self) -> int:
        return len(self.columns["t_s"])

    def write_csv(self, path: Path) -> None:
        """Numbers written exactly (repr), as ``simulate --trace-csv`` writes them."""
        names = list(self.columns)
        with path.open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(names)
            w.writerows(zip(*(self.columns[n].tolist() for n in names), strict=True))


@dataclass(frozen=True)
class FlightLog:
    path: Path
    format: str
    batteries: list[BatterySeries]
    notes: tuple[str, ...] = ()
    modes: tuple[tuple[float, str], ...] = ()
    """Flight-mode changes as the autopilot logged them: (t_s, mode name)."""
    autopilot: str | None = None
    """The autopilot and version the log names (e.g. ``ArduCopter V3.1``), when it does."""
    texts: tuple[tuple[float, str], ...] = ()
    """The autopilot's own battery messages (t_s, text), e.g. MAVLink STATUSTEXT
    "Low Battery!", when the log carries them."""

    def table(self, *, cells: int | None = None, assume_temp_c: float | None = None) -> Table:
        """The batteries on the union of their sample times, each battery's latest value
        held between its own samples (what a controller reading the latest message sees)."""
        return _table(self, cells, assume_temp_c)


def battery_name(index: int) -> str:
    """A, B, …, Z, then B26, B27 … (names the project uses for batteries)."""
    return chr(ord("A") + index) if index < 26 else f"B{index}"


def hold(x: F64) -> tuple[F64, int, int]:
    """``x`` with each NaN replaced by the last finite value before it (the first finite one
    for leading NaN); with the counts of held and of leading samples."""
    ok = np.isfinite(x)
    if ok.all():
        return x, 0, 0
    idx = np.where(ok, np.arange(len(x)), 0)
    np.maximum.accumulate(idx, out=idx)
    first = int(np.argmax(ok))
    lead = first
    idx[:first] = first
    return x[idx], int((~ok).sum()) - lead, lead


def _check_finite(path: Path, what: str, x: F64) -> None:
    bad = np.flatnonzero(~(np.abs(x) <= MAX_ABS))
    if bad.size:
        raise InputError(f"{path}: {what}: {x.flat[bad[0]]:g} is beyond +-{MAX_ABS:g}")


def _time_base(log: FlightLog) -> F64:
    start = max(float(b.t_s[0]) for b in log.batteries)
    t = np.unique(np.concatenate([b.t_s for b in log.batteries]))
    return t[t >= start]


def _table(log: FlightLog, cells: int | None, assume_temp_c: float | None) -> Table:
    if cells is not None and not 1 <= cells <= 1000:
        raise InputError(f"{log.path}: --cells {cells}: must be 1..1000")
    if assume_temp_c is not None and not (
        math.isfinite(assume_temp_c) and -60.0 <= assume_temp_c <= 100.0
    ):
        raise InputError(f"{log.path}: --assume-temp-c {assume_temp_c:g}: must be -60..100")
    t = _time_base(log)
    cols: dict[str, F64] = {"t_s": t}
    notes = [f"{log.format}: {', '.join(f'{b.name} = {b.source}' for b in log.batteries)}"]
    notes += list(log.notes)
    if len(log.batteries) > 1:
        notes.append(
            "rows are the union of the batteries' sample times from the first time every "
            "battery has reported; each battery's latest value is held between its samples"
        )
    hints: dict[str, str] = {}
    assumed: list[str] = []
    notes += autopilot_notes(log)
    for b in log.batteries:
        idx = np.searchsorted(b.t_s, t, side="right") - 1
        notes += [f"{b.name}: {n}" for n in b.notes]
        for col, note in _battery_columns(log.path, b, idx, cells, assume_temp_c, hints):
            cols.update(col)
            if note:
                (assumed if isinstance(note, Assumed) else notes).append(f"{b.name}: {note}")
    return Table(columns=cols, notes=notes, hints=hints, assumed=assumed)


WARNING_NAMES = ("none", "low", "critical", "emergency", "failed", "unhealthy", "charging")
"""PX4's ``battery_status.warning`` levels in order (BATTERY_WARNING_*)."""

MAX_MODES_NOTED = 12


def autopilot_notes(log: FlightLog) -> list[str]:
    """What the autopilot itself said about each battery and the flight (its charge counter,
    remaining, warnings, serial number, flight modes): a pilot compares PackPilot with it."""
    out: list[str] = []
    if log.autopilot:
        out.append(f"autopilot: {log.autopilot}")
    for b in log.batteries:
        out += [f"{b.name}: {x}" for x in battery_facts(b)]
    if log.modes:
        shown = ", ".join(f"{m} at {t:.1f} s" for t, m in log.modes[:MAX_MODES_NOTED])
        more = len(log.modes) - MAX_MODES_NOTED
        out.append(f"flight modes: {shown}" + (f" and {more} more" if more > 0 else ""))
    return out


def battery_facts(b: BatterySeries) -> list[str]:
    """One line per thing the autopilot reported for a battery (only what it reported)."""
    facts: list[str] = []
    if b.time_derived:
        facts.append(f"time derived: {b.time_derived}")
    if b.serial_number:
        facts.append(f"serial number {b.serial_number}")
    d = b.discharged_mah
    if d is not None and np.isfinite(d).any() and np.nanmax(d) > 0:
        facts.append(f"the autopilot counted {float(np.nanmax(d)):.0f} mAh discharged")
    if b.soc is not None and np.isfinite(b.soc).any():
        ok = b.soc[np.isfinite(b.soc)]
        low = f" (lowest {100 * ok.min():.0f} %)" if ok.min() < ok[-1] - 0.005 else ""
        facts.append(
            f"the autopilot's remaining went from {100 * ok[0]:.0f} % to {100 * ok[-1]:.0f} %"
            + low
        )
    if b.warning is not None and np.any(b.warning > 0):
        w = b.warning
        worst = int(np.max(w))
        name = WARNING_NAMES[worst] if worst < len(WARNING_NAMES) else str(worst)
        first = float(b.t_s[int(np.argmax(w > 0))])
        facts.append(
            f"the autopilot warned from {first:.1f} s, worst level {name} "
            f"({int(np.sum(w == worst))} of {len(w)} samples)"
        )
    return facts


class Assumed(str):
    """A note that records what the user stated (an option), not what the log says."""

    __slots__ = ()


def _series(
    path: Path, b: BatterySeries, what: str, x: F64, idx: NDArray[np.intp]
) -> tuple[F64, str]:
    if not np.isfinite(x).any():
        raise InputError(f"{path}: battery {b.name} ({b.source}): no valid {what} sample")
    held, n_held, lead = hold(x)
    _check_finite(path, f"battery {b.name} {what}", held)
    note = ""
    if n_held or lead:
        note = f"{what} missing in {n_held + lead} of {len(x)} samples: the last value held" + (
            f" ({lead} leading samples take the first value)" if lead else ""
        )
    return held[idx], note


def _battery_columns(
    path: Path, b: BatterySeries, idx: NDArray[np.intp], cells: int | None,
    assume_temp_c: float | None, hints: dict[str, str],
) -> Iterator[tuple[dict[str, F64], str]]:  # fmt: skip
    n = b.name
    v, note = _series(path, b, "voltage_v", b.voltage_v, idx)
    yield {f"{n}_voltage_v": v}, note
    if b.current_a is not None:
        i, note = _series(path, b, "current_a", b.current_a, idx)
        yield {f"{n}_current_a": i}, note
    else:
        hints[f"{n}_current_a"] = f"battery {n} has no current measurement in the log"
    yield from _temperature(path, b, idx, assume_temp_c, hints)
    yield from _cells(path, b, idx, v, cells, hints)
    if b.soc is not None:
        soc, note = _series(path, b, "soc", b.soc, idx)
        yield {f"{n}_soc": soc}, note
    if b.present is not None:
        yield {f"{n}_present": b.present[idx]}, ""


def _temperature(
    path: Path, b: BatterySeries, idx: NDArray[np.intp], assume: float | None,
    hints: dict[str, str],
) -> Iterator[tuple[dict[str, F64], str]]:  # fmt: skip
    n = b.name
    if b.temp_c is not None and np.isfinite(b.temp_c).any():
        temp, note = _series(path, b, "temp_c", b.temp_c, idx)
        yield {f"{n}_temp_c": temp}, note
        if assume is not None:
            yield {}, f"--assume-temp-c {assume:g} not used: the log has its temperature"
    elif assume is not None:
        yield (
            {f"{n}_temp_c": np.full(len(idx), assume)},
            Assumed(
                f"temp_c = {assume:g} degC assumed (--assume-temp-c): the log has no temperature"
            ),
        )
    else:
        hints[f"{n}_temp_c"] = (
            f"battery {n}: the log has no temperature; give --assume-temp-c T to use a stated "
            "constant temperature"
        )
        yield {}, "no temperature in the log: no temp_c column (give --assume-temp-c T)"


def _cells(
    path: Path, b: BatterySeries, idx: NDArray[np.intp], v: F64, cells: int | None,
    hints: dict[str, str],
) -> Iterator[tuple[dict[str, F64], str]]:  # fmt: skip
    n = b.name
    if cells is not None and (b.cells_v is not None or b.cell_count):
        yield {}, f"--cells {cells} not used: the log has its own cell voltages or cell count"
    measured = None if b.cells_v is None else b.cells_v[:, np.isfinite(b.cells_v).any(axis=0)]
    if measured is not None and measured.shape[1]:
        cv = np.column_stack([hold(measured[:, k])[0] for k in range(measured.shape[1])])
        _check_finite(path, f"battery {n} cell voltage", cv)
        cv = cv[idx]
        groups = {f"{n}_g{k}_v": cv[:, k] for k in range(cv.shape[1])}
        yield {f"{n}_min_cell_v": cv.min(axis=1), f"{n}_max_cell_v": cv.max(axis=1), **groups}, ""
        return
    count = b.cell_count or cells
    if count:
        how = "the log's cell count" if b.cell_count else "--cells"
        text = (
            f"no per-cell voltages: min_cell_v = max_cell_v = voltage_v / {count} ({how}), the "
            "average cell; a weak cell sits lower"
        )
        yield (
            {f"{n}_min_cell_v": v / count, f"{n}_max_cell_v": v / count},
            text if b.cell_count else Assumed(text),
        )
        return
    hints[f"{n}_min_cell_v"] = (
        f"battery {n}: the log has neither cell voltages nor a cell count; give --cells N to "
        "use voltage_v / N"
    )
    yield {}, "no cell voltages and no cell count: no min_cell_v column (give --cells N)"


def read_flight_log(path: Path) -> FlightLog:
    """A flight log by its suffix: ``.ulg`` PX4 ULog, ``.bin`` / ``.log`` ArduPilot
    DataFlash (binary / text), ``.tlog`` MAVLink telemetry log (a ground station's)."""
    if not path.exists():
        raise InputError(f"{path}: log file not found")
    if not path.is_file():
        raise InputError(f"{path}: log is not a file")
    suffix = path.suffix.lower()
    if suffix == ".ulg":
        from packpilot.io.flightlog.ulog import read_ulog

        return read_ulog(path)
    if suffix in (".bin", ".log"):
        from packpilot.io.flightlog.dataflash import read_dataflash

        return read_dataflash(path, text=suffix == ".log")
    if suffix == ".tlog":
        from packpilot.io.flightlog.tlog import read_tlog

        return read_tlog(path)
    raise InputError(f"{path}: not a flight log (.ulg, .bin, .log or .tlog)")


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """The parsers' own prints (progress, one line per bad byte, some from compiled code
    straight to file descriptors 1 and 2) held back: a damaged log is reported once, as one
    error line."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        os.dup2(null, 2)
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, null):
            os.close(fd)


def need(module: str, package: str, what: str) -> object:
    """Import an optional parser, or a one-line error naming the extra that installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise InputError(
            f"reading {what} needs the optional package {package}: pip install 'packpilot[logs]'"
        ) from None


__all__ = [
    "BatterySeries",
    "FlightLog",
    "Table",
    "autopilot_notes",
    "battery_facts",
    "battery_name",
    "hold",
    "need",
    "quiet",
    "read_flight_log",
]
