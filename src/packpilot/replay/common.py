"""Shared plumbing for replaying logged measurements through a controller.

A replay reads a log — a CSV in PackPilot's column vocabulary (what ``simulate --trace-csv``
writes and ``packpilot import`` produces) or a flight log (PX4 ULog, ArduPilot DataFlash) read
directly — runs a pure controller over it and returns a table; the CLI writes the table and
prints the summary. Validation is strict and names the row and column at fault, because a
silently skipped row would change the accumulated timers the methods depend on. Only the
columns a replay reads are parsed: a trace's status columns (``P1``, ``True``, empty cells)
are carried, never refused.

The vocabulary: per battery ``<name>_<channel>`` with the channels of
:data:`~packpilot.contract.record.BATTERY_CHANNELS` (``A_current_a``, ``A_min_cell_v``) and
group voltages ``<name>_g<k>_v``; a log of one battery may drop the ``<name>_`` prefix
(``current_a``, ``temp_c``, ``min_cell_v``).
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config.base import MAX_TIME_S
from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.errors import InputError, read_text

MAX_LOG_ABS = MAX_TIME_S
"""Largest magnitude any logged number may have (1e9: seconds, volts, amperes, degC alike).
A time of 1e306 s overflowed when a method turned it into milliseconds, and a 1e308 time gap
made an equalization replay apply its formulas gap / T1 times: nothing a logger writes is
that large, so such a cell is refused with its row and column."""

AUX = "aux"
"""The auxiliary battery's prefix in a trace: not one of the pack's batteries unless asked."""

CellValue = float | int | str | bool | None
MEASURED_CHANNELS = frozenset(
    ("voltage_v", "current_a", "soc", "temp_c", "min_cell_v", "max_cell_v")
)
"""A battery's columns include a measurement: a method's status columns ``A_seq_chg_on``,
``A_seq_dsg_on`` (a sequencing trace) end in switch channels but made a phantom battery
``A_seq`` that every replay refused the trace for."""
_GROUP_V = re.compile(r"^(?:(.+)_)?g\d+_v$")


@dataclass(frozen=True)
class ReplayResult:
    """Output table (one row per input row) plus a JSON-able summary."""

    columns: list[str]
    rows: list[list[CellValue]]
    summary: dict[str, object] = field(default_factory=dict)

    def write_csv(self, path: Path) -> None:
        with path.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(self.columns)
            writer.writerows(self.rows)


@dataclass(frozen=True)
class LogOptions:
    """What the user adds to a log that lacks it; each use is stated in the summary."""

    battery: str | None = None
    """Which battery of a multi-battery log a one-battery method replays."""
    assume_temp_c: float | None = None
    """Constant temperature used only when the log has none (never silently)."""
    cells: int | None = None
    """Series cell count, for a flight log with neither cell voltages nor a cell count."""


def _number(path: Path, lineno: int, name: str, cell: str, allow_nan: bool) -> float:
    try:
        value = float(cell)
    except ValueError:
        raise InputError(f"{path}: row {lineno}, column {name}: {cell!r} is not a number") from None
    if not allow_nan and not math.isfinite(value):
        raise InputError(f"{path}: row {lineno}, column {name}: {cell!r} is not a finite number")
    if abs(value) > MAX_LOG_ABS:
        raise InputError(
            f"{path}: row {lineno}, column {name}: {value:g} is beyond +-{MAX_LOG_ABS:g}"
        )
    return value


class _CsvColumns(Mapping[str, NDArray[np.float64]]):
    """The columns of a CSV, each parsed (and validated) the first time it is read."""

    def __init__(
        self, path: Path, header: list[str], rows: list[list[str]], lines: list[int],
        allow_nan: bool,
    ) -> None:  # fmt: skip
        self._path, self._header, self._rows, self._lines = path, header, rows, lines
        self._index = {name: j for j, name in enumerate(header)}
        self._allow_nan = allow_nan
        self._cache: dict[str, NDArray[np.float64]] = {}

    def __getitem__(self, name: str) -> NDArray[np.float64]:
        if name not in self._cache:
            j = self._index[name]
            self._cache[name] = np.array(
                [
                    _number(self._path, ln, name, row[j], self._allow_nan)
                    for ln, row in zip(self._lines, self._rows, strict=True)
                ],
                dtype=np.float64,
            )
        return self._cache[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._header)

    def __len__(self) -> int:
        return len(self._header)


@dataclass(frozen=True)
class LogTable:
    """A log: column name -> float array, its source, and what it lacks.

    ``notes`` say what the log does not carry and what was assumed instead (a flight log's
    missing temperature, cell voltages derived from the pack voltage); ``hints`` tell, for a
    column the log cannot provide, why and how to supply it.
    """

    path: Path
    columns: Mapping[str, NDArray[np.float64]]
    n_rows: int = -1
    source: str = "CSV"
    notes: tuple[str, ...] = ()
    hints: Mapping[str, str] = field(default_factory=dict)
    assumed: tuple[str, ...] = ()
    """What the user stated in place of what the log lacks, when the log was imported."""
    flight: Any = None
    """The parsed flight log (:class:`packpilot.io.flightlog.FlightLog`) when the log was one:
    what the autopilot itself said (its charge counter, remaining, warnings, flight modes)."""

    def __len__(self) -> int:
        if self.n_rows >= 0:
            return self.n_rows
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def indexed(self, prefix: str, suffix: str = "") -> list[str]:
        """Column names ``prefix_0 .. prefix_{k-1}`` (``prefix<k>suffix`` with a suffix)
        present in the log, in index order."""
        sep = "" if suffix else "_"
        pat = re.compile(rf"^{re.escape(prefix)}{sep}(\d+){re.escape(suffix)}$")
        found = sorted(
            (int(m.group(1)), name) for name in self.columns if (m := pat.match(name)) is not None
        )
        names = [name for _, name in found]
        for k, (idx, name) in enumerate(found):
            if idx != k:
                raise InputError(
                    f"{self.path}: column {prefix}{sep}{k}{suffix} is missing "
                    f"(found {name} instead)"
                )
        return names

    def require(self, names: Sequence[str], hints: Mapping[str, str] | None = None) -> None:
        """Every column of ``names`` present, or one error naming the missing ones with the
        hint of each (the flight log's own, else ``hints``): why it lacks and what to give."""
        missing = [n for n in names if n not in self.columns]
        if not missing:
            return
        every = {**(hints or {}), **self.hints}
        hints_ = [every[n] for n in missing if n in every]
        why = f" ({'; '.join(dict.fromkeys(hints_))})" if hints_ else ""
        header = ",".join(list(self.columns)[:12]) + (",…" if len(self.columns) > 12 else "")
        raise InputError(
            f"{self.path}: missing column(s) {', '.join(missing)}{why}; header is {header}"
        )

    def batteries(self) -> list[str]:
        """The batteries the log names (``""`` for an unprefixed one-battery log), in order
        of first appearance: a name with at least two battery channels (group voltages
        ``<name>_g<k>_v`` count)."""
        found: dict[str, int] = {}
        measured: set[str] = set()
        for name in self.columns:
            if (g := _GROUP_V.match(name)) is not None:  # a group voltage counts as a channel
                found[g.group(1) or ""] = found.get(g.group(1) or "", 0) + 1
                measured.add(g.group(1) or "")
            for ch in BATTERY_CHANNELS:
                prefix = "" if name == ch else name[: -len(ch) - 1]
                if name == ch or name.endswith("_" + ch):
                    found[prefix] = found.get(prefix, 0) + 1
                    if ch in MEASURED_CHANNELS:
                        measured.add(prefix)
        return [b for b, count in found.items() if count >= 2 and b in measured]

    def battery_prefix(self, battery: str | None) -> tuple[str, str]:
        """(column prefix, battery name) of the battery a one-battery method replays: the one
        asked for, or the log's only one (the auxiliary battery counts only when asked)."""
        names = self.batteries()
        if battery is not None:
            if battery not in names:
                listed = ", ".join(n for n in names if n) or "none named"
                raise InputError(f"{self.path}: --battery {battery}: not in the log ({listed})")
            return f"{battery}_", battery
        pack = [n for n in names if n != AUX]
        if len(pack) > 1:
            listed = ", ".join(n or "(unprefixed)" for n in pack)
            raise InputError(
                f"{self.path}: the log has batteries {listed}: choose one with --battery"
            )
        name = pack[0] if pack else ""
        return (f"{name}_" if name else ""), name


def _check_header(
    path: Path, header: list[str], required: Sequence[str], indexed: Sequence[str]
) -> None:
    missing = [c for c in required if c not in header]
    for prefix in indexed:
        if not any(re.fullmatch(rf"{re.escape(prefix)}_\d+", h) for h in header):
            missing.append(f"{prefix}_0")
    if missing:
        raise InputError(
            f"{path}: missing column(s) {', '.join(missing)}; header is {','.join(header)}"
        )


def read_log(
    path: Path,
    required: Sequence[str] = (),
    *,
    indexed: Sequence[str] = (),
    allow_nan: bool = False,
) -> LogTable:
    """Read a CSV log, checking the header and that every cell a replay reads is a number.

    ``required`` columns must be present and are checked now; ``indexed`` prefixes (``v`` for
    ``v_0, v_1, ...``) must have at least one column. Other columns are parsed when read.
    ``t_s`` (if present) must be strictly increasing.
    """
    text = read_text(path, "log")
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputError(f"{path}: empty file, expected a header row") from None
        _check_header(path, header, required, indexed)
        if len(set(header)) != len(header):
            raise InputError(f"{path}: duplicate column names in header")
        rows: list[list[str]] = []
        lines: list[int] = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputError(
                    f"{path}: row {lineno} has {len(row)} cells, header has {len(header)}"
                )
            rows.append(row)
            lines.append(lineno)
    if not rows:
        raise InputError(f"{path}: no data rows")
    columns = _CsvColumns(path, header, rows, lines, allow_nan)
    eager = [*required, *(h for h in header for p in indexed if re.fullmatch(rf"{p}_\d+", h))]
    for name in eager:
        columns[name]
    if "t_s" in header:
        check_time(path, columns["t_s"], lines)
    return LogTable(path=path, columns=columns, n_rows=len(rows))


def check_time(path: Path, t: NDArray[np.float64], lines: Sequence[int] | None = None) -> None:
    """``t_s`` strictly increasing, or an error naming the first row where it is not."""
    bad = np.nonzero(np.diff(t) <= 0.0)[0]
    if bad.size:
        k = int(bad[0])
        row = lines[k + 1] if lines is not None else k + 3
        raise InputError(
            f"{path}: row {row}, column t_s: time must increase strictly ({t[k]:g} -> {t[k + 1]:g})"
        )


FLIGHT_LOG_SUFFIXES = (".ulg", ".bin", ".log", ".tlog")
"""Suffixes read as flight logs (PX4 ULog, ArduPilot DataFlash binary and text); any other
file is read as a CSV."""


def open_log(
    path: Path, options: LogOptions, required: Sequence[str] = (), indexed: Sequence[str] = ()
) -> LogTable:
    """A CSV log, or a flight log imported on the fly (what it lacks in ``notes``)."""
    if path.suffix.lower() in FLIGHT_LOG_SUFFIXES:
        from packpilot.io.flightlog import read_flight_log

        flight = read_flight_log(path)
        table = flight.table(cells=options.cells, assume_temp_c=options.assume_temp_c)
        return LogTable(
            path=path, columns=table.columns, n_rows=table.n_rows, source=flight.format,
            notes=tuple(table.notes), hints=table.hints, assumed=tuple(table.assumed),
            flight=flight,
        )  # fmt: skip
    return read_log(path, required, indexed=indexed)


def refuse_options(path: Path, options: LogOptions, method: str, *names: str) -> None:
    """An option the method cannot use is an error, not silently ignored."""
    for name in names:
        if getattr(options, name) is not None:
            flag = "--" + name.replace("_", "-")
            raise InputError(f"{path}: {flag} does not apply to a {method} replay")


def log_summary(log: LogTable, assumed: Sequence[str] = ()) -> dict[str, object]:
    """The summary's account of the log: where it came from, what it lacked and what was
    assumed in its place (at import and by the replay itself)."""
    return {
        "log": str(log.path),
        "source": log.source,
        "rows": len(log),
        "assumed": [*log.assumed, *assumed],
        "notes": list(log.notes),
    }


def row_durations(t_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Duration each row holds: until the next row; the last row repeats the previous step."""
    if t_s.size == 1:
        return np.ones(1)
    dt = np.diff(t_s)
    return np.append(dt, dt[-1])


MAX_LISTED = 5
"""Most entries of a list (joins, reverse-current events) the text summary shows."""


def _text(v: object) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, dict):
        return ", ".join(f"{k} {_text(x)}" for k, x in v.items()) or "none"
    if isinstance(v, list):
        shown = ", ".join(_text(x) if not isinstance(x, dict) else f"({_text(x)})"
                          for x in v[:MAX_LISTED])  # fmt: skip
        more = f" … ({len(v)} in all)" if len(v) > MAX_LISTED else ""
        return (shown + more) or "none"
    return "-" if v is None else str(v)


def summary_lines(summary: Mapping[str, object]) -> list[str]:
    """The summary as short ``key: value`` lines (headlines, assumptions and the log's notes
    as bullet lists at the end; the config left out);
    what ``packpilot replay`` prints without ``--json``."""
    bullets = ("headlines", "assumed", "notes")
    lines = [f"{k}: {_text(v)}" for k, v in summary.items() if k not in {"config", *bullets}]
    for key in bullets:
        items = summary.get(key)
        if isinstance(items, list) and items:
            lines.append(f"{key}:")
            lines += [f"  - {x}" for x in items]
    return lines
