"""The fit's self-contained HTML page (inline SVG, no script, no network): the verdict and its
reasons first, then the parameters with their uncertainty and flags, then per log the measured
against the predicted and the straight-line voltage (the held-out part shaded), the residuals
with the noise floor, and the error on the time to 3.5 V and 3.3 V per cell.
"""

from __future__ import annotations

import html
import io
import re
from collections.abc import Sequence
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from packpilot.model.fit.validate import LogCheck, Validation
from packpilot.report.fmt import table
from packpilot.report.style import ALARM_COLOR, BATTERY_COLORS

CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;color:#222}
h1{font-size:1.5em}h2{font-size:1.2em;margin-top:1.6em;border-bottom:1px solid #ddd}
.verdict{border-left:6px solid #2ca02c;background:#f6f6f6;padding:.6em 1em}
.verdict.low{border-color:#ff7f0e}.verdict.refused{border-color:#d62728}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.2em .6em;text-align:left}
.muted{color:#666}svg{max-width:100%;height:auto}
"""


def _svg(fig: Figure) -> str:
    FigureCanvasAgg(fig)
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
    text = buf.getvalue()
    return re.sub(r"<metadata>.*?</metadata>", "", text[text.index("<svg") :], flags=re.S)


def _figure(c: LogCheck) -> str:
    fig = Figure(figsize=(10, 5.5))
    ax, rx = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    t = c.t_s
    ax.plot(t, c.measured_v, color="#444", lw=0.8, label="measured")
    ax.plot(t, c.predicted_v, color=BATTERY_COLORS[0], lw=1.1, label="fitted model")
    ax.plot(t, c.baseline_v, color=BATTERY_COLORS[1], lw=0.9, ls="--", label="straight line")
    for a in (ax, rx):
        a.axvspan(c.split_t_s, float(t[c.test.stop - 1]), color="#eee", zorder=0)
        a.grid(alpha=0.3)
    ax.set_ylabel("cell voltage (V)")
    ax.legend(loc="best", fontsize=8, title="shaded: held out", title_fontsize=8)
    res = 1000.0 * (c.predicted_v - c.measured_v)
    rx.plot(t, res, color=BATTERY_COLORS[0], lw=0.7)
    nf = 1000.0 * c.noise_floor_v
    rx.axhline(nf, color=ALARM_COLOR, lw=0.8, ls=":")
    rx.axhline(-nf, color=ALARM_COLOR, lw=0.8, ls=":", label=f"noise floor ±{nf:.1f} mV")
    rx.set_ylabel("residual (mV)")
    rx.set_xlabel("time (s)")
    rx.legend(loc="best", fontsize=8)
    return _svg(fig)


def _num(x: float | None, unit: str = "s") -> str:
    return "not reached" if x is None else f"{x:.1f} {unit}"


def _checks_table(v: Validation) -> str:
    rows = []
    for c in v.checks:
        cross = "; ".join(
            f"{lv:g} V: measured {_num(m)}, predicted {_num(p)}"
            + (f" (error {p - m:+.1f} s)" if m is not None and p is not None else "")
            + (" (outside the held-out part: fitted)"
               if m is not None and not c.split_t_s <= m <= c.t_s[c.test.stop - 1] else "")
            for lv, (m, p) in c.crossings.items()
        )
        rows.append([
            c.name, f"{c.split_t_s:.0f}..{c.t_s[c.test.stop - 1]:.0f}"
            + ("" if v.mode == "time" else " (interior)" if c.interior
               else " (extrapolation: not judged)"),
            f"{1000 * c.rmse_v:.1f}", f"{1000 * c.max_err_v:.1f}",
            f"{1000 * c.noise_floor_v:.1f}", f"{1000 * c.baseline_rmse_v:.1f}",
            f"{c.skill:+.2f}", f"{100 * c.soc_swing:.0f} %", cross,
        ])  # fmt: skip
    head = [
        "log", "held out (s)", "RMSE (mV/cell)", "max error (mV)", "noise floor (mV)",
        "straight line RMSE (mV)", "skill", "SOC swing", "time to 3.5 V / 3.3 V per cell",
    ]  # fmt: skip
    return table(head, rows)


def _mode_text(v: Validation) -> str:
    """How the held-out samples were chosen (shaded in each chart)."""
    if v.mode == "flights":
        return ("Leave one flight out: each flight (load between rests) left out of one fit and "
                "predicted by the fit of the others, its state carried through it; the verdict "
                "judges the interior flights (SOC window inside the others'); the parameters "
                "above are fitted on every flight. Shaded: the held-out flight.")  # fmt: skip
    return ("Time split: the first part of each log trains the fit, the rest (shaded) tests "
            "it.")  # fmt: skip


def _params_table(v: Validation) -> str:
    r = v.result
    rows = []
    for p in [*r.params.values(), *r.soc0.values()]:
        unc = f"±{p.rel_uncertainty:.3g}" if p.name in ("b_k",) or p.name.startswith("soc0") \
            else f"±{100 * p.rel_uncertainty:.1f} %"  # fmt: skip
        rows.append([p.name, f"{p.value:.5g} {p.unit}", unc,
                     "yes" if p.identifiable else f"no: {p.reason}"])  # fmt: skip
    return table(["parameter", "value", "uncertainty (1 sigma)", "identifiable"], rows)


def fit_html(v: Validation, title: str, extra: Sequence[str] = ()) -> str:
    """The report page; ``extra``: what the written cell set assumes beyond the fit (its
    thermal data, the wiring share), listed with the fit's assumptions."""
    r = v.result
    w = r.window
    cls = {"usable": "", "low confidence": " low", "refused": " refused"}[v.verdict]
    temp = (
        "not logged" if w.temp_min_c is None else f"{w.temp_min_c:.1f}..{w.temp_max_c:.1f} degC"
    )
    notes = [*r.assumptions, f"OCV: {r.ocv_note}", *extra, *r.notes]
    parts = [
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>PackPilot fit: {html.escape(title)}</title><style>{CSS}</style></head><body>",
        f"<h1>Cell model fitted to {html.escape(title)}</h1>",
        f"<div class='verdict{cls}' id='verdict'><b>{html.escape(v.verdict)}</b><ul>"
        + "".join(f"<li>{html.escape(x)}</li>" for x in v.reasons) + "</ul></div>",
        "<h2>Parameters (per series cell)</h2>", _params_table(v),
        f"<p class='muted'>{r.n_rc} RC pair(s); training RMSE {1000 * r.rmse_v:.1f} mV; fit "
        f"{r.fit_time_s:.1f} CPU-s. Holds for SOC {w.soc_min:.2f}..{w.soc_max:.2f}, cell "
        f"current {w.current_min_a:.1f}..{w.current_max_a:.1f} A, temperature {temp}, "
        f"{w.samples} samples over {w.duration_s:.0f} s of training data.</p>",
        "<h2>Assumptions and notes</h2><ul id='assumptions'>"
        + "".join(f"<li>{html.escape(x)}</li>" for x in notes)
        + "</ul>",
        "<h2>Held-out prediction</h2>",
        f"<p class='muted' id='validation-mode'>{html.escape(_mode_text(v))}</p>",
        _checks_table(v),
    ]
    for c in v.checks:
        parts += [f"<h2>{html.escape(c.name)}</h2>", _figure(c)]
    parts.append("</body></html>")
    return "\n".join(parts)


def write_fit_report(v: Validation, title: str, out: Path, extra: Sequence[str] = ()) -> None:
    out.write_text(fit_html(v, title, extra), encoding="utf-8")


__all__ = ["fit_html", "write_fit_report"]

