"""The single-file HTML run report: summary, events, batteries, switches, protection, controllers.

One file that opens anywhere, offline, years later: figures are inline base64 PNGs, the CSS is
inline, there is no external URL and no script is needed to see anything (one tiny inline
script only marks, after ``load``, how many images decoded, for the browser test). Built from a
:class:`Result`, so ``simulate --report`` needs no database and ``report`` reads one with
``load_run``. Long runs are downsampled for plotting (see ``report/downsample.py``) and the
event table is capped, so a 10-hour run still makes a small file quickly.
"""

from __future__ import annotations

import datetime as _dt
import html
import importlib.metadata
import json
import math
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

from packpilot.config import SUPERVISED
from packpilot.contract.bms import Event
from packpilot.contract.record import Result
from packpilot.contract.topology import Topology
from packpilot.errors import InputError
from packpilot.report import figures as F
from packpilot.report.plots import figure_png_base64
from packpilot.sim.verdict import Verdict, run_verdict

SECTION_IDS: tuple[str, ...] = (
    "verdict",
    "summary",
    "events",
    "batteries",
    "switches",
    "protection",
    "controllers",
)
SECTION_TITLES = {
    "verdict": "Verdict",
    "summary": "Summary",
    "events": "Events",
    "batteries": "Batteries",
    "switches": "Switches",
    "protection": "Protection",
    "controllers": "Controllers",
}
MAX_EVENT_ROWS = 1000
"""Events listed in the table at most; rare kinds are kept first (see ``select_events``)."""
MAX_TRANSITION_ROWS = 300
DPI = 96


# --------------------------------------------------------------------------- run information


@dataclass(frozen=True)
class RunInfo:
    """What the report says about a run beyond its ``Result``: where it came from, its config."""

    config_name: str | None = None
    status: str | None = None
    started_at: str | None = None
    finished_at: str | None = None
    source: str | None = None
    config: Mapping[str, Any] | None = None
    versions: Mapping[str, str] = field(default_factory=dict)

    @classmethod
    def from_config(cls, config: Mapping[str, Any], **kw: Any) -> RunInfo:
        """From a scenario config as a JSON-able dict (``cfg.model_dump(mode="json")``)."""
        pack = config.get("pack")
        name = pack.get("name") if isinstance(pack, Mapping) else None
        return cls(config_name=kw.pop("config_name", name), config=config, **kw)

    def _batteries(self) -> list[Mapping[str, Any]]:
        pack = (self.config or {}).get("pack")
        bats = pack.get("batteries") if isinstance(pack, Mapping) else None
        return [b for b in bats if isinstance(b, Mapping)] if isinstance(bats, list) else []

    def roles(self, names: Sequence[str]) -> list[str | None]:
        by_name = {b.get("name"): b.get("role", "traction") for b in self._batteries()}
        return [by_name.get(n) for n in names]

    def switch_kinds(self, names: Sequence[str]) -> list[str | None]:
        """Each battery's switch kind (its own ``switch`` or the pack default), None if unknown."""
        pack = (self.config or {}).get("pack")
        default = None
        if isinstance(pack, Mapping):
            sw = pack.get("switch")
            default = sw.get("kind", "mosfet_pair") if isinstance(sw, Mapping) else "mosfet_pair"
        kinds: dict[Any, str | None] = {}
        for b in self._batteries():
            sw = b.get("switch")
            kinds[b.get("name")] = sw.get("kind") if isinstance(sw, Mapping) else default
        return [kinds.get(n) for n in names]

    def event_batteries(self, names: Sequence[str]) -> list[int]:
        """Trace index of each ``Event.battery`` value: events count traction batteries only."""
        return list(Topology.of_config(self.config, names).traction)

    def event_names(self, names: Sequence[str]) -> list[str]:
        """Names for ``Event.battery`` values (the aux battery has no index of its own)."""
        return [names[i] for i in self.event_batteries(names)]

    def controllers(self) -> list[str]:
        cfg = self.config or {}
        out = [str(c) for c in cfg.get("controller") or []]
        out += [s for s in SUPERVISED if cfg.get(s) is not None]
        return out


def run_info_from_db(db_path: Path | str, run_id: int | None = None) -> RunInfo:
    """The ``runs`` row of a telemetry file (latest run when ``run_id`` is None)."""
    from packpilot.io.telemetry import list_runs

    runs = list_runs(db_path)
    if not runs:
        raise InputError(f"{db_path}: telemetry database holds no runs")
    row = runs[-1] if run_id is None else next((r for r in runs if r["id"] == run_id), None)
    if row is None:
        raise InputError(f"{db_path}: no run with id {run_id}")
    config = row["config"] if isinstance(row["config"], Mapping) else {}
    return RunInfo.from_config(
        config,
        status=row["status"],
        started_at=row["started_at"],
        finished_at=row["finished_at"],
        source=str(db_path),
        versions=row["versions"] if isinstance(row["versions"], Mapping) else {},
    )


# --------------------------------------------------------------------------- formatting


def esc(x: Any) -> str:
    return html.escape(str(x), quote=True)


def fmt_num(v: Any) -> str:
    """Numbers as a person reads them: 4 significant digits, no exponent for everyday sizes."""
    if isinstance(v, bool) or v is None:
        return str(v)
    if isinstance(v, int | np.integer):
        return f"{int(v):,}"
    if isinstance(v, float | np.floating):
        f = float(v)
        if math.isnan(f) or math.isinf(f):
            return str(f)
        a = abs(f)
        if a == 0.0:
            return "0"
        if a >= 1e7 or a < 1e-3:
            return f"{f:.3e}"
        if a >= 1e4:
            return f"{f:,.0f}"
        return f"{f:.4g}"
    return str(v)


def fmt_time(t_s: float) -> str:
    if not math.isfinite(t_s):
        return "–"
    sign = "-" if t_s < 0 else ""
    t = round(abs(t_s), 1)  # 299.99999 s (1500 steps of 0.2 s) reads 0:05:00.0, not 0:04:60.0
    h, rem = divmod(t, 3600.0)
    m, s = divmod(rem, 60.0)
    return f"{sign}{int(h)}:{int(m):02d}:{s:04.1f}"


def fmt_date(iso: str | None) -> str:
    if not iso:
        return "–"
    try:
        d = _dt.datetime.fromisoformat(iso)
    except ValueError:
        return iso
    if d.tzinfo is not None:
        d = d.astimezone(_dt.UTC)
        return d.strftime("%Y-%m-%d %H:%M:%S UTC")
    return d.strftime("%Y-%m-%d %H:%M:%S")


def fmt_data(data: Mapping[str, Any]) -> str:
    parts = []
    for k, v in data.items():
        if isinstance(v, float | int) and not isinstance(v, bool):
            text = fmt_num(v)
        elif isinstance(v, Mapping | list | tuple):
            text = json.dumps(v, default=str)
        else:
            text = str(v)
        parts.append(f"{k}={text}")
    return ", ".join(parts)


METRIC_DOC: dict[str, str] = {
    "sim_time_s": "simulated time",
    "wall_time_s": "wall-clock time of the simulation",
    "steps": "control steps",
    "energy_out_wh": "energy delivered to the load",
    "energy_in_wh": "energy taken from the charger",
    "min_cell_v": "lowest cell voltage of any battery",
    "max_cell_v": "highest cell voltage of any battery",
    "max_temp_c": "highest cell temperature",
    "peak_cross_current_a": "largest current one battery pushed into another",
    "joule_heat_j": "resistive heat in cells and switches",
    "load_unsupplied_s": "time the load did not get what it asked for",
    "final_soc": "state of charge at the end",
    "peak_string_current_a": "largest-magnitude battery current (+ = discharge)",
    "chg_diode_energy_j": "energy lost in the charge FET's body diode",
    "dsg_diode_energy_j": "energy lost in the discharge FET's body diode",
}


def metric_unit(key: str) -> str:
    if "soc" in key:
        return "%"
    return F.unit_of(key)


def metric_value(key: str, v: Any) -> str:
    if "soc" in key and isinstance(v, float):
        return fmt_num(100.0 * v)
    if isinstance(v, Mapping):
        return ", ".join(f"{k}: {fmt_num(x)}" for k, x in v.items()) or "none"
    if isinstance(v, list):
        return ", ".join(metric_value(key, x) for x in v)
    return fmt_num(v)


def table(
    header: Sequence[str] | None,
    rows: Iterable[Sequence[str]],
    *,
    cls: str = "",
    raw: bool = False,
) -> str:
    """An HTML table (no head row when ``header`` is None); cells escaped unless ``raw``."""
    cell = (lambda s: s) if raw else esc
    head = (
        "<thead><tr>" + "".join(f"<th>{esc(h)}</th>" for h in header) + "</tr></thead>"
        if header is not None
        else ""
    )
    body = "".join("<tr>" + "".join(f"<td>{cell(c)}</td>" for c in r) + "</tr>" for r in rows)
    c = f' class="{cls}"' if cls else ""
    return f"<table{c}>{head}<tbody>{body}</tbody></table>"


def img(fig: Figure, alt: str, caption: str = "") -> str:
    """A figure as an inline PNG (data URI) with its pixel size, so the layout never jumps."""
    w, h = (fig.get_size_inches() * DPI).round().astype(int)
    data = figure_png_base64(fig, dpi=DPI)
    cap = f"<figcaption>{esc(caption)}</figcaption>" if caption else ""
    return (
        f'<figure><img src="data:image/png;base64,{data}" alt="{esc(alt)}" width="{w}"'
        f' height="{h}">{cap}</figure>'
    )


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


def _summary(result: Result, info: RunInfo) -> str:
    tr = result.trace
    n_s = len(tr.t_s)
    names = result.battery_names
    roles = info.roles(names)
    span = float(tr.t_s[-1] - tr.t_s[0]) if n_s > 1 else 0.0
    dt = float(np.median(np.diff(tr.t_s))) if n_s > 1 else math.nan
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
    metrics_tbl = (
        table(("metric", "value", "unit", "meaning"), scalar_rows, cls="metrics")
        if scalar_rows
        else '<p class="note">No metrics recorded (the run did not finish).</p>'
    )
    batt_tbl = _battery_table(result, info, per_battery)
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
    return (
        warn
        + '<div class="cols"><div><h3>Run</h3>'
        + run_tbl
        + "</div><div><h3>Metrics</h3>"
        + metrics_tbl
        + "</div></div><h3>Per battery</h3>"
        + batt_tbl
        + cfg
    )


def _battery_table(result: Result, info: RunInfo, extra: list[tuple[str, list[Any]]]) -> str:
    tr = result.trace
    names = result.battery_names
    if len(tr.t_s) == 0:
        return '<p class="note">No samples recorded.</p>'
    t = tr.t_s
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2] if len(t) > 1 else 0.0))

    def col(name: str) -> NDArray[np.float64]:
        return tr.channel(name)

    def nanext(f: Any, x: NDArray[np.float64]) -> float:
        return float(f(x)) if np.isfinite(x).any() else math.nan

    def first_finite(x: NDArray[np.float64]) -> float:
        f = x[np.isfinite(x)]
        return float(f[0]) if f.size else math.nan

    def last_finite(x: NDArray[np.float64]) -> float:
        f = x[np.isfinite(x)]
        return float(f[-1]) if f.size else math.nan

    cur, soc, v = col("current_a"), col("soc"), col("voltage_v")
    roles = info.roles(names)
    kinds = info.switch_kinds(names)
    rows: list[tuple[str, ...]] = []
    if any(r is not None for r in roles):
        rows.append(("role", *[r or "–" for r in roles]))
    if any(k is not None for k in kinds):
        rows.append(("switch", *[k or "–" for k in kinds]))
    n = len(names)
    out_ah = [float(np.nansum(np.clip(cur[:, b], 0, None) * dt)) / 3600.0 for b in range(n)]
    in_ah = [float(np.nansum(np.clip(-cur[:, b], 0, None) * dt)) / 3600.0 for b in range(n)]
    stats: list[tuple[str, list[float]]] = [
        ("SOC at start (%)", [100 * first_finite(soc[:, b]) for b in range(n)]),
        ("SOC at end (%)", [100 * last_finite(soc[:, b]) for b in range(n)]),
        ("voltage min (V)", [nanext(np.nanmin, v[:, b]) for b in range(n)]),
        ("voltage max (V)", [nanext(np.nanmax, v[:, b]) for b in range(n)]),
        ("cell voltage min (V)", [nanext(np.nanmin, col("min_cell_v")[:, b]) for b in range(n)]),
        ("cell voltage max (V)", [nanext(np.nanmax, col("max_cell_v")[:, b]) for b in range(n)]),
        ("peak discharge current (A)", [max(0.0, nanext(np.nanmax, cur[:, b])) for b in range(n)]),
        ("peak charge current (A)", [max(0.0, -nanext(np.nanmin, cur[:, b])) for b in range(n)]),
        ("charge out (Ah)", out_ah),
        ("charge in (Ah)", in_ah),
        ("max temperature (°C)", [nanext(np.nanmax, col("temp_c")[:, b]) for b in range(n)]),
    ]
    rows += [(label, *[fmt_num(x) for x in vals]) for label, vals in stats]
    for key, vals in extra:
        unit = metric_unit(key)
        rows.append((key + (f" ({unit})" if unit else ""), *[metric_value(key, x) for x in vals]))
    return table(("", *names), rows, cls="battery")


def _events(result: Result, axis: F.TimeAxis, info: RunInfo) -> str:
    events = result.events
    if not events:
        return '<p class="note">No events were recorded in this run.</p>'
    names = info.event_names(result.battery_names)
    parts: list[str] = []
    fig = F.events_figure(result, axis, names, info.event_batteries(result.battery_names))
    if fig is not None:
        parts.append(img(fig, "events over time by kind", "Each mark is one event."))
    counts = Counter(e.kind for e in events)
    first: dict[str, float] = {}
    for e in events:
        first.setdefault(e.kind, e.t_s)
    parts.append(
        table(
            ("kind", "count", "first at (s)"),
            [(k, str(n), fmt_num(first[k])) for k, n in counts.items()],
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


_NO_SAMPLES = '<p class="note">No samples were recorded in this run.</p>'


def _batteries(result: Result, axis: F.TimeAxis, info: RunInfo) -> str:
    if len(result.trace.t_s) == 0:
        return _NO_SAMPLES
    roles = info.roles(result.battery_names)
    apart = [b for b, r in enumerate(roles) if r == "aux"]
    fig = F.batteries_figure(result, axis, apart)
    return img(
        fig,
        "battery voltage, current, SOC, temperature and cell voltage range",
        "Battery terminal voltage with the bus (dashed)"
        + ("; the auxiliary battery in its own panel" if apart else "")
        + "; current, + = discharge, with the load and the charger; SOC; the hottest cell's"
        " temperature; highest (solid) and lowest (dashed) cell voltage of each battery.",
    )


def _switches(result: Result, axis: F.TimeAxis, info: RunInfo) -> str:
    tr = result.trace
    if len(tr.t_s) == 0:
        return _NO_SAMPLES
    names = result.battery_names
    kinds = info.switch_kinds(names) if info.config is not None else None
    fig = F.switches_figure(result, axis, kinds)
    parts = [
        img(
            fig,
            "switch states per battery",
            "Charge (CHG) and discharge (DSG) path of each battery as switched in the plant"
            " (welded or shorted parts count as on). Orange: current through a body diode.",
        )
    ]
    if len(tr.t_s):
        rows = []
        for b, name in enumerate(names):
            chg, dsg = tr.channel("chg_on")[:, b], tr.channel("dsg_on")[:, b]
            rows.append(
                (
                    name,
                    fmt_num(100.0 * float(np.nanmean(chg > 0.5))),
                    fmt_num(100.0 * float(np.nanmean(dsg > 0.5))),
                    str(int(np.count_nonzero(np.diff(chg) != 0))),
                    str(int(np.count_nonzero(np.diff(dsg) != 0))),
                )
            )
        parts.append(
            table(
                (
                    "battery",
                    "CHG on (% of samples)",
                    "DSG on (% of samples)",
                    "CHG changes",
                    "DSG changes",
                ),
                rows,
                cls="counts",
            )
        )
    return "".join(parts)


def _protection(result: Result, channels: dict[str, F.StatusChannel], axis: F.TimeAxis) -> str:
    names = result.battery_names
    t = result.trace.t_s
    if not any(k in channels for k in ("protection_param", "protection_fraction")):
        return (
            '<p class="note">Active protection parameter: <strong>not recorded</strong>. This run'
            " has no <code>protection_param</code> / <code>protection_fraction</code> status"
            ' channels (add "protection" to <code>controller</code> to record them).</p>'
        )
    fig = F.protection_figure(channels, t, axis, names)
    parts = []
    if fig is not None:
        parts.append(
            img(
                fig,
                "active protection parameter per battery",
                "Active discharge-protection parameter (steps, left axis) and the used-up share"
                " of the allowance, sum(t_k / t_max_k) (dashed, right axis); red: tripped.",
            )
        )
    param = channels.get("protection_param")
    frac = channels.get("protection_fraction")
    if param is not None and len(t):
        t_end = float(t[-1]) + (float(t[-1] - t[-2]) if len(t) > 1 else 0.0)
        start = t[param.rows]
        dur = np.diff(np.append(start, t_end))
        rows = []
        for b in param.columns:
            per: dict[str, float] = {}
            for j, v in enumerate(param.column(b)):
                if v is not None:
                    per[str(v)] = per.get(str(v), 0.0) + float(dur[j])
            used = (
                fmt_num(100.0 * float(np.nanmax(frac.numeric(b))))
                if frac is not None and b in frac.columns
                else "–"
            )
            rows.append((names[b], ", ".join(f"{k}: {fmt_num(s)} s" for k, s in per.items()), used))
        parts.append(
            table(("battery", "time per parameter", "max allowance used (%)"), rows, cls="counts")
        )
    return "".join(parts)


def _transitions(
    channels: Mapping[str, F.StatusChannel], t: NDArray[np.float64], names: Sequence[str]
) -> tuple[list[tuple[str, ...]], int]:
    """(time, channel, battery, from, to) of every change of a label channel, first ones."""
    rows: list[tuple[float, str, str, str, str]] = []
    for name, ch in channels.items():
        if ch.kind != "label":
            continue
        lanes = [(ch.columns[0], "pack")] if ch.pack_level else [(b, names[b]) for b in ch.columns]
        for b, who in lanes:
            col = ch.column(b)
            for j in range(1, len(col)):
                if col[j] != col[j - 1]:
                    rows.append((float(t[ch.rows[j]]), name, who, str(col[j - 1]), str(col[j])))
    rows.sort(key=lambda r: r[0])
    shown: list[tuple[str, ...]] = [
        (fmt_num(r[0]), fmt_time(r[0]), *r[1:]) for r in rows[:MAX_TRANSITION_ROWS]
    ]
    return shown, len(rows)


def _controllers(result: Result, channels: dict[str, F.StatusChannel], axis: F.TimeAxis) -> str:
    names = result.battery_names
    t = result.trace.t_s
    others = {k: v for k, v in channels.items() if not k.startswith(F.PROTECTION_PREFIX)}
    if not others:
        return (
            '<p class="note">No other controller status channels were recorded (sequencing'
            " states, charging stage, equalization AH ... appear here when those controllers"
            " run).</p>"
        )
    panels = F.controller_panels(others, t, axis, names)
    parts = []
    for family, fam_panels in panels.items():
        parts.append(f"<h3>{esc(family)}</h3>")
        for k, fig in enumerate(F.panels_figures(fam_panels, axis)):
            parts.append(img(fig, f"{family} status channels" + (f" ({k + 1})" if k else "")))
    trans, total = _transitions(others, t, names)
    if trans:
        parts.append("<h3>State changes</h3>")
        if total > len(trans):
            parts.append(f'<p class="note">First {len(trans):,} of {total:,} changes.</p>')
        parts.append(
            '<div class="scroll">'
            + table(
                ("t (s)", "t (h:mm:ss)", "channel", "battery", "from", "to"), trans, cls="events"
            )
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
header .sub { margin: 0; color: var(--muted); }
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
figure { margin: .6rem 0 1rem; }
figure img { max-width: 100%; height: auto; display: block; border: 1px solid var(--line); }
figcaption { color: var(--muted); font-size: .85rem; margin-top: .25rem; }
.note { color: var(--muted); font-style: italic; }
.warn { background: #fdf0d5; border-left: 4px solid #d08a00; padding: .4rem .7rem; }
.badge { display: inline-block; padding: 0 .45rem; border-radius: .6rem; font-size: .85rem;
         font-weight: 600; background: #e1e5eb; }
.badge.ok { background: #e1e5eb; } /* the run completed: how it went is the verdict's */
.badge.error, .badge.running, .badge.interrupted { background: #f8d9d6; color: #8a1c12; }
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
"""

# Not needed to read the report: it records, once everything has loaded, how many images
# decoded (data-images-ok="decoded/total" on <body>), which the headless-browser test checks.
_SCRIPT = """
window.addEventListener("load", function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
  }
  document.body.setAttribute("data-images-ok", ok + "/" + imgs.length);
});
"""


def _version() -> str:
    try:
        return importlib.metadata.version("packpilot")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def build_html(result: Result, info: RunInfo | None = None) -> str:
    """The whole report page as one string."""
    info = info or RunInfo()
    axis = F.TimeAxis.of(result.trace.t_s)
    channels = F.status_channels(result)
    verdict = run_verdict(result, info.config)
    body = {
        "verdict": _verdict(verdict),
        "summary": _summary(result, info),
        "events": _events(result, axis, info),
        "batteries": _batteries(result, axis, info),
        "switches": _switches(result, axis, info),
        "protection": _protection(result, channels, axis),
        "controllers": _controllers(result, channels, axis),
    }
    name = info.config_name or "run"
    run = f"run {result.run_id}" if result.run_id is not None else "in-memory run"
    status = info.status or "unknown"
    badge = f'<span class="badge {esc(status)}" title="run status">run {esc(status)}</span>'
    word = verdict.word
    badge += f' <span class="badge verdict-{esc(word.lower())}">{esc(word)}</span>'
    when = fmt_date(info.started_at) if info.started_at else ""
    sub = " · ".join(x for x in (esc(name), esc(run), badge, esc(when)) if x)
    nav = "".join(f'<a href="#{s}">{esc(SECTION_TITLES[s])}</a>' for s in SECTION_IDS)
    sections = "".join(
        f'<section id="{s}"><h2>{esc(SECTION_TITLES[s])}</h2>{body[s]}</section>'
        for s in SECTION_IDS
    )
    now = _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en"><head><meta charset="utf-8">'
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        f"<title>PackPilot report: {esc(name)} ({esc(run)})</title>"
        f"<style>{_CSS}</style></head>\n<body>"
        f'<header><h1>PackPilot run report</h1><p class="sub">{sub}</p>'
        f"<nav>{nav}</nav></header>\n<main>{sections}</main>\n"
        f"<footer>Generated by PackPilot {esc(_version())} on {now}. Self-contained:"
        " plots are embedded, nothing is loaded from the network.</footer>"
        f"<script>{_SCRIPT}</script></body></html>\n"
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


def write_report(result: Result, out_path: Path | str, info: RunInfo | None = None) -> Path:
    """Write the report of an in-memory run (``simulate --report``)."""
    out = check_report_path(out_path)
    page = build_html(result, info)
    try:
        out.write_text(page, encoding="utf-8")
    except OSError as err:
        raise InputError(f"{out}: cannot write report ({err.strerror})") from err
    return out


def report_from_db(db_path: Path | str, out_path: Path | str, run_id: int | None = None) -> Path:
    """Write the report of a recorded run (latest by default): ``packpilot report``."""
    from packpilot.io.telemetry import load_run

    check_report_path(out_path)
    result = load_run(db_path, run_id)
    info = run_info_from_db(db_path, result.run_id)
    return write_report(result, out_path, info)


__all__ = [
    "SECTION_IDS",
    "RunInfo",
    "build_html",
    "check_report_path",
    "report_from_db",
    "run_info_from_db",
    "select_events",
    "write_report",
]
