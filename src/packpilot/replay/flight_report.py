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
    trip = res.summary["trip_time_s"]
    if isinstance(trip, float):
        for a in ax:
            a.axvline(trip, color=TRIP, lw=1.2)
        ax[0].annotate("would trip", (trip, 0.95), xycoords=("data", "axes fraction"),
                       color=TRIP, fontsize=8, ha="right")  # fmt: skip
    for a in ax:
        a.grid(alpha=0.3)
    return _svg(fig)


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


__all__ = ["flight_html", "write_flight_report"]
