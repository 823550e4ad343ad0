"""Load profiles: what the vehicle or site asks of the bus over time.

A profile is a zero-order hold: each row holds its value from its ``t_s`` until the next row.
Values are in one kind of demand: current (A), power (W) or resistance (Ohm). Built-in profiles
are generated from a seeded recipe so runs are reproducible without data files.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.config.base import MAX_CURRENT_A, MAX_TIME_S
from packpilot.config.scenario import LOAD_R_OHM, MAX_POWER_W
from packpilot.errors import InputError, read_text

Array = NDArray[np.float64]
KINDS = ("current", "power", "resistance", "none")


@dataclass(frozen=True)
class LoadProfile:
    kind: str
    t_s: Array
    value: Array
    repeat: bool = False

    def at(self, t_s: float) -> float:
        """Demand at time ``t_s`` (zero-order hold; 0 after the end unless ``repeat``)."""
        if self.kind == "none" or self.t_s.size == 0:
            return 0.0
        t = t_s
        end = float(self.t_s[-1])
        if self.repeat and end > 0.0:
            t = math.fmod(t_s, end)
        elif t_s >= end and self.t_s.size > 1:
            return 0.0
        i = int(np.searchsorted(self.t_s, t, side="right")) - 1
        return float(self.value[max(i, 0)])


def constant(kind: str, value: float) -> LoadProfile:
    return LoadProfile(kind=kind, t_s=np.array([0.0]), value=np.array([value]))


def builtin(name: str, base: float, kind: str) -> LoadProfile:
    """Built-in profiles, scaled by ``base`` (the hover value).

    ``uav_flight``: a 20-minute multirotor mission: spool-up, take-off burst (2.2x), climb
    (1.5x), hover with gust corrections, two fast manoeuvres (2.5x bursts of 4 s), cruise
    (1.2x), descent (0.8x), landing flare, motors off. ``uav_hover``: steady hover with small
    gust pulses. ``step``: 1x then 2x bursts every 60 s (a simple stress profile).
    """
    rows: list[tuple[float, float]]
    if name == "uav_flight":
        rows = [(0, 0.1), (5, 2.2), (15, 1.5), (45, 1.0)]
        t = 45.0
        rng = np.random.default_rng(7)
        while t < 1080:
            rows.append((t, 1.0 + 0.08 * float(rng.standard_normal())))
            t += 5.0
            if abs(t - 300) < 2.5 or abs(t - 700) < 2.5:
                rows.append((t, 2.5))
                t += 4.0
        rows += [(1080, 1.2), (1140, 0.8), (1180, 1.3), (1190, 0.05), (1200, 0.0)]
    elif name == "uav_hover":
        rows = [(0.0, 1.0)]
        rng = np.random.default_rng(11)
        for k in range(1, 720):
            rows.append((k * 5.0, 1.0 + 0.05 * float(rng.standard_normal())))
        rows.append((3600.0, 0.0))
    elif name == "step":
        rows = []
        for k in range(60):
            rows += [(k * 60.0, 1.0), (k * 60.0 + 50.0, 2.0)]
        rows.append((3600.0, 0.0))
    else:
        raise InputError(
            f"unknown built-in load profile {name!r}; known: uav_flight, uav_hover, step"
        )
    arr = np.array(rows, dtype=np.float64)
    return LoadProfile(kind=kind, t_s=arr[:, 0], value=arr[:, 1] * base)


_COLUMN_KIND = {"current_a": "current", "power_w": "power", "resistance_ohm": "resistance"}


_BOUNDS: dict[str, tuple[float, float]] = {
    "t_s": (-MAX_TIME_S, MAX_TIME_S),
    "current_a": (-MAX_CURRENT_A, MAX_CURRENT_A),
    "power_w": (-MAX_POWER_W, MAX_POWER_W),
    "resistance_ohm": LOAD_R_OHM,
}
"""What a profile cell may hold: the bounds ``[load]`` puts on its value, so a profile cannot
ask for the 1e24 A that the config refuses."""


def _check_cell(path: Path, lineno: int, col: str, cell: str) -> None:
    """A load-profile cell must be a finite number within its column's bounds (the error
    names its row and column)."""
    if cell == "":
        raise InputError(f"{path}: row {lineno}, column {col}: empty cell (gap)")
    try:
        x = float(cell)
    except ValueError:
        raise InputError(f"{path}: row {lineno}, column {col}: {cell!r} is not a number") from None
    if not math.isfinite(x):
        raise InputError(f"{path}: row {lineno}, column {col}: {cell!r} is not finite")
    lo, hi = _BOUNDS[col]
    if not lo <= x <= hi:
        raise InputError(f"{path}: row {lineno}, column {col}: {x:g} is outside {lo:g}..{hi:g}")


def from_csv(path: Path, scale: float = 1.0, repeat: bool = False) -> LoadProfile:
    """Read ``t_s`` plus one of ``current_a``, ``power_w``, ``resistance_ohm``.

    Every cell must be a finite number and time must increase strictly; the error names the
    row (1-based, header = row 1) and column.
    """
    text = read_text(path, "load profile")
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise InputError(f"{path}: empty load profile") from None
        value_cols = [c for c in header if c in _COLUMN_KIND]
        if "t_s" not in header or len(value_cols) != 1:
            raise InputError(
                f"{path}: header must be t_s plus exactly one of "
                f"{', '.join(_COLUMN_KIND)}; got {','.join(header)}"
            )
        it, iv = header.index("t_s"), header.index(value_cols[0])
        ts: list[float] = []
        vs: list[float] = []
        for lineno, row in enumerate(reader, start=2):
            if not row or all(not c.strip() for c in row):
                continue
            if len(row) > len(header):
                raise InputError(
                    f"{path}: row {lineno} has {len(row)} cells, header has {len(header)}"
                )
            for col, j in (("t_s", it), (value_cols[0], iv)):
                _check_cell(path, lineno, col, row[j].strip() if j < len(row) else "")
            t, v = float(row[it]), float(row[iv])
            if ts and t <= ts[-1]:
                raise InputError(
                    f"{path}: row {lineno}, column t_s: time {t:g} does not increase "
                    f"(previous {ts[-1]:g})"
                )
            ts.append(t)
            vs.append(v * scale)
    if not ts:
        raise InputError(f"{path}: load profile has no data rows")
    return LoadProfile(
        kind=_COLUMN_KIND[value_cols[0]], t_s=np.array(ts), value=np.array(vs), repeat=repeat
    )
