"""The flight replay as one self-contained HTML page (inline SVG, no script, no network).

Kept apart from ``packpilot.report`` (a run's report, which sits above the replay layer and is
being redesigned): this page has its own few figures — per battery the lowest cell against the
cut-off the protection would have applied, the current, the temperature (or the assumption in
its place) and the share of the allowance used; for a pack, each battery's voltage, current and
the charge and discharge FETs sequencing would have commanded.
"""

from __future__ import annotations

import html
import io
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from packpilot.replay.common import ReplayResult
from packpilot.replay.flight import FlightReplay

COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#17becf")
"""Battery colours; the alarm red (trip markers) is not among them."""
TRIP = "#d62728"

CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
.verdict{border-left:6px solid #555;background:#f6f6f6;padding:.6em 1em}
.verdict.trip{border-color:#d62728}.verdict li{margin:.25em 0}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.2em .6em;text-align:left}
.lacks li{margin:.2em 0}.muted{color:#666}svg{max-width:100%;height:auto}
"""


def _svg(fig: Figure) -> str:
    FigureCanvasAgg(fig)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    # The RDF metadata block (creator, date) names URLs and changes every run: not needed.
    return re.sub(r"<metadata>.*?</metadata>", "", text[text.index("<svg") :], flags=re.S)


def _col(res: ReplayResult, name: str) -> list[object]:
    j = res.columns.index(name)
    return [r[j] for r in res.rows]


def _protection_figure(fr: FlightReplay, name: str, res: ReplayResult, color: str) -> str:
    log = fr.log
    prefix = f"{name}_" if name else ""
    t = log.columns["t_s"]
    fig = Figure(figsize=(10, 6.4))
    ax = fig.subplots(4, 1, sharex=True)
    vmin = log.columns.get(f"{prefix}min_cell_v")
    cut = np.array([np.nan if c is None else c for c in _col(res, "cutoff_v")], dtype=float)
    if vmin is not None:
        ax[0].plot(t, vmin, color=color, lw=1.2, label="lowest cell (log)")
    ax[0].step(t, cut, where="post", color="#444", lw=1, ls="--", label="cut-off it would apply")
    ax[0].set_ylabel("cell V")
    ax[0].legend(loc="lower left", fontsize=8)
    ax[1].plot(t, log.columns[f"{prefix}current_a"], color=color, lw=1)
    ax[1].set_ylabel("current A")
    temp = log.columns.get(f"{prefix}temp_c")
    if temp is not None:
        ax[2].plot(t, temp, color=color, lw=1)
    else:
        ax[2].text(0.5, 0.5, "assumed constant (not in the log)", transform=ax[2].transAxes,
                   ha="center", va="center", color="#666")  # fmt: skip
    ax[2].set_ylabel("temp °C")
    m_s = float(res.summary["m_s"])  # type: ignore[arg-type]
    frac = np.array(_col(res, "weighted_s"), dtype=float) / m_s
    ax[3].plot(t, 100 * frac, color=color, lw=1.2)
    ax[3].axhline(100, color=TRIP, lw=0.8, ls=":")
    ax[3].set_ylabel("allowance %")
    ax[3].set_xlabel("time since log start (s)")
    _mode_marks(fr, ax)
    trip = res.summary["trip_time_s"]
    if isinstance(trip, float):
        for a in ax:
            a.axvline(trip, color=TRIP, lw=1.2)
        ax[0].annotate("would trip", (trip, 0.95), xycoords=("data", "axes fraction"),
                       color=TRIP, fontsize=8, ha="right")  # fmt: skip
    for a in ax:
        a.grid(alpha=0.3)
    return _svg(fig)


MODE_COLOR = "#888888"


def flight_modes(fr: FlightReplay) -> list[tuple[float, str]]:
    """The log's flight-mode changes (t_s, name), from the replay's summary."""
    pilot = fr.summary.get("pilot")
    if not isinstance(pilot, dict):
        return []
    return [(float(t), str(m)) for t, m in pilot["flight_modes"]]


def _mode_marks(fr: FlightReplay, ax: object) -> None:
    """Flight modes as thin grey lines on every axis, named on the first."""
    axes = list(ax)  # type: ignore[call-overload]
    for t, m in flight_modes(fr):
        for a in axes:
            a.axvline(t, color=MODE_COLOR, lw=0.6, ls=":")
        axes[0].annotate(m, (t, 0.02), xycoords=("data", "axes fraction"), rotation=90,
                         color="#666", fontsize=6, va="bottom")  # fmt: skip


def _sequencing_figure(fr: FlightReplay, res: ReplayResult) -> str:
    log = fr.log
    t = log.columns["t_s"]
    fig = Figure(figsize=(10, 5.6))
    ax = fig.subplots(3, 1, sharex=True, height_ratios=(1, 1, 0.6 + 0.5 * len(fr.batteries)))
    ticks: list[tuple[float, str]] = []
    for k, name in enumerate(fr.batteries):
        c = COLORS[k % len(COLORS)]
        ax[0].plot(t, log.columns[f"{name}_voltage_v"], color=c, lw=1, label=name)
        ax[1].plot(t, log.columns[f"{name}_current_a"], color=c, lw=1, label=name)
        base = 2.5 * (len(fr.batteries) - 1 - k)
        chg = np.array(_col(res, f"chg_{k}"), dtype=float)
        dsg = np.array(_col(res, f"dsg_{k}"), dtype=float)
        ax[2].step(t, base + 1.2 + 0.8 * dsg, where="post", color=c, lw=1.4, ls="--")
        ax[2].step(t, base + 0.8 * chg, where="post", color=c, lw=1.4)
        ticks += [(base + 0.4, f"{name} charge"), (base + 1.6, f"{name} discharge")]
    ax[0].set_ylabel("battery V (log)")
    ax[1].set_ylabel("current A (log)")
    ax[1].axhline(0, color="#888", lw=0.6)
    ax[2].set_yticks([y for y, _ in ticks], [label for _, label in ticks], fontsize=7)
    ax[2].set_ylabel("FETs it would\ncommand (up = on)")
    ax[2].set_xlabel("time since log start (s)")
    ax[0].legend(loc="upper right", fontsize=8)
    _mode_marks(fr, ax)
    for a in ax:
        a.grid(alpha=0.3)
    return _svg(fig)


def _li(items: list[str]) -> str:
    return "".join(f"<li>{html.escape(x)}</li>" for x in items)


def _facts_table(fr: FlightReplay) -> str:
    facts = fr.summary["log_facts"]
    assert isinstance(facts, dict)
    if not facts:
        return ""
    rows = []
    for name, f in facts.items():

        def cell(key: str, unit: str, f: dict[str, object] = f) -> str:
            v = f.get(key)
            return "–" if not isinstance(v, float) else f"{v:.3g} {unit}"

        when = f.get("peak_charge_t_s")
        at = f" at {when:.1f} s" if isinstance(when, float) else ""
        rows.append(
            f"<tr><td>{html.escape(name)}</td><td>{cell('peak_discharge_a', 'A')}</td>"
            f"<td>{cell('peak_charge_a', 'A')}{at}</td>"
            f"<td>{cell('lowest_min_cell_v', 'V')}</td></tr>"
        )
    return (
        "<h2>What the log shows</h2><table><tr><th>battery</th><th>peak discharge</th>"
        "<th>peak charge into it (cross-charge while flying)</th><th>lowest cell</th></tr>"
        + "".join(rows)
        + "</table>"
    )


SAG_POINTS = 1500
"""Most samples the sag chart draws (every k-th beyond that)."""


def _sag_svg(v: np.ndarray, i: np.ndarray, fit: dict[str, float], color: str) -> str:
    """Voltage against current, the samples and the straight line through the loaded ones: a
    small inline SVG (this chart has no time axis, so it is not one of the zoomable ones)."""
    ok = np.isfinite(v) & np.isfinite(i)
    v, i = v[ok], i[ok]
    step = max(1, len(v) // SAG_POINTS)
    v, i = v[::step], i[::step]
    w, h, pad = 420, 240, 40
    x0, x1 = min(0.0, float(i.min())), float(i.max()) * 1.05 or 1.0
    y0, y1 = float(v.min()) - 0.05, float(v.max()) + 0.05

    def px(a: float) -> float:
        return pad + (a - x0) / (x1 - x0) * (w - pad - 10)

    def py(a: float) -> float:
        return h - pad + (a - y0) / (y1 - y0) * -(h - pad - 10)

    dots = "".join(
        f"<circle cx='{px(a):.1f}' cy='{py(b):.1f}' r='1.6'/>" for a, b in zip(i, v, strict=True)
    )
    r, v0 = fit["resistance_ohm"], fit["v0_v"]
    xe = min(x1, (v0 - y0) / r) if r > 0 else x1  # the line ends where it leaves the chart
    line = (f"<line x1='{px(x0):.1f}' y1='{py(v0 - r * x0):.1f}' x2='{px(xe):.1f}' "
            f"y2='{py(v0 - r * xe):.1f}' stroke='#444' stroke-dasharray='4 3'/>")  # fmt: skip
    axes = (
        f"<line x1='{pad}' y1='{h - pad}' x2='{w - 10}' y2='{h - pad}' stroke='#888'/>"
        f"<line x1='{pad}' y1='10' x2='{pad}' y2='{h - pad}' stroke='#888'/>"
        f"<text x='{w / 2}' y='{h - 8}' text-anchor='middle'>current (A): {x0:.0f}..{x1:.0f}</text>"
        f"<text x='12' y='{h / 2}' transform='rotate(-90 12 {h / 2})' text-anchor='middle'>"
        f"voltage (V): {y0:.2f}..{y1:.2f}</text>"
    )
    return (
        f"<svg class='sag' viewBox='0 0 {w} {h}' width='{w}' role='img' "
        f"aria-label='voltage against current' style='max-width:100%;height:auto;font-size:11px'>"
        f"{axes}<g fill='{color}' fill-opacity='0.45'>{dots}</g>{line}</svg>"
    )


def _pilot_table(fr: FlightReplay) -> str:
    pilot = fr.summary.get("pilot")
    if not isinstance(pilot, dict):
        return ""
    charge = pilot["charge"]
    heads = {h.split(":", 1)[0]: h.split(": ", 1)[-1] for h in fr.summary["headlines"]  # type: ignore[attr-defined]
             if ":" in h}  # fmt: skip

    def mah(x: object) -> str:
        return "–" if not isinstance(x, float) else f"{x:.0f} mAh"

    def pct(x: object) -> str:
        return "–" if not isinstance(x, float) else f"{100 * x:.0f} %"

    rows = []
    for name, a in charge.items():
        diff = "–"
        if isinstance(a["packpilot_mah"], float) and isinstance(a["autopilot_mah"], float):
            diff = f"{a['packpilot_mah'] - a['autopilot_mah']:+.0f} mAh"
        warn = "none"
        if a["warning_worst"] is not None:
            warn = f"{a['warning_worst']} from {a['warning_first_t_s']:.1f} s"
        elif pilot.get("texts"):
            (t0, first), n = pilot["texts"][0], len(pilot["texts"])
            warn = f"'{first}' at {t0:.1f} s" + (f" ({n} battery messages)" if n > 1 else "")
        rem = "–" if a["remaining_start"] is None else (
            f"{pct(a['remaining_start'])} → {pct(a['remaining_end'])} "
            f"(lowest {pct(a['remaining_lowest'])})")  # fmt: skip
        rows.append(
            f"<tr><td>{html.escape(name)}</td><td>{mah(a['packpilot_mah'])}</td>"
            f"<td>{mah(a['autopilot_mah'])}</td><td>{diff}</td><td>{rem}</td>"
            f"<td>{html.escape(warn)}</td><td>{html.escape(heads.get(name, '–'))}</td></tr>"
        )
    table = (
        "<table id='pilot'><tr><th>battery</th><th>charge used (PackPilot, from the logged "
        "current)</th><th>the autopilot's count</th><th>difference</th><th>the autopilot's "
        "remaining</th><th>the autopilot's warnings</th><th>what PackPilot would have done"
        "</th></tr>" + "".join(rows) + "</table>"
    ) if rows else ""  # fmt: skip
    return table


def _modes_line(fr: FlightReplay) -> str:
    pilot = fr.summary.get("pilot")
    if not isinstance(pilot, dict) or not pilot["flight_modes"]:
        return "<p id='modes'>Flight modes: not in the log.</p>"
    shown = " → ".join(f"{html.escape(str(m))} {t:.1f} s" for t, m in pilot["flight_modes"])
    return f"<p id='modes'>Flight modes (marked on the charts' time axis): {shown}</p>"


def _sag_blocks(fr: FlightReplay) -> list[str]:
    pilot = fr.summary.get("pilot")
    if not isinstance(pilot, dict):
        return []
    out: list[str] = []
    log = fr.log
    for k, (name, fit) in enumerate(pilot["sag"].items()):
        prefix = "" if name == "battery" and "voltage_v" in log.columns else f"{name}_"
        if not isinstance(fit, dict):
            out.append(f"<p>{html.escape(name)}: the log's current does not move enough to "
                       "draw voltage against current.</p>")  # fmt: skip
            continue
        v, i = log.columns[f"{prefix}voltage_v"], log.columns[f"{prefix}current_a"]
        out.append(
            f"<p>{html.escape(name)}: the voltage sagged {fit['sag_at_peak_v']:.2f} V at the "
            f"peak {fit['peak_a']:.1f} A; the straight line through {fit['samples']} loaded "
            f"samples is V = {fit['v0_v']:.2f} V − {1000 * fit['resistance_ohm']:.1f} mΩ × I "
            "(cells, wiring, connectors and the sensor together; one line is the flight's "
            "average: a pack that warms sags less as it goes).</p>"
            + _sag_svg(v, i, fit, COLORS[k % len(COLORS)])
        )
    return out


def pilot_blocks(fr: FlightReplay) -> list[str]:
    """The flight as the pilot saw it: charge used by both counts, the autopilot's remaining and
    warnings next to what PackPilot would have done, the flight modes, the voltage sag."""
    return [
        "<h2>The flight as the pilot saw it</h2>", _pilot_table(fr), _modes_line(fr),
        "<h3>Voltage sag against current</h3>", *_sag_blocks(fr),
    ]  # fmt: skip


def summary_blocks(fr: FlightReplay, box_class: str, note_class: str) -> list[str]:
    """What both flight pages open with: the verdict lines, the open-loop caveat, what the log
    lacks or assumed, the log's facts (this static page and ``report.flight``'s zoomable one)."""
    s = fr.summary
    tripped = any(r.summary["tripped"] for r in fr.protection.values())
    heads = s["headlines"]
    assert isinstance(heads, list)
    lacks = [*s["assumed"], *s["notes"]]  # type: ignore[misc]
    return [
        f"<div class='{box_class}{' trip' if tripped else ''}' id='verdict'>"
        f"<ul>{_li(heads)}</ul></div>",
        f"<p class='{note_class}'>Open loop: the log's measurements are as flown; these are the"
        " commands PackPilot would have given from them, not a re-flown flight.</p>",
        "<h2>What the log lacks, and what was assumed</h2>",
        f"<ul class='lacks' id='lacks'>{_li(lacks) or '<li>nothing</li>'}</ul>",
        _facts_table(fr),
        *pilot_blocks(fr),
    ]


def protection_blocks(
    fr: FlightReplay, figure: Callable[[int, str, ReplayResult], str]
) -> list[str]:
    """One section per battery: its protection replay drawn by ``figure(k, name, result)``, or
    why it was not replayed."""
    out: list[str] = []
    for k, name in enumerate(fr.batteries):
        res = fr.protection.get(name)
        title = f"Protection, battery {html.escape(name or '')}".rstrip(", ")
        if res is None:
            out.append(f"<h2>{title}</h2><p>not replayed: {html.escape(fr.skipped[name])}</p>")
            continue
        out += [f"<h2>{title}</h2>", figure(k, name, res)]
    return out


def flight_html(fr: FlightReplay) -> str:
    """The page: verdict lines first, then what the log lacks, then the figures."""
    s = fr.summary
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        "<title>PackPilot flight replay</title>",
        f"<style>{CSS}</style></head><body>",
        "<h1>What PackPilot would have done on this flight</h1>",
        f"<p class='muted'>{html.escape(str(s['log']))} · {html.escape(str(s['source']))} · "
        f"{s['rows']} rows · {float(s['duration_s']):.1f} s · batteries "  # type: ignore[arg-type]
        f"{html.escape(', '.join(b or 'battery' for b in fr.batteries))}</p>",
        *summary_blocks(fr, "verdict", "muted"),
        *protection_blocks(
            fr, lambda k, name, res: _protection_figure(fr, name, res, COLORS[k % len(COLORS)])
        ),
    ]
    if fr.sequencing is not None:
        parts += ["<h2>Parallel discharge sequencing</h2>", _sequencing_figure(fr, fr.sequencing)]
    parts.append("</body></html>")
    return "\n".join(parts)


def write_flight_report(fr: FlightReplay, out: Path) -> None:
    out.write_text(flight_html(fr), encoding="utf-8")


__all__ = ["flight_html", "flight_modes", "pilot_blocks", "write_flight_report"]
