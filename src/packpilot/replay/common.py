"""Shared plumbing for replaying logged measurements through a controller.

A replay reads a CSV log whose every cell must be a finite number, runs a pure controller
over it and returns a table; the CLI writes the table and prints the summary. Validation is
strict and names the row and column at fault, because a silently skipped row would change
the accumulated timers the methods depend on.
"""

from __future__ import annotations

import csv
import io
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.config.base import MAX_TIME_S
from packpilot.errors import InputError, read_text

MAX_LOG_ABS = MAX_TIME_S
"""Largest magnitude any logged number may have (1e9: seconds, volts, amperes, degC alike).
A time of 1e306 s overflowed when a method turned it into milliseconds, and a 1e308 time gap
made an equalization replay apply its formulas gap / T1 times: nothing a logger writes is
that large, so such a cell is refused with its row and column."""

CellValue = float | int | str | bool | None


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
class LogTable:
    """A validated numeric CSV log: column name -> float array, plus the source path."""

    path: Path
    columns: dict[str, NDArray[np.float64]]

    def __len__(self) -> int:
        return len(next(iter(self.columns.values()))) if self.columns else 0

    def indexed(self, prefix: str) -> list[str]:
        """Column names ``prefix_0 .. prefix_{k-1}`` present in the log, in index order."""
        pat = re.compile(rf"^{re.escape(prefix)}_(\d+)$")
        found = sorted(
            (int(m.group(1)), name) for name in self.columns if (m := pat.match(name)) is not None
        )
        names = [name for _, name in found]
        for k, (idx, name) in enumerate(found):
            if idx != k:
                raise InputError(
                    f"{self.path}: column {prefix}_{k} is missing (found {name} instead)"
                )
        return names


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
    if len(set(header)) != len(header):
        raise InputError(f"{path}: duplicate column names in header")


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


def read_log(
    path: Path,
    required: Sequence[str],
    *,
    indexed: Sequence[str] = (),
    allow_nan: bool = False,
) -> LogTable:
    """Read a CSV log, checking the header and that every cell is a number.

    ``required`` columns must be present; ``indexed`` prefixes (``v`` for ``v_0, v_1, ...``)
    must have at least one column. ``t_s`` (if required) must be strictly increasing.
    """
    text = read_text(path, "log")
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputError(f"{path}: empty file, expected a header row") from None
        _check_header(path, header, required, indexed)
        data: list[list[float]] = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) != len(header):
                raise InputError(
                    f"{path}: row {lineno} has {len(row)} cells, header has {len(header)}"
                )
            data.append(
                [
                    _number(path, lineno, name, cell, allow_nan)
                    for name, cell in zip(header, row, strict=True)
                ]
            )
    if not data:
        raise InputError(f"{path}: no data rows")
    arr = np.asarray(data, dtype=np.float64)
    columns = {name: arr[:, j].copy() for j, name in enumerate(header)}
    if "t_s" in columns:
        t = columns["t_s"]
        bad = np.nonzero(np.diff(t) <= 0.0)[0]
        if bad.size:
            raise InputError(
                f"{path}: row {int(bad[0]) + 3}, column t_s: time must increase strictly "
                f"({t[bad[0]]:g} -> {t[bad[0] + 1]:g})"
            )
    return LogTable(path=path, columns=columns)


def row_durations(t_s: NDArray[np.float64]) -> NDArray[np.float64]:
    """Duration each row holds: until the next row; the last row repeats the previous step."""
    if t_s.size == 1:
        return np.ones(1)
    dt = np.diff(t_s)
    return np.append(dt, dt[-1])
