"""The chart sections of the report: batteries, switches, one section per enabled method, and the
remaining controller channels (nominal ones in one line each).

Each method section leads with the figures the benchmarks judge that method by
(:mod:`packpilot.sim.quality`, the same functions), then the few charts that show them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.record import Result
from packpilot.contract.soc_source import BATTERY, COUNTER, FALLBACK, OBSERVER, SOURCES
from packpilot.report.channels import (
    StatusChannel,
    categories,
    core_soc,
    family_of,
    group_base,
    natural_key,
    nominal,
    status_channels,
)
from packpilot.report.charts import Chart, Series, Store, sample_indices, spans
from packpilot.report.digest import RunDigest
from packpilot.report.fmt import esc, fmt_num, fmt_time, table
from packpilot.report.info import RunInfo
from packpilot.report.style import ALARM_COLOR, battery_color, unit_of
from packpilot.sim import quality as Q

F64 = NDArray[np.float64]
DIODE_COLOR = "#ff9f1c"
WARN_COLOR = "#b07800"
PACK_COLOR = "#222222"


class Page:
    """One report being built: the run, its packed series and the charts drawn so far."""

    def __init__(self, result: Result, info: RunInfo, digest: RunDigest | None = None) -> None:
        self.result = result
        self.info = info
        self.digest = digest or RunDigest.of_result(result, info.config)
        """The figures of every sample (``result`` may carry a decimated trace)."""
        self.t = result.trace.t_s
        self.names = result.battery_names
        self.roles = info.roles(self.names)
        self.traction = [b for b, r in enumerate(self.roles) if r != "aux"]
        if self.digest.decimated:  # already thinned while it was read: draw what was kept
            idx = np.arange(len(self.t), dtype=np.intp)
        else:
            idx = sample_indices(result) if len(self.t) else np.zeros(0, np.intp)
        self.store = Store(idx)
        self.tkey = self.store.add("t", self.t, 1e-3) if len(self.t) else ""
        self.channels = status_channels(result)
        self.charts: dict[str, Chart] = {}
        self.shown: set[str] = set()
        """Status channels a method section already charts."""
        self.marks: list[tuple[float, str, str]] = []
        """Alarm first times, drawn on the battery charts."""

    # -- data ----------------------------------------------------------------------------
    def bat(self, name: str, b: int, q: float | None = None) -> str:
        return self.store.add(f"{name}/{b}", self.result.trace.channel(name)[:, b], q)

    def pack(self, name: str) -> str:
        return self.store.add(name, getattr(self.result.trace, name))

    def status(self, ch: StatusChannel, b: int, cats: Sequence[str] | None = None) -> str:
        """One battery's column of a status channel at every step (labels as category codes)."""
        if cats is not None:
            index = {c: i for i, c in enumerate(cats)}
            other = index.get("other", math.nan)
            col = np.array(
                [math.nan if v is None else index.get(str(v), other) for v in ch.column(b)],
                dtype=np.float64,
            )
            q: float | None = 1.0
        else:
            col = ch.numeric(b)
            q = None
        counts = np.diff(np.append(ch.rows, len(self.t)))
        return self.store.add(f"{ch.name}/{b}", np.repeat(col, counts), q)

    def status_at(self, name: str, k: int, b: int) -> object:
        """A status channel's value for battery ``b`` at step ``k`` (None when absent)."""
        ch = self.channels.get(name)
        if ch is None or b >= ch.values.shape[1]:
            return None
        j = int(np.searchsorted(ch.rows, k, side="right")) - 1
        return None if j < 0 else ch.values[j, b]

    def core_soc(self, b: int) -> tuple[F64, NDArray[np.int64]]:
        """The SOC the core used for battery ``b`` at every step and its source there
        (``report/channels.py:core_soc``)."""
        return core_soc(self.channels, len(self.t), b, self.result.trace.channel("soc")[:, b])

    # -- charts --------------------------------------------------------------------------
    def chart(self, chart: Chart, caption: str = "") -> str:
        """Register a chart; its placeholder (drawn by report.js)."""
        base, k = chart.id, 1
        while chart.id in self.charts:
            k += 1
            chart.id = f"{base}-{k}"
        self.charts[chart.id] = chart
        cap = f'<p class="cap">{esc(caption)}</p>' if caption else ""
        return (
            f'<div class="chart" data-chart="{esc(chart.id)}" style="min-height:'
            f'{chart.height + 60}px"><div class="ctitle">{esc(chart.title)}</div>'
            f'<div class="plot"></div>{cap}</div>'
        )

    def status_chart(self, ch: StatusChannel, title: str | None = None) -> Chart:
        """A chart of any status channel: states as named levels, numbers as lines."""
        lanes = ch.lanes()
        n = len(lanes)
        chart = Chart(f"st-{ch.name}", title or ch.name, unit_of(ch.name), height=140)
        cats: list[str] | None = None
        if ch.kind == "label":
            cats = categories(ch)
            if ch.name.endswith("_param"):
                cats = sorted(cats, key=natural_key)
        elif ch.kind == "bool":
            cats = ["false", "true"]
        if cats is not None:
            chart.categories = cats
            chart.height = max(110, 40 + 22 * len(cats))
        for k, b in enumerate(lanes):
            label = "pack" if ch.pack_level else self.names[b]
            color = PACK_COLOR if ch.pack_level else battery_color(b)
            off = (k - (n - 1) / 2) * 0.16 if cats is not None and n > 1 else 0.0
            key = self.status(ch, b, cats if ch.kind == "label" else None)
            chart.series.append(Series(key, label, color, step=True, offset=off))
        return chart


# --------------------------------------------------------------------------- batteries


def batteries(page: Page) -> str:
    """Voltage, current, SOC, cell voltages and temperature of every battery, zoomable."""
    if len(page.t) == 0:
        return '<p class="note">No samples were recorded in this run.</p>'
    names, tr = page.names, page.result.trace
    aux = [b for b, r in enumerate(page.roles) if r == "aux"]
    main = [b for b in range(len(names)) if b not in aux]
    marks = page.marks
    v = Chart("voltage", "Battery voltage and bus (V)", "V", marks=marks)
    v.series = [Series(page.bat("voltage_v", b), names[b], battery_color(b)) for b in main]
    v.series.append(Series(page.pack("bus_v"), "bus", PACK_COLOR, dash=True, width=1.0))
    v_caption = _range_on_batteries(v, page.t, tr.channel("voltage_v")[:, main], tr.bus_v)
    i = Chart("current", "Current, + = discharge (A)", "A", height=200, marks=marks)
    i.series = [Series(page.bat("current_a", b), names[b], battery_color(b)) for b in main]
    digest = page.digest  # over every sample, not only the charted ones
    if digest.load_any:
        i.series.append(Series(page.pack("load_a"), "load", PACK_COLOR, dash=True, width=1.0))
    if not digest.demand_is_load:
        i.series.append(Series(page.pack("load_demand_a"), "load demand", "#888888", dash=True))
    if digest.charger_any:
        i.series.append(Series(page.pack("charger_a"), "charger", "#6b8e23", dash=True))
    soc, soc_caption = soc_chart(page, marks)
    cell = Chart("cells", "Highest (solid) and lowest (dashed) cell voltage (V)", "V", marks=marks)
    for b in main:
        cell.series.append(Series(page.bat("max_cell_v", b), f"{names[b]} max", battery_color(b)))
        cell.series.append(
            Series(page.bat("min_cell_v", b), f"{names[b]} min", battery_color(b), dash=True)
        )
    temp = Chart("temp", "Hottest cell temperature (°C)", "°C", height=150, marks=marks)
    temp.series = [
        Series(page.bat("temp_c", b), names[b], battery_color(b)) for b in range(len(names))
    ]
    parts = [page.chart(v, v_caption), page.chart(i), page.chart(soc, soc_caption),
             page.chart(cell), page.chart(temp)]  # fmt: skip
    if aux:
        va = Chart("aux-voltage", "Auxiliary battery voltage (V)", "V", height=130)
        va.series = [Series(page.bat("voltage_v", b), names[b], battery_color(b)) for b in aux]
        parts.append(page.chart(va))
    if marks:
        parts.insert(
            0,
            '<p class="note">Dashed vertical lines: the first time of each alarm (red) or warning'
            " (amber) of the verdict.</p>",
        )
    return "".join(parts)


BUS_OFF_SCALE_COLOR = "#9aa3af"


def battery_v_range(volts: F64, pad: float = 0.06) -> tuple[float, float] | None:
    """The voltage axis of the battery chart: the batteries' own range plus a margin (None
    without a finite value), so a bus that drops to 0 V cannot squash them into a thin band."""
    finite = volts[np.isfinite(volts)]
    if finite.size == 0:
        return None
    lo, hi = float(finite.min()), float(finite.max())
    margin = max(pad * (hi - lo), 0.05)
    return lo - margin, hi + margin


FALLBACK_COLOR = "#f5d9a8"
"""Shading of the SOC chart where a battery's observer was not trusted (its fallback shown)."""


def soc_share(codes: NDArray[np.int64]) -> str:
    """"observer 93 %, fallback 7 %": how much of the run each source gave the SOC."""
    n = max(len(codes), 1)
    parts = [(int(np.sum(codes == k)), name) for k, name in enumerate(SOURCES)]
    return ", ".join(f"{SHORT[name]} {100.0 * c / n:.0f} %" for c, name in
                     sorted(parts, reverse=True) if c)  # fmt: skip


SHORT = {OBSERVER: "observer", FALLBACK: "fallback (coulomb counter)",
         COUNTER: "coulomb counter", BATTERY: "battery's own"}  # fmt: skip


def soc_chart(page: Page, marks: list[tuple[float, str, str]]) -> tuple[Chart, str]:
    """The SOC the core used (solid, ``contract/soc_source.py``) and the plant's true SOC
    (dashed), per battery; where a battery's observer was not trusted (its fallback shown)
    the chart is shaded, and the caption says which source gave each battery's SOC for how
    much of the run."""
    names, tr = page.names, page.result.trace
    chart = Chart("soc", "State of charge (%): what the BMS used (solid) and the plant's truth "
                  "(dashed)", "%", marks=marks)  # fmt: skip
    said = []
    fallback = np.zeros(len(page.t), dtype=bool)
    for b in range(len(names)):
        soc, codes = page.core_soc(b)
        chart.series.append(Series(page.store.add(f"soc_core/{b}", soc), names[b],
                                   battery_color(b), scale=100.0))  # fmt: skip
        truth = np.asarray(tr.channel("soc")[:, b], np.float64)
        if not np.allclose(truth, soc, atol=1e-9, equal_nan=True):
            plant = Series(page.bat("soc", b), f"{names[b]} (plant)", battery_color(b),
                           dash=True, width=1.0, scale=100.0)
            chart.series.append(plant)
        fallback |= codes == SOURCES.index(FALLBACK)
        if b in page.traction or np.any(codes != SOURCES.index(BATTERY)):
            said.append(f"{names[b]}: {soc_share(codes)}")
    found = spans(np.asarray(page.t, np.float64), fallback)
    chart.bands.extend((a, z, FALLBACK_COLOR) for a, z in found)
    caption = "SOC from: " + "; ".join(said) + "."
    if found:
        caption += (" Shaded: a battery's observer was not trusted (settling after the start,"
                    " or restarting after diverging) and its SOC is the fallback, the coulomb"
                    " counter.")  # fmt: skip
    return chart, caption


def _range_on_batteries(chart: Chart, t: F64, volts: F64, bus_v: F64) -> str:
    """Fix the chart's axis on the batteries; the times the bus leaves it are shaded grey and
    named in the caption (the bus itself is drawn, clipped, over the same axis)."""
    rng = battery_v_range(volts)
    if rng is None:
        return ""
    chart.y_range = rng
    with np.errstate(invalid="ignore"):
        off = (bus_v < rng[0]) | (bus_v > rng[1])
    found = spans(t, off)
    if not found:
        return ""
    chart.bands.extend((a, b, BUS_OFF_SCALE_COLOR) for a, b in found)
    low = float(np.nanmin(bus_v[off])) if np.isfinite(bus_v[off]).any() else math.nan
    when = ", ".join(f"{fmt_time(a)}–{fmt_time(b)}" for a, b in found[:4])
    more = f" and {len(found) - 4} more" if len(found) > 4 else ""
    return (
        f"The axis spans the batteries ({rng[0]:.1f}–{rng[1]:.1f} V). Shaded grey: the bus"
        f" was off this scale (down to {low:.1f} V) at {when}{more}."
    )


# --------------------------------------------------------------------------- switches


def switches(page: Page) -> str:
    """CHG/DSG path of every battery as lanes, body-diode conduction, and a count table."""
    tr = page.result.trace
    if len(page.t) == 0:
        return '<p class="note">No samples were recorded in this run.</p>'
    names = page.names
    kinds = page.info.switch_kinds(names) if page.info.config is not None else [None] * len(names)
    digest = page.digest  # the table counts every sample; the chart draws the kept ones
    lanes: list[tuple[int, str, str, str | None]] = []  # battery, label, state key, diode
    for b, name in enumerate(names):
        same = digest.same_paths(b)
        if kinds[b] == "relay":
            lanes.append((b, f"{name} relay", "dsg_on", None))
        elif kinds[b] is None and same:
            lanes.append((b, f"{name} CHG = DSG", "dsg_on", None))
        else:
            lanes.append((b, f"{name} DSG", "dsg_on", "dsg_diode_a"))
            lanes.append((b, f"{name} CHG", "chg_on", "chg_diode_a"))
    n = len(lanes)
    chart = Chart("switches", "Switch paths (raised = closed)", height=max(110, 30 + 34 * n))
    chart.categories = [lab for _, lab, _, _ in reversed(lanes)]
    for k, (b, label, state, diode) in enumerate(lanes):
        level = n - 1 - k
        key = page.store.add(f"{state}/{b}", (tr.channel(state)[:, b] > 0.5).astype(float), 1.0)
        chart.series.append(
            Series(
                key,
                label,
                battery_color(b),
                step=True,
                offset=level - 0.35,
                scale=0.7,
                states=("off", "on"),
            )
        )
        if diode is not None and digest.diode_conducted(diode[:3], b):
            on = np.abs(np.nan_to_num(tr.channel(diode)[:, b])) > 1e-6
            d = np.where(on, 0.0, np.nan)
            chart.series.append(
                Series(page.store.add(f"{diode}-on/{b}", d, 1.0), f"{label} diode",
                       DIODE_COLOR, width=5.0, offset=level, states=("conducting",))
            )  # fmt: skip
    on_chg, on_dsg = digest.on_share("chg"), digest.on_share("dsg")
    n_chg, n_dsg = digest.changes("chg"), digest.changes("dsg")
    rows = [
        (name, fmt_num(100.0 * on_chg[b]), fmt_num(100.0 * on_dsg[b]), str(n_chg[b]),
         str(n_dsg[b]))
        for b, name in enumerate(names)
    ]  # fmt: skip
    head = ("battery", "CHG on (% of samples)", "DSG on (% of samples)", "CHG changes",
            "DSG changes")  # fmt: skip
    return page.chart(
        chart,
        "As switched in the plant (a welded relay or a shorted FET counts as on). Orange: current"
        " through a body diode.",
    ) + table(head, rows, cls="counts")


# --------------------------------------------------------------------------- methods


def _f(x: Any, digits: str = "") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    return fmt_num(x)


def sequencing(page: Page) -> str:
    """Co-discharge share, switch changes, load share, cross-charge: bench_sequencing's figures."""
    cfg = page.info.scenario()
    if cfg is None or len(page.t) < 2:
        return '<p class="note">The figures need the run\'s scenario configuration and samples.</p>'
    fig = Q.sequencing_figures(cfg, page.result)
    verdicts = Q.sequencing_verdicts(fig)
    doc = {
        "co_share": ("co-discharge share", "", "of the loaded time after the voltages met in"
                     " which every battery discharged with both FETs on"),
        "sw_per_min": ("switch changes", "/min", "FET gate changes per minute of steady load"),
        "peak_share": ("peak load share", "", "largest battery current over the load current"
                       " after the voltages met (load > 5 A); with every battery engaged the"
                       " split is the plant's (direct parallel gives the same)"),
        "peak_share_held": ("peak load share, one held out", "", "the same at the steps in"
                            " which the controller held a battery out (0: never)"),
        "rev_peak_a": ("peak current into a battery", "A", "no charger on"),
        "rev_1a_s": ("longest > 1 A into a battery", "s", "uninterrupted"),
        "cross_mah_h": ("cross-charge", "mAh/h", "charge pushed into batteries per hour"),
        "meet_s": ("voltages met at", "s", "open-circuit voltages within v_co"),
        "join_s": ("all discharging from", "s", "first period every battery discharged"),
        "diode_j": ("body-diode loss", "J", "both paths, all batteries"),
        "joins": ("joins", "", "BatteryJoined events"),
        "risk_events": ("cross-current risks", "", "CrossCurrentRisk events"),
    }  # fmt: skip
    rows = []
    for key, (label, unit, meaning) in doc.items():
        goal = Q.SEQUENCING_GOAL_TEXT.get(key, "")
        verdict = verdicts.get(key, "")
        cls = {"met": "ok", "MISSED": "bad"}.get(verdict, "")
        shown = f'<span class="{cls}">{esc(verdict)}</span>' if verdict and verdict != "-" else ""
        rows.append((esc(label), esc(_f(fig[key])), esc(unit), esc(goal), shown, esc(meaning)))
    out = table(("figure", "value", "unit", "goal", "", "meaning"), rows, cls="figures", raw=True)
    out += (
        '<p class="note">As <code>benchmarks/bench_sequencing.py</code> computes them'
        " (<code>packpilot.sim.quality.sequencing_figures</code>). Energy and heat against direct"
        " parallel need a second run: see the benchmark.</p>"
    )
    charts = []
    for name, title in (("seq_state", "Sequencing state per battery"),
                        ("seq_mode", "Sequencing mode")):  # fmt: skip
        ch = page.channels.get(name)
        if ch is not None and ch.columns:
            page.shown.add(name)
            charts.append(page.chart(page.status_chart(ch, title)))
    return out + "".join(charts)


def protection(page: Page) -> str:
    """Per battery: trip, parameter time, allowance used, margin to the cut-off, time to trip."""
    ch = page.channels
    if not any(k in ch for k in ("protection_param", "protection_fraction")):
        return (
            '<p class="note">Not recorded: this run has no <code>protection_*</code> status'
            " channels.</p>"
        )
    names, t = page.names, page.t
    event_of = {trace_b: k for k, trace_b in enumerate(page.info.event_batteries(names))}
    param = ch.get("protection_param")
    protected = list((param or ch["protection_fraction"]).columns)
    rows = []
    for b in protected:
        f = Q.protection_figures(page.result, b, event_of.get(b, b))
        rows.append(
            (
                names[b],
                "no" if not f["tripped"] else f"at {fmt_num(f['trip_s'])} s ({f['param_at_trip']})",
                _param_times(param, b, t) if param is not None else "–",
                _f(None if f["max_fraction"] is None else 100.0 * f["max_fraction"]),
                _f(f["min_margin_v"]),
                _f(f["min_time_to_trip_s"]),
            )
        )
    head = ("battery", "tripped", "time per parameter", "max allowance used (%)",
            "least margin to cut-off (V)", "shortest predicted time to trip (s)")  # fmt: skip
    out = table(head, rows, cls="counts")
    out += (
        '<p class="note">Margin: lowest cell voltage minus the active cut-off while discharging'
        " (negative: below the cut-off, the allowance running down). Allowance: sum(t_k /"
        " t_max_k). Figures from <code>packpilot.sim.quality.protection_figures</code>, as"
        " <code>benchmarks/bench_protection.py</code> reports them. Red: tripped.</p>"
    )
    bands = _trip_bands(page, ch.get("protection_tripped"))
    parts = [out]
    if param is not None:
        c = page.status_chart(param, "Active protection parameter")
        c.bands = bands
        parts.append(page.chart(c))
    frac = ch.get("protection_fraction")
    if frac is not None and nominal(frac) is not None:
        parts.append(f'<p class="note">Allowance used: {esc(nominal(frac))}.</p>')
    elif frac is not None:
        c = Chart("prot-fraction", "Allowance used (%)", "%", bands=bands, height=150)
        c.series = [
            Series(page.status(frac, b), names[b], battery_color(b), step=True, scale=100.0)
            for b in frac.columns
        ]
        parts.append(page.chart(c))
    cut = ch.get("protection_cutoff_v")
    if cut is not None:
        c = Chart("prot-margin", "Lowest cell (solid) and active cut-off (dashed) (V)", "V",
                  bands=bands)  # fmt: skip
        for b in cut.columns:
            c.series.append(Series(page.bat("min_cell_v", b), names[b], battery_color(b)))
            c.series.append(
                Series(page.status(cut, b), f"{names[b]} cut-off", battery_color(b), dash=True,
                       step=True)
            )  # fmt: skip
        parts.append(page.chart(c))
    page.shown.update(k for k in ch if k.startswith("protection_"))
    return "".join(parts)


def _param_times(param: StatusChannel, b: int, t: F64) -> str:
    t_end = float(t[-1]) + (float(t[-1] - t[-2]) if len(t) > 1 else 0.0)
    dur = np.diff(np.append(t[param.rows], t_end))
    per: dict[str, float] = {}
    for j, v in enumerate(param.column(b)):
        if v is not None:
            per[str(v)] = per.get(str(v), 0.0) + float(dur[j])
    return ", ".join(f"{k}: {fmt_num(s)} s" for k, s in sorted(per.items(), key=lambda kv:
                                                               natural_key(kv[0])))  # fmt: skip


def _trip_bands(page: Page, tripped: StatusChannel | None) -> list[tuple[float, float, str]]:
    if tripped is None:
        return []
    out: list[tuple[float, float, str]] = []
    n = len(page.t)
    for b in tripped.columns:
        col = np.repeat(np.nan_to_num(tripped.numeric(b)), np.diff(np.append(tripped.rows, n)))
        out += [(a, z, ALARM_COLOR) for a, z in spans(page.t, col > 0.5)]
    return out


def charging(page: Page) -> str:
    """Time in each stage, the stage periods, time to full, peak charge current."""
    res, names = page.result, page.names
    if len(page.t) < 2:
        return '<p class="note">No samples were recorded in this run.</p>'
    cfg = page.info.scenario()
    traction = page.traction
    times = Q.stage_times(res)
    cur = res.trace.channel("current_a")
    peak = {names[b]: max(0.0, -float(np.nanmin(cur[:, b]))) for b in traction}
    ttf = math.nan
    if cfg is not None and cfg.charging is not None:
        c = cfg.charging
        per_cell = c.voltage_basis == "cell"
        series = [cfg.pack.batteries[b].series_groups for b in traction] if per_cell else []
        scale = np.asarray(series, dtype=np.float64) if per_cell else 1.0
        ttf = Q.time_to_full(res, c.v_sat_v * scale, c.termination_current_a, traction,
                             c.reach_tol_v * scale)  # fmt: skip
    done = next((e.t_s for e in res.events if e.kind == "ChargeComplete"), None)
    kv = [
        ("charge complete (the method's ChargeComplete)", "no" if done is None else
         f"at {fmt_num(done)} s ({fmt_time(done)})"),
        ("time to full (the benchmark's criterion)", "not reached" if not math.isfinite(ttf)
         else f"{fmt_num(ttf)} s ({fmt_time(ttf)})"),
        ("peak charge current", ", ".join(f"{k}: {fmt_num(v)} A" for k, v in peak.items())),
        ("time per stage", ", ".join(f"{k}: {fmt_num(v)} s" for k, v in times.items()) or "–"),
    ]  # fmt: skip
    out = table(None, kv, cls="kv")
    rows = [
        (r["stage"], fmt_num(r["t0_s"]), fmt_num(r["duration_s"]), str(r["n"]),
         fmt_num(r["charge_ah"]), fmt_num(r["mean_a"]))
        for r in Q.stage_breakdown(res, traction)
    ]  # fmt: skip
    if rows:
        out += table(("stage", "from (s)", "duration (s)", "batteries connected", "charge (Ah)",
                      "mean charge current (A)"), rows, cls="counts")  # fmt: skip
    out += (
        '<p class="note">Time to full: every traction battery within reach_tol_v of V_sat with its'
        " charge current at the termination current. Stage periods moving less than 0.05 Ah are"
        " left out. From <code>packpilot.sim.quality</code> (<code>time_to_full</code>,"
        " <code>stage_breakdown</code>), as <code>benchmarks/bench_charging.py</code> uses"
        " them.</p>"
    )
    parts = [out]
    stage = page.channels.get("chg_stage")
    if stage is not None and stage.columns:
        parts.append(page.chart(page.status_chart(stage, "Charging stage")))
        page.shown.add("chg_stage")
    chart = Chart("chg-current", "Charge current into each battery, charger current (A)", "A")
    for b in traction:
        key = page.bat("current_a", b)
        chart.series.append(Series(key, names[b], battery_color(b), scale=-1.0))
    chart.series.append(Series(page.pack("charger_a"), "charger", "#6b8e23", dash=True))
    parts.append(page.chart(chart))
    return "".join(parts)


def equalization(page: Page) -> str:
    """Cell (group) voltage spread at start and end, balancing energy, what is still owed."""
    tr, names = page.result.trace, page.names
    if len(page.t) == 0:
        return '<p class="note">No samples were recorded in this run.</p>'
    dt = np.diff(page.t, append=page.t[-1])
    rows = []
    chart = Chart("eq-spread", "Group voltage spread (mV)", "mV")
    for b in page.traction:
        s = Q.group_spread_mv(tr, b)
        if not np.isfinite(s).any():
            continue
        finite = np.flatnonzero(np.isfinite(s))
        owed = _owed_end(page, b)
        rows.append(
            (
                names[b],
                fmt_num(float(s[finite[0]])),
                fmt_num(float(s[finite[-1]])),
                fmt_num(float(np.nanmax(s))),
                fmt_num(float(np.nansum(tr.channel("balancer_w")[:, b] * dt)) / 3600.0),
                _f(owed),
            )
        )
        chart.series.append(Series(page.store.add(f"spread/{b}", s), names[b], battery_color(b)))
    head = ("battery", "spread at start (mV)", "spread at end (mV)", "max spread (mV)",
            "balancing energy (Wh)", "still owed at end (Ah)")  # fmt: skip
    out = table(head, rows, cls="counts") if rows else '<p class="note">No group voltages.</p>'
    out += (
        '<p class="note">Spread: highest minus lowest series-group voltage of a battery as'
        " recorded (under load it includes the groups' resistance differences; the benchmark"
        " measures it at rest, both with <code>packpilot.sim.quality.spread_mv</code>)."
        " Balancing energy: the balancers' power integrated. Owed: balancing charge granted"
        " (AH) not yet delivered.</p>"
    )
    parts = [out, page.chart(chart)]
    w = Chart("eq-power", "Balancer power (W)", "W", height=150)
    w.series = [
        Series(page.bat("balancer_w", b), names[b], battery_color(b)) for b in page.traction
    ]
    parts.append(page.chart(w))
    return "".join(parts)


def _owed_end(page: Page, b: int) -> float | None:
    total, seen = 0.0, False
    for name, ch in page.channels.items():
        base = group_base(name)
        if base is None or base[0] != "eq_owed_ah" or b not in ch.columns:
            continue
        v = ch.values[-1, b]
        if v is not None:
            total, seen = total + float(v), True
    return total if seen else None


METHODS: dict[str, tuple[str, Any]] = {
    "sequencing": ("Parallel discharge sequencing", sequencing),
    "protection": ("Discharge protection", protection),
    "charging": ("Staged charging", charging),
    "equalization": ("Equalization", equalization),
}
"""Method sections, in page order: shown only for the methods the scenario enables."""


# --------------------------------------------------------------------------- other channels


def controllers(page: Page) -> str:
    """Every status channel no method section drew: nominal ones as one line, the rest as
    charts folded per controller."""
    rest = {k: v for k, v in page.channels.items() if k not in page.shown}
    if not rest:
        return '<p class="note">No other controller status channels were recorded.</p>'
    families: dict[str, list[str]] = {}
    for name in rest:
        families.setdefault(family_of(name), []).append(name)
    parts = []
    for family, chans in families.items():
        flat, busy = [], []
        grouped: dict[str, list[str]] = {}
        for name in chans:
            why = nominal(rest[name])
            if why is not None:
                flat.append(f"<li><code>{esc(name)}</code>: nominal ({esc(why)})</li>")
            elif group_base(name) and rest[name].kind == "numeric":
                grouped.setdefault(group_base(name)[0], []).append(name)  # type: ignore[index]
            else:
                busy.append(name)
        parts.append(f"<h3>{esc(family)}</h3>")
        if flat:
            parts.append(f'<ul class="nominal">{"".join(flat)}</ul>')
        charts = [page.chart(page.status_chart(rest[n])) for n in busy]
        charts += [c for base, names in grouped.items() for c in _group_charts(page, base, names)]
        if charts:
            n_ch = len(busy) + sum(len(v) for v in grouped.values())
            parts.append(
                f"<details><summary>{n_ch} channel{'s' if n_ch != 1 else ''} that changed:"
                f" {esc(', '.join(busy + [b + '_g*' for b in grouped]))}</summary>"
                + "".join(charts)
                + "</details>"
            )
    return "".join(parts)


def _group_charts(page: Page, base: str, names: list[str]) -> list[str]:
    """Per-group channels (``<base>_g<k>``): one chart per battery, a line per group."""
    chans = sorted(((group_base(n)[1], page.channels[n]) for n in names), key=lambda gc: gc[0])  # type: ignore[index]
    cols = sorted({b for _, ch in chans for b in ch.columns})
    out = []
    palette = ("#440154", "#414487", "#2a788e", "#22a884", "#7ad151", "#fde725", "#bc3754",
               "#f98e09")  # fmt: skip
    for b in cols:
        c = Chart(f"grp-{base}-{b}", f"{base} per group — {page.names[b]}", unit_of(base))
        for j, (g, ch) in enumerate(chans):
            if b in ch.columns:
                c.series.append(Series(page.status(ch, b), f"g{g}", palette[j % len(palette)],
                                       step=True))  # fmt: skip
        out.append(page.chart(c))
    return out


__all__ = ["METHODS", "Page", "batteries", "controllers", "switches"]


MAX_SOP_POINTS = 120
"""State-of-power predictions drawn along a run at most (each one a few milliseconds)."""


def _scenario(info: RunInfo) -> Any:
    """The run's scenario, typed, or None when its recorded config does not read back."""
    from packpilot.config.scenario import parse_config
    from packpilot.errors import PackPilotError

    if not info.config:
        return None
    try:
        return parse_config(dict(info.config), "recorded config")
    except PackPilotError:
        return None


def power(page: Page) -> str:
    """The pack's state of power along the run (``docs/power.md``): at up to 120 instants,
    the largest discharge and charge current it could have held for 2, 10 and 30 s, predicted
    from the recorded state by ``sim/power_view.py`` (the function ``run`` publishes its
    CCL/DCL and 0x231 from, and the dashboard shows: the core's SOC and its source, the
    observer's polarisation and R0 where it was trusted), beside the current drawn; the
    lowest of each over the run for the pack (A and W) and per battery (its share of the
    pack's limit, and its limit alone). Empty when the run's config does not read back or
    nothing was recorded."""
    from packpilot.sim.power import params_of
    from packpilot.sim.power_view import state_of_power_now, view_of_status

    cfg = _scenario(page.info)
    cols = page.traction
    if cfg is None or len(page.t) == 0 or not cols:
        return ""
    prm = params_of(cfg)
    if prm.series.shape[0] != len(cols):
        return ""
    tr = page.result.trace
    n, nb, nh = len(page.t), len(cols), prm.horizons_s.shape[0]
    picks = np.unique(np.linspace(0, n - 1, min(MAX_SOP_POINTS, n)).astype(np.intp))
    pack = np.full((4, nh, n), math.nan)  # dsg A, dsg W, chg A, chg W
    bat = np.full((4, nb, n), math.nan)  # 10 s: share dsg, alone dsg, share chg, alone chg
    h10 = int(np.argmin(np.abs(prm.horizons_s - 10.0)))
    for k in picks:

        def at(name: str, b: int, k: int = int(k)) -> object:
            return page.status_at(name, k, b)

        view = view_of_status(
            tr.battery[k], at, cols, bus_v=float(tr.bus_v[k]), load_a=float(tr.load_a[k]),
            mode=page.status_at("mode", int(k), cols[0]),
        )  # fmt: skip
        # each battery alone at 10 s only, the one horizon shown: a third of the searches
        out = state_of_power_now(cfg, prm, view, alone=float(prm.horizons_s[h10]))
        if out is None:
            continue
        pack[:, :, k] = (out.pack_dsg_a[0], out.pack_dsg_w[0], out.pack_chg_a[0],
                         out.pack_chg_w[0])  # fmt: skip
        bat[:, :, k] = (out.share_dsg_a[0, :, h10], out.alone_dsg_a[0, :, h10],
                        out.share_chg_a[0, :, h10], out.alone_chg_a[0, :, h10])  # fmt: skip
    held = np.maximum.accumulate(np.where(np.isfinite(pack[0, 0]), np.arange(n), 0))
    drawn = np.nansum(tr.channel("current_a")[:, cols], axis=1)
    chart = Chart("power", "State of power and the current drawn (A; charge below zero)", "A",
                  height=220, marks=page.marks)  # fmt: skip
    for h, secs in enumerate(prm.horizons_s.tolist()):
        dash = h != h10
        chart.series.append(Series(page.store.add(f"sop/dsg{secs:g}", pack[0, h][held]),
                                   f"{secs:g} s discharge", "#1f77b4", dash=dash))  # fmt: skip
        chart.series.append(Series(page.store.add(f"sop/chg{secs:g}", -pack[2, h][held]),
                                   f"{secs:g} s charge", "#6b8e23", dash=dash))  # fmt: skip
    chart.series.append(Series(page.store.add("sop/drawn", drawn), "pack current", PACK_COLOR,
                               width=1.0))  # fmt: skip
    i30 = int(np.argmax(prm.horizons_s))
    headroom = pack[0, i30][held] - drawn
    low = float(np.nanmin(headroom)) if np.isfinite(headroom).any() else math.nan
    when = float(page.t[int(np.nanargmin(headroom))]) if math.isfinite(low) else math.nan

    def lowest(x: F64) -> str:
        return fmt_num(float(np.nanmin(x))) if np.isfinite(x).any() else "–"

    rows = []
    for h, secs in enumerate(prm.horizons_s.tolist()):
        rows.append((f"{secs:g} s", lowest(pack[0, h]), lowest(pack[1, h]), lowest(pack[2, h]),
                     lowest(pack[3, h])))  # fmt: skip
    facts = table(("pack, lowest over the run", "discharge (A)", "discharge (W)", "charge (A)",
                   "charge (W)"), rows, cls="sop")  # fmt: skip
    facts += table(("", "value"), [
        ("lowest 30 s discharge limit (A)", lowest(pack[0, i30])),
        ("least headroom, 30 s limit - current (A)", fmt_num(low)),
        ("... at", fmt_time(when) if math.isfinite(when) else "–"),
        ("lowest 10 s charge limit (A)", lowest(pack[2, h10])),
    ])  # fmt: skip
    per = [(page.names[b], *[lowest(bat[q, j]) for q in range(4)]) for j, b in enumerate(cols)]
    facts += table(("battery, lowest over the run (10 s)", "share of the discharge (A)",
                    "alone, discharge (A)", "share of the charge (A)", "alone, charge (A)"),
                   per, cls="sop-battery")  # fmt: skip
    note = (
        '<p class="note">Predicted from the recorded state as <code>run</code> predicts '
        "its CCL/DCL and the dashboard shows it (<code>sim/power_view.py</code>: the SOC the "
        "core used, the observer's polarisation and R0 where it was trusted, the cell set's "
        "resistances elsewhere; temperatures, switch states, the limits layer's limits), at up "
        "to 120 instants: the largest constant current the pack could have held for that long "
        "without any battery crossing its cut-off, current or temperature limit "
        "(docs/power.md). A battery's share: what it carries while the pack draws its limit; "
        "alone: its own limit with the others off the bus.</p>"
    )
    return note + facts + page.chart(chart)
