"""Figures of a run: per-battery voltage, current, SOC and temperature with event markers.

Built on ``matplotlib.figure.Figure`` with an Agg canvas, never ``pyplot``: no display is
needed, no global figure state leaks between calls, and the web/report code can render
figures from worker threads.
"""

from __future__ import annotations

import base64
import io
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from numpy.typing import NDArray

from packpilot.contract.bms import Event
from packpilot.contract.record import Result
from packpilot.contract.soc_source import LABELS as SOC_LABELS
from packpilot.contract.soc_source import SOURCES
from packpilot.errors import InputError
from packpilot.report.channels import SOC_CHANNELS, core_soc, status_channels
from packpilot.report.style import battery_color

_FORMATS = ("png", "svg", "pdf")
_MAX_EVENT_LABELS = 12
"""Above this many events only the legend names the kinds; per-line text would overlap."""
_LABEL_CHARS = 34
"""A rotated label longer than this would run out of the top panel."""
# Events use a palette distinct from the battery lines (tab10) so a marker never looks like data.
_EVENT_COLORS = ("#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")


def _time_unit(t_s: NDArray[np.float64]) -> tuple[float, str]:
    """Seconds per plotted unit and the axis label: s, min or h so tick labels stay short."""
    span = float(np.nanmax(t_s) - np.nanmin(t_s)) if np.isfinite(t_s).any() else 0.0
    if span > 3 * 3600:
        return 3600.0, "time (h)"
    if span > 300:
        return 60.0, "time (min)"
    return 1.0, "time (s)"


def _has_data(x: NDArray[np.float64]) -> bool:
    return bool(np.isfinite(x).any())


UNDRAWN_KINDS = frozenset({"BalancingUpdated", "SocCorrected"})
"""Routine kinds counted in the legend but not drawn: the demo's 136 balancing updates drew a
grey curtain over every panel (the dashboard's charts leave them out too)."""


def _plot_events(result: Result, axes: list[Axes], scale: float) -> list[Line2D]:
    """Vertical lines on every panel, one colour per kind; legend handles returned."""
    every = [e for e in result.events if np.isfinite(e.t_s)]
    if not every:
        return []
    counts = Counter(e.kind for e in every)
    events = [e for e in every if e.kind not in UNDRAWN_KINDS]
    colors = {k: _EVENT_COLORS[i % len(_EVENT_COLORS)] for i, k in enumerate(counts)}
    alpha = 0.8 if len(events) <= 50 else 0.35
    for e in events:
        x = e.t_s / scale
        for ax in axes:
            ax.axvline(x, color=colors[e.kind], lw=0.9, ls=":", alpha=alpha, zorder=1)
    if events and len(events) <= _MAX_EVENT_LABELS:
        _label_events(result, events, axes[0], scale, colors)
    return [
        Line2D([], [], color=colors[k], ls=":", lw=1.2, label=f"{k} ({n})")
        if k not in UNDRAWN_KINDS
        else Line2D([], [], color="none", ls="none", label=f"{k} ({n}, not drawn)")
        for k, n in counts.items()
    ]


def _label_events(
    result: Result, events: list[Event], ax: Axes, scale: float, colors: dict[str, str]
) -> None:
    """One rotated label per cluster of near-simultaneous events, so texts never overprint."""
    t = np.array([e.t_s for e in events]) / scale
    span = float(t.max() - t.min()) or 1.0
    order = np.argsort(t, kind="stable")
    clusters: list[list[Event]] = []
    last = -np.inf
    for i in order:
        if t[i] - last > 0.015 * span or not clusters:
            clusters.append([])
        clusters[-1].append(events[i])
        last = t[i]
    for cl in clusters:
        parts = []
        for (kind, b), n in Counter((e.kind, e.battery) for e in cl).items():
            who = ""
            if b is not None and 0 <= b < len(result.battery_names):
                who = f" {result.battery_names[b]}"
            parts.append(f"{kind}{who}" + (f" ×{n}" if n > 1 else ""))
        text = ", ".join(parts)
        if len(text) > _LABEL_CHARS:
            text = text[: _LABEL_CHARS - 1] + "…"
        label = ax.annotate(
            text,
            xy=(cl[0].t_s / scale, 1.0),
            xycoords=("data", "axes fraction"),
            xytext=(2, -3),
            textcoords="offset points",
            rotation=90,
            va="top",
            ha="left",
            fontsize=7,
            color=colors[cl[0].kind],
            bbox={"boxstyle": "square,pad=0.1", "fc": "white", "ec": "none", "alpha": 0.7},
            annotation_clip=True,
        )
        label.set_clip_on(True)
        label.set_in_layout(False)  # a long label must not squeeze the panels


def _range_on_batteries(ax: Axes, t: Any, tr: Any) -> None:
    """The voltage panel spans the batteries, not a bus that dropped to 0 V (which would squash
    them into a thin band); where the bus is off that scale it is shaded grey and labelled."""
    from packpilot.report.charts import spans
    from packpilot.report.sections import battery_v_range

    volts = tr.channel("voltage_v")
    rng = battery_v_range(np.asarray(volts, dtype=np.float64))
    if rng is None:
        return
    ax.set_ylim(*rng)
    if not _has_data(tr.bus_v):
        return
    with np.errstate(invalid="ignore"):
        off = (tr.bus_v < rng[0]) | (tr.bus_v > rng[1])
    found = spans(np.asarray(t, dtype=np.float64), off)
    for k, (a, b) in enumerate(found):
        ax.axvspan(a, b, color="0.6", alpha=0.3, lw=0, label="bus off scale" if k == 0 else None)


def run_figure(result: Result) -> Figure:
    """The standard four-panel figure of a run (also embedded in the HTML report)."""
    tr = result.trace
    fig = Figure(figsize=(10.0, 9.0), layout="constrained")
    FigureCanvasAgg(fig)
    axes = list(fig.subplots(4, 1, sharex=True))
    title = "PackPilot run" + (f" {result.run_id}" if result.run_id is not None else "")
    fig.suptitle(title, fontsize=11)
    if tr.t_s.size == 0:
        for ax in axes:
            ax.text(0.5, 0.5, "no samples", ha="center", va="center", transform=ax.transAxes)
        return fig

    scale, t_label = _time_unit(tr.t_s)
    t = tr.t_s / scale
    ax_v, ax_i, ax_soc, ax_t = axes
    soc_chans = status_channels(result, SOC_CHANNELS)
    sources: set[str] = set()
    for b, name in enumerate(result.battery_names):
        color = battery_color(b)
        ax_v.plot(t, tr.channel("voltage_v")[:, b], color=color, lw=1.2, label=name)
        ax_i.plot(t, tr.channel("current_a")[:, b], color=color, lw=1.2, label=name)
        # the SOC the core used (solid), the plant's truth (dashed) where it differs
        truth = tr.channel("soc")[:, b]
        soc, codes = core_soc(soc_chans, len(t), b, truth)
        sources |= {SOURCES[int(k)] for k in np.unique(codes)}
        ax_soc.plot(t, 100.0 * soc, color=color, lw=1.2, label=name)
        if not np.allclose(soc, truth, atol=1e-9, equal_nan=True):
            ax_soc.plot(t, 100.0 * truth, color=color, lw=0.7, ls="--", label=f"{name} (plant)")
        ax_t.plot(t, tr.channel("temp_c")[:, b], color=color, lw=1.2, label=name)
    if _has_data(tr.bus_v):
        ax_v.plot(t, tr.bus_v, color="k", lw=0.8, ls="--", label="bus")
    _range_on_batteries(ax_v, t, tr)
    if _has_data(tr.load_a) and np.nanmax(np.abs(tr.load_a)) > 0:
        ax_i.plot(t, tr.load_a, color="k", lw=0.8, ls="--", label="load")
    # Demand only when it differs from what was delivered: that gap is an unsupplied load.
    if _has_data(tr.load_demand_a) and not np.allclose(
        tr.load_demand_a, tr.load_a, rtol=1e-6, atol=1e-6, equal_nan=True
    ):
        ax_i.plot(t, tr.load_demand_a, color="0.5", lw=0.8, ls=":", label="load demand")
    if _has_data(tr.charger_a) and np.nanmax(np.abs(tr.charger_a)) > 0:
        ax_i.plot(t, tr.charger_a, color="0.4", lw=0.8, ls="-.", label="charger")
    ax_i.axhline(0.0, color="0.6", lw=0.6, zorder=0)

    ax_v.set_ylabel("voltage (V)")
    ax_i.set_ylabel("current (A)\n+ = discharge")
    ax_soc.set_ylabel("SOC (%)")
    used = ", ".join(SOC_LABELS[x] for x in SOURCES if x in sources)
    ax_soc.set_title(f"SOC the BMS used ({used}); dashed: the plant's truth", fontsize=8,
                     loc="left")  # fmt: skip
    ax_t.set_ylabel("temperature (°C)")
    ax_t.set_xlabel(t_label)
    if np.isfinite(t).any() and np.nanmax(t) > np.nanmin(t):
        ax_t.set_xlim(float(np.nanmin(t)), float(np.nanmax(t)))
    for ax in axes:
        ax.grid(True, lw=0.4, alpha=0.5)

    event_handles = _plot_events(result, axes, scale)
    ncol = min(len(result.battery_names) + 1, 6)
    ax_v.legend(loc="best", fontsize=8, ncol=ncol, framealpha=0.8)
    ax_i.legend(loc="best", fontsize=8, ncol=ncol, framealpha=0.8)
    if event_handles:
        fig.legend(
            handles=event_handles,
            loc="outside lower center",
            ncol=min(len(event_handles), 4),
            fontsize=8,
            title="events",
            title_fontsize=8,
            frameon=False,
        )
    return fig


def plot_run(result: Result, out_path: Path | str) -> None:
    """Write the run figure; the format follows the suffix (.png, .svg or .pdf)."""
    out = Path(out_path)
    fmt = out.suffix.lower().lstrip(".")
    if fmt not in _FORMATS:
        raise InputError(
            f"{out}: plot file must end in one of {', '.join('.' + f for f in _FORMATS)}"
        )
    fig = run_figure(result)
    fig.savefig(out, format=fmt, dpi=120)


def figure_png_base64(fig: Figure, *, dpi: int = 100) -> str:
    """A PNG of ``fig`` as base64 text, for ``<img src="data:image/png;base64,...">``."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    return base64.b64encode(buf.getvalue()).decode("ascii")


__all__ = ["figure_png_base64", "plot_run", "run_figure"]
