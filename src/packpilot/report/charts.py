"""Interactive charts of the report: the data, packed small, and what each chart draws.

The page carries the run's series at full resolution, so zooming into 50 s of a 90-minute flight
shows every 0.2 s sample. Each series is quantized (four to five significant digits, see
:func:`quantum`), delta-encoded as little-endian int32, deflated and base64'd; the browser inflates
it with ``DecompressionStream`` (no library, no network). Smooth battery signals pack to a few
kB each, a step channel to almost nothing. A run longer than :data:`FULL_RES_MAX` samples is
thinned first by :mod:`packpilot.report.downsample` (min/max buckets of the battery channels plus
every switch change), so a 10-hour run still makes a small page.

Python decides *what* each chart shows (:class:`Chart`); ``static/report.js`` draws it with the
bundled uPlot (zoom by drag or wheel, hover values, charts of one group move together).
"""

from __future__ import annotations

import base64
import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.record import Result
from packpilot.report.downsample import change_indices, minmax_indices

F64 = NDArray[np.float64]
FULL_RES_MAX = 120_000
"""Samples kept at full resolution; longer runs are thinned to about this many."""
_NAN = np.iinfo(np.int32).min


def quantum(y: F64) -> float:
    """The resolution a series is stored at: a power of ten about 1e-4 of its largest value
    (four significant digits at the top of its range, finer below)."""
    finite = np.abs(y[np.isfinite(y)])
    top = float(finite.max()) if finite.size else 0.0
    if top < 1e-5:  # zero, or denormal dust: nothing finer than 1e-9 is worth carrying
        return 1.0 if top == 0.0 else 1e-9
    return float(10.0 ** math.floor(math.log10(top * 1e-4)))


def pack(y: F64, q: float | None = None) -> dict[str, Any]:
    """One series for the page: ``{"q": quantum, "n": length, "z": base64(deflate(int32 deltas))}``
    with ``"nan"``: [start, end) runs of missing samples (drawn as gaps)."""
    y = np.asarray(y, dtype=np.float64)
    q = quantum(y) if q is None else q
    nan = ~np.isfinite(y)
    ints = np.round(np.where(nan, 0.0, y) / q)
    ints = np.clip(ints, -(2**31) + 1, 2**31 - 1).astype(np.int64)
    if nan.any():  # a gap repeats the previous value, so the deltas stay small
        idx = np.where(~nan, np.arange(len(y)), 0)
        np.maximum.accumulate(idx, out=idx)
        ints = ints[idx]
    deltas = np.diff(ints, prepend=0).astype("<i4")
    out: dict[str, Any] = {
        "q": q,
        "n": len(y),
        "z": base64.b64encode(zlib.compress(deltas.tobytes(), 9)).decode("ascii"),
    }
    if nan.any():
        d = np.diff(np.concatenate([[0], nan.astype(np.int8), [0]]))
        out["nan"] = np.stack([np.flatnonzero(d == 1), np.flatnonzero(d == -1)], 1).tolist()
    return out


def sample_indices(result: Result) -> NDArray[np.intp]:
    """The samples the page carries: all of them, or for a long run the min/max buckets of the
    battery channels and every switch change (see the module docstring)."""
    tr = result.trace
    n = len(tr.t_s)
    if n <= FULL_RES_MAX:
        return np.arange(n, dtype=np.intp)
    keys = ("voltage_v", "current_a", "min_cell_v", "max_cell_v", "soc", "temp_c")
    n_b = len(result.battery_names)
    budget = max(1000, FULL_RES_MAX // (len(keys) * max(n_b, 1)))
    parts = [minmax_indices(tr.channel(k)[:, b], budget) for k in keys for b in range(n_b)]
    parts += [change_indices(tr.channel(k)[:, b]) for k in ("chg_on", "dsg_on") for b in range(n_b)]
    parts.append(minmax_indices(tr.load_a, budget))
    idx = np.unique(np.concatenate(parts))
    return idx.astype(np.intp)


class Store:
    """The packed series of one page, each stored once however many charts draw it."""

    def __init__(self, idx: NDArray[np.intp]) -> None:
        self.idx = idx
        self.data: dict[str, dict[str, Any]] = {}

    def add(self, key: str, full: F64, q: float | None = None) -> str:
        """Store a full-length series (sampled at the page's samples) under ``key``."""
        if key not in self.data:
            self.data[key] = pack(np.asarray(full, dtype=np.float64)[self.idx], q)
        return key

    def add_raw(self, key: str, values: F64, q: float | None = None) -> str:
        """Store a series as is (one on its own time axis, e.g. CAN frame rates)."""
        self.data[key] = pack(np.asarray(values, dtype=np.float64), q)
        return key


@dataclass
class Series:
    """One line of a chart."""

    key: str
    """The store key of its data."""
    label: str
    color: str
    dash: bool = False
    step: bool = False
    width: float = 1.4
    offset: float = 0.0
    """Added to the values when drawn (keeps equal lines of several batteries apart)."""
    scale: float = 1.0
    """Multiplied into the values when drawn (a fraction shown in %)."""
    states: Sequence[str] | None = None
    """Names of the stored values 0, 1, … shown on hover (a switch: off, on)."""

    def spec(self) -> dict[str, Any]:
        out: dict[str, Any] = {"key": self.key, "label": self.label, "color": self.color}
        if self.states is not None:
            out["states"] = list(self.states)
        for name, default in (("dash", False), ("step", False), ("width", 1.4), ("offset", 0.0),
                              ("scale", 1.0)):  # fmt: skip
            value = getattr(self, name)
            if value != default:
                out[name] = value
        return out


@dataclass
class Chart:
    """One interactive chart: a title, a y unit or category names, its lines, shaded spans."""

    id: str
    title: str
    unit: str = ""
    series: list[Series] = field(default_factory=list)
    height: int = 170
    group: str = "run"
    """Charts of one group share the cursor and the zoom."""
    categories: Sequence[str] | None = None
    """y tick names of a state chart (value k is ``categories[k]``)."""
    bands: list[tuple[float, float, str]] = field(default_factory=list)
    """Shaded time spans (t0, t1, colour), e.g. a trip or a body diode conducting."""
    marks: list[tuple[float, str, str]] = field(default_factory=list)
    """Vertical lines (t, colour, label), e.g. the alarms' first times."""
    y_range: tuple[float, float] | None = None
    x_key: str | None = None
    """Store key of the chart's own time axis; None: the run's samples."""

    def spec(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "id": self.id,
            "title": self.title,
            "unit": self.unit,
            "height": self.height,
            "group": self.group,
            "series": [s.spec() for s in self.series],
        }
        if self.categories is not None:
            out["categories"] = list(self.categories)
        if self.bands:
            out["bands"] = [[round(a, 3), round(b, 3), c] for a, b, c in self.bands]
        if self.marks:
            out["marks"] = [[round(t, 3), c, lab] for t, c, lab in self.marks]
        if self.y_range is not None:
            out["yRange"] = list(self.y_range)
        if self.x_key is not None:
            out["x"] = self.x_key
        return out


def spans(t: F64, on: NDArray[np.bool_], min_frac: float = 1 / 800) -> list[tuple[float, float]]:
    """Time spans (t0, t1) where ``on`` holds, each at least ``min_frac`` of the run wide (a
    one-sample trip still shows), touching spans merged, at most 2000."""
    if len(t) == 0 or not on.any():
        return []
    d = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)
    t_end = np.append(t[1:], t[-1])
    width = (float(t[-1]) - float(t[0])) * min_frac
    out: list[tuple[float, float]] = []
    for s, e in zip(t[starts], t_end[ends - 1], strict=True):
        a, b = float(s), max(float(e), float(s) + width)
        if out and a <= out[-1][1]:
            out[-1] = (out[-1][0], max(out[-1][1], b))
        else:
            out.append((a, b))
    if len(out) > 2000:
        gap = (float(t[-1]) - float(t[0])) / 2000
        merged = [out[0]]
        for a, b in out[1:]:
            if a - merged[-1][1] <= gap:
                merged[-1] = (merged[-1][0], b)
            else:
                merged.append((a, b))
        out = merged
    return out


__all__ = ["FULL_RES_MAX", "Chart", "Series", "Store", "pack", "quantum", "sample_indices", "spans"]
