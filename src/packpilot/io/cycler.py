"""Lab cycler exports: a cell's capacity test or pulse test as the cycler wrote it, read for
``packpilot fit`` (issue #27 §2: "and lab cycler exports — capacity tests and pulse tests").

One format is read, by this module, without a reader library (why none: ``docs/fit.md``,
"Lab cycler exports"): the **Maccor text export** (MIMS "Export to text"), tab-separated,
one title line (``Today's Date ... Date of Test: ... Filename: ... Procedure: ...``), one
line of column names, then one row per data point::

    Rec#  Cyc#  Step  Test (Sec)  Step (Sec)  Amp-hr  Watt-hr  Amps  Volts  State  ES  DPt Time ...

Older exports write the test time as ``TestTime`` = ``"0d 00:00:01.0000"``; both are read.
``State`` says what the channel did: ``C`` charge, ``D`` discharge, ``R`` rest, ``O`` other
(a procedure's own step); the sign of ``Amps`` is taken from it where it is C or D (exports
differ: some sign the current, some do not), else from ``Amps`` itself (a Maccor export signs
discharge negative). The result is in PackPilot's convention: current positive when
discharging. ``Amp-hr`` restarts every step, so it is not a charge counter: the fit integrates
the sampled current (a cycler samples densely). A temperature column (``Temp 1``, ``Temp``)
is carried when the export has one.

A file that is not such an export, or a row that does not parse (a torn last line, a field
that is not a number), is refused in one line naming the line.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import F64

TITLE = "Today's Date"
TIME_COLUMNS = ("Test (Sec)", "TestTime", "Test Time")
TEMP_COLUMNS = ("Temp 1", "Temp1", "Temp")
_DHMS = re.compile(r"^\s*(\d+)d\s+(\d+):(\d+):(\d+(?:\.\d*)?)\s*$")


@dataclass(frozen=True)
class CyclerSeries:
    """One cell's channel as the cycler logged it (SI units, current + = discharge)."""

    path: Path
    t_s: F64
    current_a: F64
    voltage_v: F64
    state: tuple[str, ...]
    temp_c: F64 | None
    procedure: str
    notes: tuple[str, ...]


def is_cycler_export(path: Path) -> bool:
    """Whether the file starts as a Maccor text export (its title line)."""
    try:
        with path.open("rb") as fh:
            head = fh.read(len(TITLE))
    except OSError:
        return False
    return head == TITLE.encode()


def _seconds(field: str) -> float:
    """A Maccor time: seconds (``769267.24``) or ``"0d 00:00:01.0000"``."""
    m = _DHMS.match(field)
    if m:
        d, h, mi, s = m.groups()
        return ((int(d) * 24 + int(h)) * 60 + int(mi)) * 60 + float(s)
    return float(field)


def _column(names: list[str], wanted: tuple[str, ...]) -> int | None:
    for w in wanted:
        if w in names:
            return names.index(w)
    return None


def _number(path: Path, line: int, name: str, field: str, *, time: bool = False) -> float:
    try:
        x = _seconds(field) if time else float(field)
    except ValueError:
        raise InputError(
            f"{path}: line {line}: malformed Maccor row: {name} is {field.strip()!r}, not a number"
        ) from None
    if not math.isfinite(x):
        raise InputError(f"{path}: line {line}: malformed Maccor row: {name} is {x}")
    return x


def _procedure(title: str) -> str:
    m = re.search(r"Procedure:\s*(.*?)\s*(?:\t|Comment/Barcode:|$)", title)
    return m.group(1) if m else ""


def read_maccor(path: Path) -> CyclerSeries:
    """The channel of a Maccor text export (see the module's docstring)."""
    if not path.is_file():
        raise InputError(f"{path}: cycler export not found")
    lines = path.read_text(encoding="latin-1").splitlines()
    if len(lines) < 3 or not lines[0].startswith(TITLE):
        raise InputError(
            f"{path}: not a Maccor text export (no \"{TITLE}\" title line and column names)"
        )
    names = [n.strip() for n in lines[1].split("\t")]
    cols = {k: _column(names, w) for k, w in (("t", TIME_COLUMNS), ("i", ("Amps",)),
                                              ("v", ("Volts",)), ("state", ("State",)),
                                              ("temp", TEMP_COLUMNS))}  # fmt: skip
    missing = [k for k, w in (("t", "Test (Sec) / TestTime"), ("i", "Amps"), ("v", "Volts"))
               if cols[k] is None]  # fmt: skip
    if missing:
        miss = ", ".join(w for k, w in (("t", "Test (Sec) / TestTime"), ("i", "Amps"),
                                        ("v", "Volts")) if k in missing)  # fmt: skip
        raise InputError(f"{path}: a Maccor export without the column(s) {miss}")
    rows = _rows(path, lines, names, cols)
    return _series(path, rows, cols["temp"] is not None, _procedure(lines[0]))


def _rows(path: Path, lines: list[str], names: list[str], cols: dict[str, int | None]
          ) -> list[tuple[float, float, float, str, float]]:  # fmt: skip
    need = len(names)
    out = []
    for n, line in enumerate(lines[2:], start=3):
        if not line.strip():
            continue
        f = line.split("\t")
        if len(f) < need:
            raise InputError(
                f"{path}: line {n}: malformed Maccor row: {len(f)} fields of the {need} columns "
                "(the export writes every column on every row): a torn or truncated line"
            )
        ct, ci, cv = cols["t"] or 0, cols["i"] or 0, cols["v"] or 0
        t = _number(path, n, names[ct], f[ct], time=True)
        amps = _number(path, n, "Amps", f[ci])
        volts = _number(path, n, "Volts", f[cv])
        state = f[cols["state"]].strip() if cols["state"] is not None else ""
        temp = _number(path, n, "Temp", f[cols["temp"]]) if cols["temp"] is not None else math.nan
        out.append((t, amps, volts, state, temp))
    if len(out) < 2:
        raise InputError(f"{path}: a Maccor export with {len(out)} data rows: nothing to fit")
    return out


def _series(path: Path, rows: list[tuple[float, float, float, str, float]], has_temp: bool,
            procedure: str) -> CyclerSeries:  # fmt: skip
    t = np.array([r[0] for r in rows])
    amps = np.array([r[1] for r in rows])
    states = tuple(r[3] for r in rows)
    sign = np.array([1.0 if s == "D" else -1.0 if s == "C" else 0.0 for s in states])
    # C/D: the state's sign on |Amps|; any other state: Amps as signed (discharge negative).
    cur = np.where(sign != 0.0, sign * np.abs(amps), -amps)
    notes = [f"{path.name}: Maccor text export, procedure {procedure or 'not named'}; "
             "current sign from State (C/D), charge from the sampled current (Amp-hr restarts "
             "every step)"]  # fmt: skip
    keep = np.append(np.diff(t) > 0.0, True)
    if not keep.all():
        notes.append(
            f"{path.name}: {int((~keep).sum())} rows with the next row's time dropped (the "
            "cycler logs a step's end and the next step's start at one time)"
        )
    if np.any(np.diff(t[keep]) < 0.0):
        k = int(np.flatnonzero(np.diff(t[keep]) < 0.0)[0])
        raise InputError(f"{path}: data row {k + 2}: the test time goes backwards")
    temp = np.array([r[4] for r in rows])[keep] if has_temp else None
    return CyclerSeries(
        path=path, t_s=t[keep] - t[0], current_a=cur[keep],
        voltage_v=np.array([r[2] for r in rows])[keep],
        state=tuple(s for s, k in zip(states, keep, strict=True) if k), temp_c=temp,
        procedure=procedure, notes=tuple(notes),
    )  # fmt: skip


__all__ = ["CyclerSeries", "is_cycler_export", "read_maccor"]
