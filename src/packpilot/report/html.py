"""The single-file HTML run report: verdict and KPIs first, one section per enabled method with
the figures the benchmarks judge it by, interactive charts, nominal channels in one line each.

One file that opens anywhere, offline, years later: the charting library (uPlot, MIT, bundled as
package data under ``report/static/uplot``), the chart script and the data are inline; there is
no external URL. The tables (verdict, KPIs, figures, events) need no script; the charts do (any
current browser). Built from a :class:`Result`, so ``simulate --report`` needs no database and
``report`` reads one with ``report/stream.py`` (a run of up to ``charts.FULL_RES_MAX`` samples
whole, a longer one in blocks: exact figures folded by ``report/digest.py``, a min/max-decimated
trace for the charts, memory bounded whatever the run's length). The series are packed at full
resolution (long runs are thinned, see ``report/charts.py``) and the event table is capped, so a
10-hour run still makes a small file quickly.
"""

from __future__ import annotations

import datetime as _dt
import importlib.metadata
import json
import math
from collections import Counter
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.contract.bms import Event
from packpilot.contract.record import Result
from packpilot.contract.severity import Severity, row_of
from packpilot.contract.soc_source import BATTERY, SOURCES
from packpilot.contract.soc_source import LABELS as SOC_LABELS
from packpilot.errors import InputError
from packpilot.report import sections as S
from packpilot.report.can_log import can_section
from packpilot.report.digest import CHANGES_PER_BUCKET as DECIMATED_CHANGES
from packpilot.report.digest import RunDigest
from packpilot.report.fmt import (
    METRIC_DOC,
    esc,
    fmt_data,
    fmt_date,
    fmt_num,
    fmt_time,
    metric_unit,
    metric_value,
    table,
)
from packpilot.report.info import RunInfo, run_info_from_db
from packpilot.report.sections import SHORT as SOC_SHORT
from packpilot.report.style import ALARM_COLOR
from packpilot.sim.verdict import Verdict

SECTION_IDS: tuple[str, ...] = (
    "verdict",
    "summary",
    "batteries",
    "switches",
    "events",
    "controllers",
)
"""Sections every report has; method sections (:data:`METHOD_SECTIONS`) and ``can`` come
when the run has them."""
METHOD_SECTIONS: tuple[str, ...] = tuple(S.METHODS)
SECTION_TITLES = {
    "verdict": "Verdict",
    "summary": "Summary",
    "batteries": "Batteries",
    "switches": "Switches",
    "power": "State of power",
    "events": "Events",
    "controllers": "Other channels",
    "can": "CAN bus",
    **{k: title for k, (title, _) in S.METHODS.items()},
}
MAX_EVENT_ROWS = 1000
"""Events listed in the table at most; rare kinds are kept first (see ``select_events``)."""


def severity_of(kind: str) -> Severity:
    return row_of(kind).severity


# --------------------------------------------------------------------------- sections


def select_events(events: Sequence[Event], limit: int = MAX_EVENT_ROWS) -> list[int]:
    """Indices of the events to list: every kind gets a fair share, rare kinds in full.

    A long run can log thousands of routine events (state changes); a trip or a fault must
    not disappear behind them, so the budget is shared out from the rarest kind up.
    """
    if len(events) <= limit:
        return list(range(len(events)))
    by_kind: dict[str, list[int]] = {}
    for i, e in enumerate(events):
        by_kind.setdefault(e.kind, []).append(i)
    chosen: list[int] = []
    left = limit
    kinds = sorted(by_kind, key=lambda k: len(by_kind[k]))
    for j, k in enumerate(kinds):
        share = left // (len(kinds) - j)
        chosen.extend(by_kind[k][:share])
        left -= min(share, len(by_kind[k]))
    return sorted(chosen)


def _verdict(verdict: Verdict) -> str:
    """The verdict and the alarms table: the first thing a reader sees."""
    word = verdict.word
    head = (
        f'<p class="verdict {esc(word.lower())}" id="verdict-word">{esc(word)}</p>'
        + ("" if verdict.alarms else '<p class="note">No warning, alarm or fault: the events'
           " and the physics checks (over-discharge, cross-charge, load loss) are clean.</p>")
    )  # fmt: skip
    if not verdict.alarms:
        return head
    rows = [
        (
            f"{fmt_num(a.t_s)} s ({fmt_time(a.t_s)})",
            a.battery or "pack",
            f'<span class="sev {a.severity.label}">{esc(a.severity.label)}</span>',
            esc(a.kind) + (f" ×{a.count}" if a.count > 1 else ""),
            esc(a.cause),
            "no" if a.cleared_t_s is None else f"yes, at {fmt_num(a.cleared_t_s)} s",
            esc(a.source),
        )
        for a in verdict.alarms
    ]
    header = ("first at", "battery", "severity", "what", "cause", "cleared?", "from")
    return head + table(header, rows, cls="alarms", raw=True)


def _kpis(
    result: Result, digest: RunDigest, verdict: Verdict, soc_end: list[tuple[float, str]]
) -> str:
    """The headline numbers, as tiles: what a reader checks before anything else."""
    m = result.metrics
    span = digest.span_s
    n_alarm = sum(1 for a in verdict.alarms if a.severity >= Severity.ALARM)
    n_warn = sum(1 for a in verdict.alarms if a.severity == Severity.WARNING)
    tiles: list[tuple[str, str, str]] = [
        (verdict.word, "verdict", verdict.word.lower()),
        (f"{n_alarm} / {n_warn}", "alarms / warnings", "alarm" if n_alarm else
         ("warning" if n_warn else "ok")),
        (fmt_time(span), "simulated time", ""),
    ]  # fmt: skip

    def tile(key: str, label: str, unit: str, scale: float = 1.0) -> None:
        v = m.get(key)
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(float(v)):
            tiles.append((f"{fmt_num(float(v) * scale)} {unit}".strip(), label, ""))

    tile("energy_out_wh", "energy to the load", "Wh")
    tile("energy_in_wh", "energy from the charger", "Wh")
    tile("min_cell_v", "lowest cell voltage", "V")
    tile("max_cell_v", "highest cell voltage", "V")
    tile("max_temp_c", "hottest cell", "°C")
    tile("peak_cross_current_a", "peak cross current", "A")
    tile("load_unsupplied_s", "load unsupplied", "s")
    for name, (x, src) in zip(result.battery_names, soc_end, strict=False):
        if math.isfinite(float(x)):
            tiles.append((f"{fmt_num(100.0 * float(x))} %",
                          f"SOC of {name} at the end ({SOC_SHORT[src]})", ""))  # fmt: skip
    tiles.append((f"{len(result.events):,}", "events", ""))
    body = "".join(
        f'<div class="kpi {esc(cls)}"><div class="v">{esc(v)}</div><div class="k">{esc(k)}'
        "</div></div>"
        for v, k, cls in tiles
    )
    return f'<div class="kpis" id="kpis">{body}</div>'


def core_soc_end(page: S.Page) -> list[tuple[float, str]]:
    """Per battery: the last SOC the core used in the run and its source then
    (``contract/soc_source.py``; NaN and "battery" when nothing was recorded)."""
    out: list[tuple[float, str]] = []
    for b in range(len(page.names)):
        soc, codes = page.core_soc(b)
        ok = np.flatnonzero(np.isfinite(soc))
        k = int(ok[-1]) if ok.size else -1
        out.append((float(soc[k]), SOURCES[int(codes[k])]) if k >= 0 else (math.nan, BATTERY))
    return out


def _summary(
    result: Result, info: RunInfo, verdict: Verdict, digest: RunDigest, page: S.Page
) -> str:
    n_s = digest.n
    names = result.battery_names
    roles = info.roles(names)
    span = digest.span_s
    dt = digest.dt_median() if n_s > 1 else math.nan
    bats = ", ".join(
        n + (" (aux)" if r == "aux" else "") for n, r in zip(names, roles, strict=True)
    )
    ctrl = ", ".join(info.controllers()) or ("none" if info.config is not None else "unknown")
    rows = [
        ("configuration", info.config_name or "–"),
        ("run id", "–" if result.run_id is None else str(result.run_id)),
        ("status", info.status or "–"),
        ("started", fmt_date(info.started_at)),
        ("finished", fmt_date(info.finished_at)),
        ("source", info.source or "–"),
        ("batteries", bats or "–"),
        ("controllers", ctrl),
        ("samples", f"{n_s:,}" + (f" (every {fmt_num(dt)} s)" if math.isfinite(dt) else "")),
        ("time span", f"{fmt_num(span)} s ({fmt_time(span)})"),
        ("events", str(len(result.events))),
    ]
    if info.versions:
        rows.append(("versions", ", ".join(f"{k} {v}" for k, v in info.versions.items())))
    run_tbl = table(None, rows, cls="kv")

    n_b = len(names)
    scalar_rows: list[tuple[str, str, str, str]] = []
    per_battery: list[tuple[str, list[Any]]] = []
    for key, v in result.metrics.items():
        if key in ("battery_names", "events"):
            continue  # the names head the battery table; events have their own section
        if key == "final_soc" and isinstance(v, list):
            continue  # the battery table's "SOC at end"
        if isinstance(v, list) and len(v) == n_b and n_b > 1:
            per_battery.append((key, v))
            continue
        scalar_rows.append((key, metric_value(key, v), metric_unit(key), METRIC_DOC.get(key, "")))
    if result.build_time_s > 0:
        key = "build_time_s"
        scalar_rows.append(
            (key, metric_value(key, result.build_time_s), metric_unit(key), METRIC_DOC[key])
        )
    metrics_tbl = (
        table(("metric", "value", "unit", "meaning"), scalar_rows, cls="metrics")
        if scalar_rows
        else '<p class="note">No metrics recorded (the run did not finish).</p>'
    )
    batt_tbl = _battery_table(result, info, digest, per_battery, core_soc_end(page))
    cfg = ""
    if info.config is not None:
        text = json.dumps(info.config, indent=2, default=str)
        cfg = (
            "<details><summary>Scenario configuration (JSON)</summary>"
            f"<pre>{esc(text)}</pre></details>"
        )
    warn = ""
    if info.status not in (None, "ok"):
        warn = (
            f'<p class="warn">This run ended with status <strong>{esc(info.status)}</strong>:'
            " it did not finish normally (it failed, or its process stopped while recording),"
            " so what follows covers only what was recorded.</p>"
        )
    if digest.decimated:
        warn += (
            f'<p class="note" id="decimated">Charts decimated: {digest.decimated:,} points per'
            " bucket, min/max kept (and the switch and status changes, up to"
            f" {DECIMATED_CHANGES} per bucket in all, rarest first): {len(result.trace.t_s):,}"
            f" of {n_s:,} samples."
            " The verdict, the summary, the per-battery and switch tables and the events count"
            " every sample; the method sections' figures are computed from the charted"
            " samples.</p>"
        )
    return (
        warn
        + _kpis(result, digest, verdict, core_soc_end(page))
        + '<div class="cols"><div><h3>Run</h3>'
        + run_tbl
        + "</div><div><h3>Metrics</h3>"
        + metrics_tbl
        + "</div></div><h3>Per battery</h3>"
        + batt_tbl
        + cfg
    )


def _battery_table(
    result: Result, info: RunInfo, digest: RunDigest, extra: list[tuple[str, list[Any]]],
    soc_end: list[tuple[float, str]],
) -> str:  # fmt: skip
    """Per battery figures over every sample (from the digest: a long run is never held)."""
    names = result.battery_names
    if digest.n == 0:
        return '<p class="note">No samples recorded.</p>'
    ext = digest.extreme
    roles = info.roles(names)
    kinds = info.switch_kinds(names)
    rows: list[tuple[str, ...]] = []
    if any(r is not None for r in roles):
        rows.append(("role", *[r or "–" for r in roles]))
    if any(k is not None for k in kinds):
        rows.append(("switch", *[k or "–" for k in kinds]))
    out_ah, in_ah = digest.charge_ah()
    if soc_end:
        rows.append(("SOC the BMS used at end (%)", *[fmt_num(100 * x) for x, _ in soc_end]))
        rows.append(("... from", *[SOC_LABELS[src] for _, src in soc_end]))
    stats: list[tuple[str, list[float]]] = [
        ("true SOC at start (%, plant)", [100 * x for x in ext("soc_first")]),
        ("true SOC at end (%, plant)", [100 * x for x in ext("soc_last")]),
        ("voltage min (V)", ext("v_min")),
        ("voltage max (V)", ext("v_max")),
        ("cell voltage min (V)", ext("cmin")),
        ("cell voltage max (V)", ext("cmax")),
        ("peak discharge current (A)", [max(0.0, x) for x in ext("i_max")]),
        ("peak charge current (A)", [max(0.0, -x) for x in ext("i_min")]),
        ("charge out (Ah)", out_ah),
        ("charge in (Ah)", in_ah),
        ("max temperature (°C)", ext("temp_max")),
    ]
    rows += [(label, *[fmt_num(x) for x in vals]) for label, vals in stats]
    for key, vals in extra:
        unit = metric_unit(key)
        rows.append((key + (f" ({unit})" if unit else ""), *[metric_value(key, x) for x in vals]))
    return table(("", *names), rows, cls="battery")


def _events(result: Result, info: RunInfo) -> str:
    events = result.events
    if not events:
        return '<p class="note">No events were recorded in this run.</p>'
    names = info.event_names(result.battery_names)
    parts: list[str] = []
    counts = Counter(e.kind for e in events)
    first: dict[str, float] = {}
    for e in events:
        first.setdefault(e.kind, e.t_s)
    parts.append(
        table(
            ("kind", "severity", "count", "first at (s)"),
            [(k, severity_of(k).label, str(n), fmt_num(first[k])) for k, n in counts.items()],
            cls="counts",
        )
    )
    chosen = select_events(events)
    if len(chosen) < len(events):
        parts.append(
            f'<p class="note">Listing {len(chosen):,} of {len(events):,} events: every kind'
            " gets a share, rare kinds are listed in full. The telemetry database holds them"
            " all.</p>"
        )

    def who(b: int | None) -> str:
        if b is None:
            return "pack"
        return names[b] if 0 <= b < len(names) else str(b)

    rows = [
        (
            fmt_num(events[i].t_s),
            fmt_time(events[i].t_s),
            events[i].kind,
            who(events[i].battery),
            events[i].message,
            fmt_data(events[i].data),
        )
        for i in chosen
    ]
    parts.append(
        '<div class="scroll">'
        + table(("t (s)", "t (h:mm:ss)", "kind", "battery", "message", "data"), rows, cls="events")
        + "</div>"
    )
    return "".join(parts)


# --------------------------------------------------------------------------- page

_CSS = """
:root { --fg: #1d2330; --muted: #5b6475; --line: #d9dde5; --accent: #1f5fa8; --bg2: #f4f6f9; }
* { box-sizing: border-box; }
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, "DejaVu Sans", sans-serif;
       color: var(--fg); margin: 0; background: #fff; }
header { background: var(--bg2); border-bottom: 1px solid var(--line); padding: 1rem 1.5rem; }
header h1 { margin: 0 0 .2rem; font-size: 1.5rem; }
header .sub { margin: 0; color: var(--muted); overflow-wrap: anywhere; }
nav { margin-top: .6rem; display: flex; flex-wrap: wrap; gap: .4rem 1rem; }
nav a { color: var(--accent); text-decoration: none; font-weight: 600; }
main { max-width: 1040px; margin: 0 auto; padding: 0 1.5rem 2rem; }
section { border-bottom: 1px solid var(--line); padding: 1rem 0 1.5rem; }
h2 { font-size: 1.25rem; margin: .6rem 0 .6rem; }
h3 { font-size: 1.02rem; margin: 1rem 0 .4rem; }
table { border-collapse: collapse; margin: .4rem 0 .8rem; font-size: .86rem; }
th, td { border: 1px solid var(--line); padding: .22rem .5rem; text-align: left;
         vertical-align: top; }
th { background: var(--bg2); }
tbody tr:nth-child(even) { background: #fafbfc; }
table.metrics td:nth-child(2), table.battery td:not(:first-child), table.counts td:nth-child(n+2)
  { text-align: right; font-variant-numeric: tabular-nums; }
table.battery td:first-child, table.kv td:first-child { font-weight: 600; white-space: nowrap; }
table.events td { font-size: .8rem; }
table.events td:last-child { font-family: ui-monospace, "DejaVu Sans Mono", monospace;
                             font-size: .74rem; word-break: break-word; }
.scroll { max-height: 28rem; overflow: auto; border: 1px solid var(--line); }
.scroll table { margin: 0; width: 100%; }
.cols { display: flex; flex-wrap: wrap; gap: 0 2rem; }
.chart { margin: .5rem 0 .9rem; }
.ctitle { font-weight: 600; font-size: .9rem; margin-bottom: .1rem; }
.cap { color: var(--muted); font-size: .82rem; margin: .1rem 0 0; }
.plot .u-legend { font-size: .78rem; text-align: left; }
.plot .u-legend .u-series { padding: 0 .4rem 0 0; }
.zoombar { position: sticky; top: 0; z-index: 5; background: #fffffff0; border-bottom: 1px solid
           var(--line); padding: .3rem 1.5rem; font-size: .85rem; color: var(--muted); }
.zoombar button { font: inherit; margin-left: .6rem; padding: .05rem .6rem; cursor: pointer; }
.kpis { display: grid; grid-template-columns: repeat(auto-fill, minmax(150px, 1fr));
        gap: .5rem; margin: .4rem 0 1rem; }
.kpi { border: 1px solid var(--line); border-radius: .4rem; padding: .4rem .6rem;
       background: var(--bg2); }
.kpi .v { font-size: 1.25rem; font-weight: 700; font-variant-numeric: tabular-nums; }
.kpi .k { font-size: .78rem; color: var(--muted); }
.kpi.alarm .v, .kpi.fault .v { color: #b3261e; }
.kpi.warning .v { color: #8a5a00; }
.kpi.ok .v { color: #135d27; }
ul.nominal { margin: .2rem 0 .6rem; padding-left: 1.2rem; font-size: .85rem; color: var(--muted);
             columns: 2 22rem; }
details { margin: .3rem 0 .8rem; }
details > summary { cursor: pointer; color: var(--accent); font-size: .9rem; }
table.figures td:nth-child(2) { text-align: right; font-variant-numeric: tabular-nums; }
span.ok { color: #135d27; font-weight: 600; }
span.bad { color: #b3261e; font-weight: 600; }
.note { color: var(--muted); font-style: italic; }
.warn { background: #fdf0d5; border-left: 4px solid #d08a00; padding: .4rem .7rem; }
.badge { display: inline-block; padding: 0 .45rem; border-radius: .6rem; font-size: .85rem;
         font-weight: 600; background: #e1e5eb; }
.runstate { color: var(--muted); font-size: .85rem; }
.badge.error, .badge.running, .badge.interrupted, .badge.stopped, .badge.aborted
  { background: #f8d9d6; color: #8a1c12; }
.badge.verdict-ok, .verdict.ok { background: #d6f0dc; color: #135d27; }
.badge.verdict-warning, .verdict.warning { background: #fdf0d5; color: #7a4d00; }
.badge.verdict-alarm, .badge.verdict-fault, .verdict.alarm, .verdict.fault
  { background: #f8d9d6; color: #8a1c12; }
.verdict { display: inline-block; font-size: 1.6rem; font-weight: 700; padding: .2rem 1rem;
           border-radius: .4rem; margin: .2rem 0 .6rem; }
.sev { font-weight: 600; }
.sev.fault, .sev.alarm { color: #b3261e; }
.sev.warning { color: #8a5a00; }
pre { background: var(--bg2); padding: .6rem; overflow: auto; font-size: .78rem; }
footer { color: var(--muted); font-size: .8rem; text-align: center; padding: 1rem; }
code { overflow-wrap: anywhere; }
/* a phone: the page never scrolls sideways; a wide table scrolls inside itself */
@media (max-width: 700px) {
  header, .zoombar { padding-left: .75rem; padding-right: .75rem; }
  main { padding: 0 .75rem 2rem; }
  table { display: block; max-width: 100%; overflow-x: auto; }
  .kpis { grid-template-columns: repeat(auto-fill, minmax(130px, 1fr)); }
  .u-legend { display: block; }
  .cols > div { min-width: 0; max-width: 100%; }
  table.alarms { display: block; }
  table.alarms thead { display: none; }
  table.alarms tr { display: block; border-bottom: 1px solid var(--line); padding: .3rem 0; }
  table.alarms td { display: inline-block; border: 0; padding: 0 .5rem 0 0; }
  table.alarms td:nth-child(5) { display: block; }
}
"""


def _version() -> str:
    try:
        return importlib.metadata.version("packpilot")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _asset(name: str) -> str:
    return resources.files("packpilot.report").joinpath("static", name).read_text(encoding="utf-8")


def _scripts(page: S.Page) -> str:
    """uPlot (with its licence), the chart data and the chart script, all inline."""
    data = {
        "t": page.tkey,
        "span": [float(page.t[0]), float(page.t[-1])] if len(page.t) else [0.0, 1.0],
        "store": page.store.data,
        "charts": {cid: c.spec() for cid, c in page.charts.items()},
    }
    text = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    licence = _asset("uplot/LICENSE").replace("*/", "* /")
    return (
        f"<style>{_asset('uplot/uPlot.min.css')}</style>"
        f"<script>/* uPlot, bundled unmodified. {licence} */\n{_asset('uplot/uPlot.iife.min.js')}"
        "</script>"
        f'<script type="application/json" id="pp-data">{text}</script>'
        f"<script>{_asset('report.js')}</script>"
    )


def _alarm_marks(verdict: Verdict) -> list[tuple[float, str, str]]:
    return [
        (a.t_s, ALARM_COLOR if a.severity >= Severity.ALARM else S.WARN_COLOR,
         f"{a.kind} {a.battery or 'pack'}")
        for a in verdict.alarms
        if math.isfinite(a.t_s)
    ]  # fmt: skip


def _sections(result: Result, info: RunInfo, verdict: Verdict, page: S.Page) -> dict[str, str]:
    """Every section's body, in page order."""
    page.marks.extend(_alarm_marks(verdict))
    body = {"verdict": _verdict(verdict),
            "summary": _summary(result, info, verdict, page.digest, page)}  # fmt: skip
    for key, (_, build) in S.METHODS.items():
        if info.enabled(key):
            body[key] = build(page)
    body["batteries"] = S.batteries(page)
    body["switches"] = S.switches(page)
    power = S.power(page)
    if power:
        body["power"] = power
    body["events"] = _events(result, info)
    body["controllers"] = S.controllers(page)
    can_html, can_charts = can_section(info.can_log_path(), page.store)
    if can_html:
        body["can"] = can_html + "".join(page.chart(c) for c in can_charts)
    return body


def _run_meta(info: RunInfo, result: Result) -> str:
    """``<meta name="packpilot-run" content="demo.sqlite#1">`` when the run is recorded: the
    dashboard opening that recording finds this page by it, whatever the page is called."""
    if info.db is None or result.run_id is None:
        return ""
    return f'<meta name="packpilot-run" content="{esc(Path(info.db).name)}#{result.run_id}">'


def build_html(result: Result, info: RunInfo | None = None, digest: RunDigest | None = None) -> str:
    """The whole report page as one string. ``digest``: the figures of every sample when
    ``result`` carries a decimated trace (:func:`report_from_db` of a long run); without it
    they are computed from ``result`` itself."""
    info = info or RunInfo()
    digest = digest or RunDigest.of_result(result, info.config)
    verdict = digest.verdict()
    page = S.Page(result, info, digest)
    body = _sections(result, info, verdict, page)
    name = info.config_name or "run"
    run = f"run {result.run_id}" if result.run_id is not None else "in-memory run"
    status = info.status or "unknown"
    word = verdict.word
    badge = f'<span class="badge verdict-{esc(word.lower())}" title="verdict">{esc(word)}</span>'
    # The verdict says how the run went; a run that completed needs no second badge (a
    # coloured "run ok" beside a WARNING reads as a contradiction). Only a run that did not
    # complete says so, in red.
    if status == "ok":
        badge += ' <span class="runstate" title="run status">run completed</span>'
    else:
        badge += f' <span class="badge {esc(status)}" title="run status">run {esc(status)}</span>'
    when = fmt_date(info.started_at) if info.started_at else ""
    sub = " · ".join(x for x in (esc(name), esc(run), badge, esc(when)) if x)
    nav = "".join(f'<a href="#{s}">{esc(SECTION_TITLES[s])}</a>' for s in body)
    sections = "".join(
        f'<section id="{s}"><h2>{esc(SECTION_TITLES[s])}</h2>{html}</section>'
        for s, html in body.items()
    )
    zoom = (
        '<div class="zoombar">Charts: drag across one to zoom, wheel to zoom around the cursor,'
        ' double-click to go back; they move together. Showing: <strong data-range="run">whole'
        ' run</strong><button type="button" data-reset="run">reset zoom</button></div>'
        if page.charts
        else ""
    )
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        f"{_run_meta(info, result)}"
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>PackPilot report: {esc(name)} ({esc(run)})</title>"
        f"<style>{_CSS}</style></head>\n<body>"
        f'<header><h1>PackPilot run report</h1><p class="sub">{sub}</p>'
        f"<nav>{nav}</nav></header>\n{zoom}<main>{sections}</main>\n"
        f"<footer>Generated by PackPilot {esc(_version())} on {now}. Self-contained: the charts"
        " (uPlot, MIT licence) and their data are embedded, nothing is loaded from the"
        f" network.</footer>{_scripts(page)}</body></html>\n"
    )


def check_report_path(out_path: Path | str) -> Path:
    """Refuse a report path that cannot be written, before any work is done."""
    out = Path(out_path)
    if out.suffix.lower() not in (".html", ".htm"):
        raise InputError(f"{out}: report file must end in .html")
    if not out.parent.is_dir():
        raise InputError(f"{out}: directory {out.parent} does not exist")
    if out.is_dir():
        raise InputError(f"{out}: is a directory")
    return out


def write_report(
    result: Result,
    out_path: Path | str,
    info: RunInfo | None = None,
    digest: RunDigest | None = None,
) -> Path:
    """Write the report of an in-memory run (``simulate --report``)."""
    out = check_report_path(out_path)
    page = build_html(result, info, digest)
    try:
        out.write_text(page, encoding="utf-8")
    except OSError as err:
        raise InputError(f"{out}: cannot write report ({err.strerror})") from err
    return out


def report_from_db(
    db_path: Path | str,
    out_path: Path | str,
    run_id: int | None = None,
    can_log: Path | str | None = None,
) -> Path:
    """Write the report of a recorded run (latest by default): ``packpilot report``; with
    ``can_log``, its CAN section reads that log (else the one the run's config names)."""
    import dataclasses

    from packpilot.report.stream import read_run

    check_report_path(out_path)
    if can_log is not None and not Path(can_log).is_file():
        raise InputError(f"--can-log {can_log}: no such file")
    result, digest = read_run(db_path, run_id)
    info = run_info_from_db(db_path, result.run_id)
    if can_log is not None:
        info = dataclasses.replace(info, can_log=str(can_log))
    return write_report(result, out_path, info, digest)


__all__ = [
    "METHOD_SECTIONS",
    "SECTION_IDS",
    "RunInfo",
    "build_html",
    "check_report_path",
    "fmt_num",
    "report_from_db",
    "run_info_from_db",
    "select_events",
    "write_report",
]
