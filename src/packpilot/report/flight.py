"""The flight replay's page with the run report's interactive charts (``replay flight --report``).

The replay layer cannot import the report (the report sits above it), so this module, on the
report's side, draws what :mod:`packpilot.replay.flight_report` lays out — the headlines, what
the log lacks, the log facts — and puts every figure in uPlot charts of the same kind as the
run report's (:mod:`packpilot.report.charts`, ``static/report.js``): drag or wheel to zoom,
hover for values, all charts moving together on the log's time axis. Everything is inline; the
page loads nothing.
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from packpilot.replay.common import ReplayResult
from packpilot.replay.flight import FlightReplay
from packpilot.replay.flight_report import flight_modes, protection_blocks, summary_blocks
from packpilot.report.charts import Chart, Series, Store
from packpilot.report.fmt import esc
from packpilot.report.html import _CSS, _asset
from packpilot.report.style import ALARM_COLOR, battery_color

CUT_COLOR = "#444444"
MODE_COLOR = "#999999"


def _col(res: ReplayResult, name: str) -> np.ndarray:
    j = res.columns.index(name)
    return np.array([np.nan if r[j] is None else r[j] for r in res.rows], dtype=float)


class _Charts:
    """The page's store and charts (the part of the run report's ``Page`` a replay needs)."""

    def __init__(self, t: np.ndarray) -> None:
        self.store = Store(np.arange(len(t), dtype=np.intp))
        self.tkey = self.store.add("t", t, 1e-3)
        self.span = [float(t[0]), float(t[-1])] if len(t) else [0.0, 1.0]
        self.charts: dict[str, Chart] = {}

    def add(self, chart: Chart, caption: str = "") -> str:
        self.charts[chart.id] = chart
        cap = f'<p class="cap">{esc(caption)}</p>' if caption else ""
        return (
            f'<div class="chart" data-chart="{esc(chart.id)}" style="min-height:'
            f'{chart.height + 60}px"><div class="ctitle">{esc(chart.title)}</div>'
            f'<div class="plot"></div>{cap}</div>'
        )

    def scripts(self) -> str:
        data = {
            "t": self.tkey,
            "span": self.span,
            "store": self.store.data,
            "charts": {cid: c.spec() for cid, c in self.charts.items()},
        }
        text = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
        licence = _asset("uplot/LICENSE").replace("*/", "* /")
        return (
            f"<style>{_asset('uplot/uPlot.min.css')}</style>"
            f"<script>/* uPlot, bundled unmodified. {licence} */\n"
            f"{_asset('uplot/uPlot.iife.min.js')}</script>"
            f'<script type="application/json" id="pp-data">{text}</script>'
            f"<script>{_asset('report.js')}</script>"
        )


def _protection(page: _Charts, fr: FlightReplay, k: int, name: str, res: ReplayResult) -> str:
    """One battery: lowest cell against the cut-off, current, temperature, allowance used."""
    log = fr.log
    prefix = f"{name}_" if name else ""
    color = battery_color(k)
    trip = res.summary["trip_time_s"]
    marks = [(float(trip), ALARM_COLOR, "would trip")] if isinstance(trip, float) else []
    marks += _mode_marks(fr)
    ident = name or "battery"
    v = Chart(f"{ident}-cell", "Lowest cell and the cut-off it would apply (V)", "V", marks=marks)
    vmin = log.columns.get(f"{prefix}min_cell_v")
    if vmin is not None:
        v.series.append(Series(page.store.add(f"{ident}/vmin", vmin), "lowest cell", color))
    cut = page.store.add(f"{ident}/cut", _col(res, "cutoff_v"))
    v.series.append(Series(cut, "cut-off", CUT_COLOR, dash=True, step=True, width=1.2))
    i = Chart(f"{ident}-current", "Current, + = discharge (A)", "A", height=150, marks=marks)
    i.series.append(
        Series(page.store.add(f"{ident}/i", log.columns[f"{prefix}current_a"]), ident, color)
    )
    parts = [page.add(v), page.add(i)]
    temp = log.columns.get(f"{prefix}temp_c")
    if temp is not None:
        tc = Chart(f"{ident}-temp", "Temperature (°C)", "°C", height=130, marks=marks)
        tc.series.append(Series(page.store.add(f"{ident}/temp", temp), ident, color))
        parts.append(page.add(tc))
    else:
        parts.append('<p class="note">Temperature: assumed constant (not in the log).</p>')
    m_s = float(res.summary["m_s"])  # type: ignore[arg-type]
    frac = 100.0 * _col(res, "weighted_s") / m_s
    a = Chart(f"{ident}-allowance", "Share of the allowance used (%)", "%", height=140,
              marks=marks)  # fmt: skip
    a.series.append(Series(page.store.add(f"{ident}/frac", frac), ident, color))
    top = float(np.nanmax(frac)) if np.isfinite(frac).any() else 100.0
    a.y_range = (0.0, max(105.0, top * 1.05))
    parts.append(page.add(a, "The protection trips at 100 %."))
    return "".join(parts)


def _mode_marks(fr: FlightReplay) -> list[tuple[float, str, str]]:
    """The log's flight modes as the charts' vertical marks (the pilot's time axis)."""
    return [(t, MODE_COLOR, m) for t, m in flight_modes(fr)]


def _sequencing(page: _Charts, fr: FlightReplay, res: ReplayResult) -> str:
    """The pack: each battery's voltage and current, and the FETs sequencing would command."""
    log = fr.log
    n = len(fr.batteries)
    modes = _mode_marks(fr)
    v = Chart("seq-voltage", "Battery voltage, from the log (V)", "V", marks=modes)
    i = Chart("seq-current", "Current, + = discharge, from the log (A)", "A", height=150,
              marks=modes)  # fmt: skip
    fets = Chart("seq-fets", "FETs sequencing would command (solid: charge, dashed: discharge)",
                 categories=["off", "on"], height=110, marks=modes)  # fmt: skip
    for k, name in enumerate(fr.batteries):
        c = battery_color(k)
        v.series.append(Series(page.store.add(f"{name}/v", log.columns[f"{name}_voltage_v"]),
                               name, c))  # fmt: skip
        i.series.append(Series(page.store.add(f"{name}/seq-i", log.columns[f"{name}_current_a"]),
                               name, c))  # fmt: skip
        off = (k - (n - 1) / 2) * 0.12
        fets.series.append(Series(page.store.add(f"{name}/chg", _col(res, f"chg_{k}"), 1.0),
                                  f"{name} charge", c, step=True, offset=off, states=("off", "on")))
        fets.series.append(Series(page.store.add(f"{name}/dsg", _col(res, f"dsg_{k}"), 1.0),
                                  f"{name} discharge", c, dash=True, step=True, offset=off + 0.04,
                                  states=("off", "on")))  # fmt: skip
    return page.add(v) + page.add(i) + page.add(fets)


_EXTRA_CSS = """
main { max-width: 1100px; }
.verdict-box { border-left: 6px solid #555; background: #f6f6f6; padding: .6em 1em; }
.verdict-box.trip { border-color: #d62728; }
.verdict-box li, .lacks li { margin: .25em 0; }
"""


def flight_page(fr: FlightReplay) -> str:
    """The whole page: headlines first, what the log lacks, the log facts, then the charts."""
    s = fr.summary
    t = np.asarray(fr.log.columns["t_s"], dtype=float)
    page = _Charts(t)
    names = ", ".join(b or "battery" for b in fr.batteries)
    body = [
        *summary_blocks(fr, "verdict-box", "note"),
        *protection_blocks(fr, lambda k, name, res: _protection(page, fr, k, name, res)),
    ]
    if fr.sequencing is not None:
        body += ["<h2>Parallel discharge sequencing</h2>", _sequencing(page, fr, fr.sequencing)]
    sub = (
        f"{html.escape(str(s['log']))} · {html.escape(str(s['source']))} · {s['rows']} rows · "
        f"{float(s['duration_s']):.1f} s · batteries {html.escape(names)}"  # type: ignore[arg-type]
    )
    zoom = (
        '<div class="zoombar">Charts: drag across one to zoom, wheel to zoom around the cursor,'
        ' double-click to go back; they move together. Showing: <strong data-range="run">whole'
        ' run</strong><button type="button" data-reset="run">reset zoom</button></div>'
    )
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        "<title>PackPilot flight replay</title>"
        f"<style>{_CSS}{_EXTRA_CSS}</style></head><body>"
        f"<header><h1>What PackPilot would have done on this flight</h1>"
        f'<p class="sub">{sub}</p></header>{zoom}<main>{"".join(body)}</main>'
        "<footer>Self-contained: the charts (uPlot, MIT licence) and their data are embedded,"
        f" nothing is loaded from the network.</footer>{page.scripts()}</body></html>\n"
    )


def write_flight_page(fr: FlightReplay, out: Path) -> None:
    out.write_text(flight_page(fr), encoding="utf-8")


__all__ = ["flight_page", "write_flight_page"]
