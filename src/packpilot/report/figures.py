"""Figures of the HTML run report: events, batteries, switches, protection, controller status.

Every figure plots downsampled series (:mod:`packpilot.report.downsample`), so a 10-hour run
renders in seconds and its PNGs stay small. Like ``plots.py`` this uses ``Figure`` with an Agg
canvas, never ``pyplot``. All figures of one report share one time axis (:class:`TimeAxis`) so
panels line up when read one under the other. Battery ``b`` is colour ``C{b}`` everywhere.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import NDArray

from packpilot.contract.bms import StatusValue
from packpilot.contract.record import Result
from packpilot.report.downsample import MAX_POINTS, downsample, step_indices

WIDTH_IN = 10.0
MAX_CATEGORIES = 14
"""A label channel with more distinct values shows the most frequent ones and 'other'."""
MAX_PANELS_PER_FIGURE = 10

ChannelKind = Literal["numeric", "bool", "label"]


ALARM_COLOR = "tab:red"
"""Trips and alarms; no battery is drawn in it (``C3`` is this red, so it is skipped)."""
BATTERY_COLORS: tuple[str, ...] = ("C0", "C1", "C2", "C4", "C5", "C6", "C7", "C8", "C9")


def battery_color(b: int) -> str:
    """Battery ``b``'s colour, the same in every figure, never the alarm colour."""
    return BATTERY_COLORS[b % len(BATTERY_COLORS)]


# --------------------------------------------------------------------------- time axis


@dataclass(frozen=True)
class TimeAxis:
    """Seconds per plotted unit, the axis label and the run's span (in plotted units)."""

    scale: float
    label: str
    lo: float
    hi: float

    @classmethod
    def of(cls, t_s: NDArray[np.float64]) -> TimeAxis:
        finite = t_s[np.isfinite(t_s)] if t_s.size else t_s
        if finite.size == 0:
            return cls(1.0, "time (s)", 0.0, 1.0)
        lo, hi = float(finite.min()), float(finite.max())
        span = hi - lo
        scale, label = 1.0, "time (s)"
        if span > 3 * 3600:
            scale, label = 3600.0, "time (h)"
        elif span > 300:
            scale, label = 60.0, "time (min)"
        if hi <= lo:
            hi = lo + scale
        return cls(scale, label, lo / scale, hi / scale)

    def apply(self, ax: Axes, *, label: bool = True) -> None:
        ax.set_xlim(self.lo, self.hi)
        ax.grid(True, lw=0.4, alpha=0.5)
        if label:
            ax.set_xlabel(self.label)


LEFT, RIGHT = 0.16, 0.92
"""Fixed side margins (figure fractions) for every report figure, so that time axes of
figures shown one under another line up (constrained layout would shift each one)."""


def _new_figure(
    heights_in: Sequence[float],
    *,
    top_in: float = 0.35,
    bottom_in: float = 0.55,
    gap_in: float = 0.3,
    sharex: bool = True,
) -> tuple[Figure, list[Axes]]:
    """A figure with one axes per entry of ``heights_in`` (inches), stacked, shared time axis."""
    n = len(heights_in)
    height = top_in + bottom_in + sum(heights_in) + gap_in * (n - 1)
    fig = Figure(figsize=(WIDTH_IN, height))
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(
        n,
        1,
        height_ratios=list(heights_in),
        left=LEFT,
        right=RIGHT,
        top=1.0 - top_in / height,
        bottom=bottom_in / height,
        hspace=gap_in / (sum(heights_in) / n),
    )
    axes: list[Axes] = []
    for k in range(n):
        axes.append(fig.add_subplot(gs[k, 0], sharex=axes[0] if sharex and axes else None))
    for ax in axes[:-1]:
        ax.tick_params(labelbottom=False)
    return fig, axes


def _no_data(ax: Axes, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")
    ax.set_yticks([])


# --------------------------------------------------------------------------- status channels


@dataclass(frozen=True)
class StatusChannel:
    """One controller status channel, compressed to the steps where its tuple changed.

    ``rows[j]`` is the step index (into the trace) from which ``values[j, :]`` holds, up to
    the next row; ``values`` has one column per battery (None where a battery has no value).
    """

    name: str
    kind: ChannelKind
    rows: NDArray[np.intp]
    values: NDArray[Any]
    columns: tuple[int, ...]
    """Batteries that carry a value at least once (the aux battery usually does not)."""
    pack_level: bool
    """Every battery carries the same value at every step (a pack-wide quantity)."""

    def column(self, b: int) -> NDArray[Any]:
        return self.values[:, b]

    def numeric(self, b: int) -> NDArray[np.float64]:
        """Column ``b`` as floats, None as NaN, booleans as 0/1."""
        col = self.values[:, b]
        return np.array([math.nan if v is None else float(v) for v in col], dtype=np.float64)


def _compress(seqs: Sequence[Sequence[StatusValue]]) -> tuple[list[int], list[tuple[Any, ...]]]:
    """Indices where the per-step tuple differs from the previous one (Python-level, cheap)."""
    rows: list[int] = []
    vals: list[tuple[Any, ...]] = []
    prev: Any = object()
    for i, s in enumerate(seqs):
        if s is prev:  # a loaded run repeats the very same tuple object between changes
            continue
        prev = s
        t = tuple(s)
        if vals and t == vals[-1]:
            continue
        rows.append(i)
        vals.append(t)
    return rows, vals


def _kind_of(values: NDArray[Any]) -> ChannelKind:
    seen = {type(v) for v in values.ravel() if v is not None}
    if not seen:
        return "numeric"
    if any(issubclass(t, str) for t in seen):
        return "label"
    if all(issubclass(t, bool | np.bool_) for t in seen):
        return "bool"
    return "numeric"


def status_channels(result: Result) -> dict[str, StatusChannel]:
    """Every status channel of a run, aligned to the trace's steps and compressed.

    A channel shorter than the run is taken to cover the run's end (how telemetry stores it:
    a channel starts at the first step that carried it); its earlier steps have no value.
    """
    n_s = len(result.trace.t_s)
    n_b = len(result.battery_names)
    out: dict[str, StatusChannel] = {}
    for name, seqs in result.trace.status.items():
        if not seqs or n_s == 0:
            continue
        if len(seqs) > n_s:
            seqs = seqs[len(seqs) - n_s :]
        offset = n_s - len(seqs)
        rows_l, vals_l = _compress(seqs)
        width = max(n_b, max(len(v) for v in vals_l))
        values = np.full((len(vals_l), width), None, dtype=object)
        for j, v in enumerate(vals_l):
            values[j, : len(v)] = v
        rows = np.asarray(rows_l, dtype=np.intp) + offset
        if offset > 0:
            rows = np.concatenate([[0], rows]).astype(np.intp)
            values = np.concatenate([np.full((1, width), None, dtype=object), values])
        columns = tuple(
            b
            for b in range(min(width, n_b))
            if any(v is not None and not (isinstance(v, float) and v != v) for v in values[:, b])
        )
        pack_level = len(columns) > 1 and all(
            bool(np.all(values[:, b] == values[:, columns[0]])) for b in columns[1:]
        )
        out[name] = StatusChannel(
            name, _kind_of(values[:, list(columns)]), rows, values, columns, pack_level
        )
    return out


def _step_xy(
    ch: StatusChannel, col: NDArray[np.float64], t: NDArray[np.float64], axis: TimeAxis
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Step points of one column, extended to the last sample and thinned if needed."""
    x = np.append(t[ch.rows], t[-1]) / axis.scale
    y = np.append(col, col[-1])
    idx = step_indices(y, MAX_POINTS)
    return x[idx], y[idx]


def _categories(ch: StatusChannel) -> list[str]:
    """Labels by first appearance, most frequent kept when there are too many."""
    seen: Counter[str] = Counter()
    order: list[str] = []
    for b in ch.columns:
        for v in ch.values[:, b]:
            if v is None:
                continue
            s = str(v)
            if s not in seen:
                order.append(s)
            seen[s] += 1
    if len(order) <= MAX_CATEGORIES:
        return order
    keep = {s for s, _ in seen.most_common(MAX_CATEGORIES - 1)}
    return [s for s in order if s in keep] + ["other"]


def _natural_key(text: str) -> list[Any]:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text)]


def _label_codes(ch: StatusChannel, b: int, cats: list[str]) -> NDArray[np.float64]:
    index = {c: i for i, c in enumerate(cats)}
    other = index.get("other", math.nan)
    return np.array(
        [math.nan if v is None else index.get(str(v), other) for v in ch.values[:, b]],
        dtype=np.float64,
    )


def _short(text: str, n: int = 22) -> str:
    return text if len(text) <= n else text[: n - 1] + "…"


def _lanes(ch: StatusChannel) -> list[tuple[int, str]]:
    """(column, legend label) pairs: one 'pack' lane for a pack-wide channel."""
    if ch.pack_level:
        return [(ch.columns[0], "pack")]
    return [(b, "") for b in ch.columns]


def plot_status(
    ax: Axes,
    ch: StatusChannel,
    t: NDArray[np.float64],
    axis: TimeAxis,
    names: Sequence[str],
    *,
    title: str | None = None,
) -> None:
    """One status channel on one axes: lines per battery, or one black line if pack-wide."""
    lanes = _lanes(ch)
    if not lanes:
        _no_data(ax, f"{ch.name}: no values")
        return
    n = len(lanes)
    spread = 0.12 if n > 1 else 0.0  # small offsets keep equal battery lines visible
    if ch.kind == "label":
        cats = _categories(ch)
        for k, (b, label) in enumerate(lanes):
            x, y = _step_xy(ch, _label_codes(ch, b, cats), t, axis)
            off = (k - (n - 1) / 2) * spread / max(n - 1, 1) * 2 if n > 1 else 0.0
            color = "k" if label == "pack" else battery_color(b)
            ax.plot(
                x, y + off, drawstyle="steps-post", lw=1.3, color=color, label=label or names[b]
            )
        ax.set_yticks(range(len(cats)), [_short(c) for c in cats], fontsize=7)
        ax.set_ylim(-0.6, len(cats) - 0.4)
    elif ch.kind == "bool":
        for k, (b, label) in enumerate(lanes):
            x, y = _step_xy(ch, ch.numeric(b), t, axis)
            off = (k - (n - 1) / 2) * spread / max(n - 1, 1) * 2 if n > 1 else 0.0
            color = "k" if label == "pack" else battery_color(b)
            ax.plot(
                x, y + off, drawstyle="steps-post", lw=1.3, color=color, label=label or names[b]
            )
        ax.set_yticks([0, 1], ["false", "true"], fontsize=7)
        ax.set_ylim(-0.4, 1.4)
    else:
        for b, label in lanes:
            x, y = _step_xy(ch, ch.numeric(b), t, axis)
            color = "k" if label == "pack" else battery_color(b)
            ax.plot(x, y, drawstyle="steps-post", lw=1.1, color=color, label=label or names[b])
        ax.tick_params(axis="y", labelsize=7)
    ax.set_ylabel(channel_label(ch.name), fontsize=8)
    if title:
        ax.set_title(title, fontsize=9, loc="left")
    if n > 1 or lanes[0][1] == "pack":
        ax.legend(loc="upper left", fontsize=7, ncol=min(n, 8), framealpha=0.7)
    axis.apply(ax, label=False)


_UNITS = (
    ("_mv", "mV"),
    ("_v", "V"),
    ("_a", "A"),
    ("_ah", "Ah"),
    ("_wh", "Wh"),
    ("_w", "W"),
    ("_j", "J"),
    ("_s", "s"),
    ("_c", "°C"),
    ("_ohm", "Ω"),
)


def unit_of(name: str) -> str:
    """The SI unit a name's suffix announces ('' when it has none)."""
    base = re.sub(r"_g\d+$", "", name)
    for suffix, unit in _UNITS:
        if base.endswith(suffix):
            return unit
    return ""


def channel_label(name: str) -> str:
    unit = unit_of(name)
    return f"{name}\n({unit})" if unit else name


# --------------------------------------------------------------------------- figures


def events_figure(
    result: Result,
    axis: TimeAxis,
    names: Sequence[str],
    colors: Sequence[int] | None = None,
) -> Figure | None:
    """Events over time, one row per kind, coloured by battery (black: pack-wide).

    ``names[b]`` names ``Event.battery == b``; ``colors[b]`` is that battery's index in the
    trace, so its colour matches the other figures when an aux battery shifts the numbering.
    """
    events = [e for e in result.events if np.isfinite(e.t_s)]
    if not events:
        return None
    counts = Counter(e.kind for e in events)
    kinds = list(counts)  # order of first occurrence
    row = {k: i for i, k in enumerate(kinds)}
    fig, (ax,) = _new_figure([0.5 + 0.3 * len(kinds)], top_in=0.6)
    span = max(axis.hi - axis.lo, 1e-9)
    groups: dict[int | None, list[tuple[float, int]]] = {}
    for e in events:
        groups.setdefault(e.battery, []).append((e.t_s / axis.scale, row[e.kind]))
    handles: list[Line2D] = []
    ordered = sorted(groups.items(), key=lambda kv: -1 if kv[0] is None else kv[0])
    for j, (b, pts) in enumerate(ordered):
        arr = np.array(pts, dtype=np.float64)
        # Thousands of events cannot be told apart on 1,000 pixels: one marker per pixel-ish bin.
        key = np.round((arr[:, 0] - axis.lo) / span * 2000.0) * 1000 + arr[:, 1]
        _, first = np.unique(key, return_index=True)
        arr = arr[np.sort(first)]
        # Each battery a little above or below the row, so simultaneous events stay distinct.
        if len(ordered) > 1:
            arr[:, 1] += 0.6 * (j / (len(ordered) - 1) - 0.5)
        if b is None:
            color, label = "k", "pack"
        elif 0 <= b < len(names):
            color = battery_color(colors[b] if colors is not None and b < len(colors) else b)
            label = names[b]
        else:
            color, label = "0.5", f"battery {b}"
        ax.plot(
            arr[:, 0],
            arr[:, 1],
            ls="none",
            marker="|",
            ms=12 if len(ordered) == 1 else 7,
            mew=2.0,
            color=color,
            alpha=0.85,
            clip_on=False,  # an event at t = 0 sits on the frame; show all of it
        )
        handles.append(
            Line2D([], [], ls="none", marker="|", ms=9, mew=2.0, color=color, label=label)
        )
    ax.set_yticks(range(len(kinds)), [_short(f"{k} ({counts[k]})", 26) for k in kinds], fontsize=8)
    ax.set_ylim(len(kinds) - 0.5, -0.5)
    axis.apply(ax)
    ax.set_title("events by kind (count); colour = battery", fontsize=9, loc="left")
    ax.legend(
        handles=handles,
        loc="lower right",
        bbox_to_anchor=(1.0, 1.0),
        fontsize=8,
        ncol=min(len(handles), 8),
        frameon=False,
        borderaxespad=0.2,
    )
    return fig


def hold_runs(
    x: NDArray[np.float64], on: NDArray[np.bool_], max_runs: int = 2000, min_width: float = 0.0
) -> list[tuple[float, float]]:
    """(start, width) of the intervals where a sample-and-hold flag is on.

    Sample ``i`` holds from ``x[i]`` to ``x[i+1]``. Runs separated by less than 1/4000 of the
    span are merged when there are more than ``max_runs`` (a flickering flag would otherwise
    draw thousands of slivers no one can see). Runs are at least ``min_width`` wide, so a
    one-sample diode conduction or trip still shows on a long time axis.
    """
    if len(x) == 0 or not on.any():
        return []
    d = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    starts = np.flatnonzero(d == 1)
    ends = np.flatnonzero(d == -1)  # exclusive sample index
    x_end = np.append(x[1:], x[-1])
    s_x = x[starts]
    e_x = x_end[ends - 1]
    if min_width > 0.0:
        e_x = np.maximum(e_x, s_x + min_width)
    if len(s_x) > max_runs:
        gap = (float(x[-1]) - float(x[0])) / 4000.0
        keep = np.concatenate([[True], s_x[1:] - e_x[:-1] > gap])
        s_x = s_x[keep]
        e_x = np.maximum.reduceat(e_x, np.flatnonzero(keep))
    return [(float(a), float(b - a)) for a, b in zip(s_x, e_x, strict=True)]


def _pack_currents(result: Result, ax_i: Axes, line: Callable[..., None]) -> None:
    """The load, its demand where it differs, and the charger, on the current panel."""
    tr = result.trace
    if np.isfinite(tr.load_a).any() and np.nanmax(np.abs(tr.load_a)) > 0:
        line(ax_i, tr.load_a, color="0.15", lw=0.9, ls="-.", label="load")
    if not np.allclose(tr.load_demand_a, tr.load_a, rtol=1e-6, atol=1e-6, equal_nan=True):
        line(ax_i, tr.load_demand_a, color="0.5", lw=0.8, ls=":", label="load demand")
    if np.isfinite(tr.charger_a).any() and np.nanmax(np.abs(tr.charger_a)) > 0:
        line(ax_i, tr.charger_a, color="tab:olive", lw=0.9, ls=(0, (5, 2)), label="charger")


def _unique_handles(axes: Sequence[Axes]) -> list[Any]:
    """The legend handles of ``axes``, the first of each label, in order."""
    handles: list[Any] = []
    seen: set[str] = set()
    for ax in axes:
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            if lab not in seen:
                seen.add(lab)
                handles.append(h)
    return handles


def batteries_figure(result: Result, axis: TimeAxis, apart: Sequence[int] = ()) -> Figure:
    """Voltage, current, SOC, temperature and cell-voltage range of every battery.

    Batteries in ``apart`` (an auxiliary 12 V battery next to 100 V traction batteries) get
    their own voltage panel, or the traction voltages would be squashed into a flat line.
    """
    tr = result.trace
    names = result.battery_names
    apart = [b for b in apart if 0 <= b < len(names)]
    main = [b for b in range(len(names)) if b not in apart]
    heights = [2.0] + ([1.2] if apart else []) + [2.0, 1.6, 1.6, 1.6]
    fig, axes = _new_figure(heights, top_in=0.55)
    ax_v = axes[0]
    ax_va = axes[1] if apart else None
    ax_i, ax_soc, ax_t, ax_c = axes[-4:]
    if tr.t_s.size == 0:
        for ax in axes:
            _no_data(ax, "no samples recorded")
        return fig
    t = tr.t_s / axis.scale

    def line(ax: Axes, y: NDArray[np.float64], **kw: Any) -> None:
        if np.isfinite(y).any():
            ax.plot(*downsample(t, y), **kw)

    for b, name in enumerate(names):
        c = battery_color(b)
        ax_vb = ax_va if ax_va is not None and b in apart else ax_v
        line(ax_vb, tr.channel("voltage_v")[:, b], color=c, lw=1.1, label=name)
        line(ax_i, tr.channel("current_a")[:, b], color=c, lw=1.1, label=name)
        line(ax_soc, 100.0 * tr.channel("soc")[:, b], color=c, lw=1.1, label=name)
        line(ax_t, tr.channel("temp_c")[:, b], color=c, lw=1.1, label=name)
        line(ax_c, tr.channel("max_cell_v")[:, b], color=c, lw=1.0, label=f"{name} max")
        line(ax_c, tr.channel("min_cell_v")[:, b], color=c, lw=1.0, ls="--", label=f"{name} min")
    line(ax_v, tr.bus_v, color="k", lw=0.8, ls="--", label="bus")
    _pack_currents(result, ax_i, line)
    ax_i.axhline(0.0, color="0.6", lw=0.6, zorder=0)
    ax_v.set_ylabel(
        "voltage (V)"
        if not apart
        else "voltage (V)\n" + _short(", ".join(names[b] for b in main), 18)
    )
    if ax_va is not None:
        ax_va.set_ylabel("voltage (V)\n" + _short(", ".join(names[b] for b in apart), 18))
    ax_i.set_ylabel("current (A)\n+ = discharge")
    ax_soc.set_ylabel("SOC (%)")
    ax_t.set_ylabel("max cell\ntemperature (°C)")
    ax_c.set_ylabel("cell voltage (V)\nmax —, min --")
    for ax in axes:
        axis.apply(ax, label=ax is ax_c)
    # One legend for the figure: per-panel "best" placement is slow on long runs and repeats.
    handles = _unique_handles([a for a in (ax_v, ax_va, ax_i) if a is not None])
    ax_v.legend(
        handles=handles,
        loc="lower center",
        bbox_to_anchor=(0.5, 1.0),
        fontsize=8,
        ncol=min(len(handles), 10),
        frameon=False,
        borderaxespad=0.2,
    )
    return fig


def switches_figure(
    result: Result, axis: TimeAxis, switch_kinds: Sequence[str | None] | None = None
) -> Figure:
    """Charge and discharge path of every battery as step plots in lanes (a relay: one lane).

    A raised line is a closed path. Orange where current flows through a body diode (path
    off, diode conducting): there a MOSFET pair loses 0.5-0.7 V and heats.
    """
    tr = result.trace
    names = result.battery_names
    chg = tr.channel("chg_on")
    dsg = tr.channel("dsg_on")
    chg_d = tr.channel("chg_diode_a")
    dsg_d = tr.channel("dsg_diode_a")
    lanes: list[tuple[int, str, NDArray[np.float64], NDArray[np.float64] | None]] = []
    for b, name in enumerate(names):
        kind = switch_kinds[b] if switch_kinds is not None and b < len(switch_kinds) else None
        same = bool(np.array_equal(chg[:, b], dsg[:, b], equal_nan=True))
        if kind == "relay":
            lanes.append((b, f"{name} relay", dsg[:, b], None))
        elif kind is None and same:
            lanes.append((b, f"{name} CHG = DSG", dsg[:, b], None))
        else:
            lanes.append((b, f"{name} DSG", dsg[:, b], dsg_d[:, b]))
            lanes.append((b, f"{name} CHG", chg[:, b], chg_d[:, b]))
    fig, (ax,) = _new_figure([max(1.0, 0.42 * len(lanes))], top_in=0.5)
    if tr.t_s.size == 0 or not lanes:
        _no_data(ax, "no samples recorded")
        return fig
    t = tr.t_s / axis.scale
    diode_seen = False
    n = len(lanes)
    min_w = (axis.hi - axis.lo) / 600.0  # ~1.5 px
    for k, (b, _label, state, diode) in enumerate(lanes):
        base = float(n - 1 - k)  # first battery on top
        y = base + 0.7 * np.where(np.isnan(state), np.nan, np.clip(state, 0.0, 1.0))
        idx = step_indices(y)
        c = battery_color(b)
        ax.plot(t[idx], y[idx], drawstyle="steps-post", color=c, lw=1.4)
        ax.fill_between(t[idx], base, y[idx], step="post", color=c, alpha=0.18, lw=0)
        if diode is not None:
            runs = hold_runs(t, np.nan_to_num(np.abs(diode)) > 1e-6, min_width=min_w)
            if runs:
                diode_seen = True
                ax.broken_barh(runs, (base, 0.7), color="tab:orange", alpha=0.5, lw=0)
        if k and lanes[k - 1][0] != b:
            ax.axhline(base + 0.85, color="0.75", lw=0.6)
    ax.set_yticks(
        [n - 1 - k + 0.35 for k in range(n)],
        [_short(lab, 24) for _, lab, _, _ in lanes],
        fontsize=8,
    )
    ax.set_ylim(-0.15, n - 0.15)
    axis.apply(ax)
    ax.grid(False, axis="y")
    ax.set_title("switch paths (raised = closed / on)", fontsize=9, loc="left")
    if diode_seen:
        ax.legend(
            handles=[
                Line2D([], [], color="tab:orange", alpha=0.6, lw=6, label="body diode conducts")
            ],
            loc="lower right",
            bbox_to_anchor=(1.0, 1.0),
            fontsize=8,
            frameon=False,
            borderaxespad=0.2,
        )
    return fig


def protection_figure(
    channels: dict[str, StatusChannel],
    t: NDArray[np.float64],
    axis: TimeAxis,
    names: Sequence[str],
) -> Figure | None:
    """Active protection parameter (steps) and used-up allowance (%) per protected battery."""
    param = channels.get("protection_param")
    frac = channels.get("protection_fraction")
    tripped = channels.get("protection_tripped")
    base = param or frac
    if base is None or not base.columns:
        return None
    cols = base.columns
    # Parameters in their natural order (P1 below P2 below P3), not by first appearance.
    cats = sorted(_categories(param), key=_natural_key) if param is not None else []
    fig, axes = _new_figure([max(1.3, 0.35 + 0.22 * len(cats))] * len(cols), gap_in=0.45)
    for ax, b in zip(axes, cols, strict=True):
        c = battery_color(b)
        handles: list[Line2D] = []
        if param is not None and b in param.columns:
            x, y = _step_xy(param, _label_codes(param, b, cats), t, axis)
            ax.plot(x, y, drawstyle="steps-post", color=c, lw=1.6)
            ax.set_yticks(range(len(cats)), [_short(s, 16) for s in cats], fontsize=8)
            ax.set_ylim(-0.6, len(cats) - 0.4)
            handles.append(Line2D([], [], color=c, lw=1.6, label="active parameter"))
        ax.set_ylabel("parameter", fontsize=8)
        if tripped is not None and b in tripped.columns:
            x, y = _step_xy(tripped, tripped.numeric(b), t, axis)
            runs = hold_runs(x, np.nan_to_num(y) > 0.5, min_width=(axis.hi - axis.lo) / 600.0)
            if runs:
                ax.broken_barh(
                    runs,
                    (0.0, 1.0),
                    color=ALARM_COLOR,
                    alpha=0.18,
                    lw=0,
                    transform=ax.get_xaxis_transform(),
                )
                handles.append(Line2D([], [], color=ALARM_COLOR, alpha=0.4, lw=6, label="tripped"))
        if frac is not None and b in frac.columns:
            ax2 = ax.twinx()
            x, y = _step_xy(frac, 100.0 * frac.numeric(b), t, axis)
            ax2.plot(x, y, color="0.25", lw=1.0, ls="--")
            ax2.set_ylabel("allowance\nused (%)", fontsize=7)
            top = float(np.nanmax(y)) if np.isfinite(y).any() else 100.0
            ax2.set_ylim(0.0, max(105.0, top * 1.05))
            ax2.tick_params(axis="y", labelsize=7)
            handles.append(Line2D([], [], color="0.25", lw=1.0, ls="--", label="allowance used"))
        ax.set_title(names[b] if b < len(names) else f"battery {b}", fontsize=9, loc="left")
        if handles:
            ax.legend(
                handles=handles,
                loc="lower right",
                bbox_to_anchor=(1.0, 1.0),
                fontsize=7,
                ncol=3,
                frameon=False,
                borderaxespad=0.2,
            )
        axis.apply(ax, label=ax is axes[-1])
    return fig


# --------------------------------------------------------------------------- controllers

FAMILIES: tuple[tuple[str, str], ...] = (
    ("mode", "Supervisor"),
    ("seq_", "Parallel discharge sequencing"),
    ("chg_", "Staged charging"),
    ("eq_", "Equalization"),
    ("passive_", "Equalization"),
    ("lim_", "Safety limits"),
    ("limit_", "Safety limits"),
    ("pack_limit_", "Safety limits"),
    ("plaus_", "Plausibility"),
    ("soc_", "SOC estimation"),
)
PROTECTION_PREFIX = "protection_"


def family_of(channel: str) -> str:
    for prefix, family in FAMILIES:
        if channel == prefix or (prefix.endswith("_") and channel.startswith(prefix)):
            return family
    return "Other controller channels"


@dataclass(frozen=True)
class Panel:
    """One axes of a controller figure."""

    title: str
    height_in: float
    draw: Callable[[Axes], None]


def _group_panel(
    base: str,
    members: list[tuple[int, StatusChannel]],
    b: int,
    t: NDArray[np.float64],
    axis: TimeAxis,
    names: Sequence[str],
) -> Panel:
    """Per-group channels (``<base>_g<k>``) of one battery on one axes, colour = group."""

    def draw(ax: Axes) -> None:
        import matplotlib as mpl

        cmap = mpl.colormaps["viridis"]
        n = len(members)
        for j, (g, ch) in enumerate(members):
            x, y = _step_xy(ch, ch.numeric(b), t, axis)
            ax.plot(
                x, y, drawstyle="steps-post", lw=1.0, color=cmap(j / max(n - 1, 1)), label=f"g{g}"
            )
        ax.set_ylabel(channel_label(base), fontsize=8)
        ax.tick_params(axis="y", labelsize=7)
        ax.legend(
            loc="upper left",
            fontsize=6,
            ncol=min(n, 12),
            framealpha=0.7,
            title="group",
            title_fontsize=6,
        )
        axis.apply(ax, label=False)

    who = names[b] if b < len(names) else f"battery {b}"
    return Panel(f"{base} per group — {who}", 2.0, draw)


def controller_panels(
    channels: dict[str, StatusChannel],
    t: NDArray[np.float64],
    axis: TimeAxis,
    names: Sequence[str],
) -> dict[str, list[Panel]]:
    """Panels by controller family for every non-protection status channel."""
    out: dict[str, list[Panel]] = {}
    grouped: dict[str, list[tuple[int, StatusChannel]]] = {}
    for name, ch in channels.items():
        if name.startswith(PROTECTION_PREFIX) or not ch.columns:
            continue
        m = re.fullmatch(r"(.+)_g(\d+)", name)
        if m and ch.kind == "numeric":
            grouped.setdefault(m.group(1), []).append((int(m.group(2)), ch))
            continue
        height = {"label": max(0.9, 0.4 + 0.22 * len(_categories(ch))), "bool": 1.0}.get(
            ch.kind, 1.5
        )

        def draw(ax: Axes, ch: StatusChannel = ch) -> None:
            plot_status(ax, ch, t, axis, names)

        scope = " (pack-wide)" if ch.pack_level else ""
        out.setdefault(family_of(name), []).append(Panel(f"{name}{scope}", height, draw))
    for base, members in grouped.items():
        members.sort(key=lambda gm: gm[0])
        cols = sorted({b for _, ch in members for b in ch.columns})
        family = family_of(base)
        for b in cols:
            present = [(g, ch) for g, ch in members if b in ch.columns]
            out.setdefault(family, []).append(_group_panel(base, present, b, t, axis, names))
    return out


def panels_figures(panels: list[Panel], axis: TimeAxis) -> list[Figure]:
    """Stack panels into figures of at most ``MAX_PANELS_PER_FIGURE`` axes each."""
    figs: list[Figure] = []
    for i in range(0, len(panels), MAX_PANELS_PER_FIGURE):
        chunk = panels[i : i + MAX_PANELS_PER_FIGURE]
        fig, axes = _new_figure([p.height_in for p in chunk], gap_in=0.45)
        for ax, p in zip(axes, chunk, strict=True):
            p.draw(ax)
            ax.set_title(p.title, fontsize=9, loc="left")
        axes[-1].set_xlabel(axis.label)
        figs.append(fig)
    return figs


__all__ = [
    "FAMILIES",
    "Panel",
    "StatusChannel",
    "TimeAxis",
    "batteries_figure",
    "channel_label",
    "controller_panels",
    "events_figure",
    "family_of",
    "hold_runs",
    "panels_figures",
    "plot_status",
    "protection_figure",
    "status_channels",
    "switches_figure",
    "unit_of",
]
