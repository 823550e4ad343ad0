"""Text formatting of the report: numbers as a person reads them, times, tables, escaping.

Everything the report writes from run data (battery names, event messages, data fields) goes
through :func:`esc` or :func:`table`, so a name like ``<script>`` lands on the page as text.
"""

from __future__ import annotations

import datetime as _dt
import html
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from packpilot.report.style import unit_of


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
    "wall_time_s": "wall-clock time of the simulation (compiling the kernels not included)",
    "build_time_s": "wall-clock time compiling the kernels or loading them from the cache",
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
    return unit_of(key)


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


__all__ = [
    "METRIC_DOC",
    "esc",
    "fmt_data",
    "fmt_date",
    "fmt_num",
    "fmt_time",
    "metric_unit",
    "metric_value",
    "table",
]
