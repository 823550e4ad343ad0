"""The dashboard's fleet view (``packpilot dashboard --fleet fleet.sqlite``, page ``/fleet``):
one row per battery of ``fleet report`` — flights, R0 first against recent, capacity and
cell-spread change, the flags — and per battery its R0 and cell spread flight by flight as
small inline charts, so a pack drifting away from its first flights is seen at a glance.
The page is plain HTML and SVG, no script; its data are in ``/api/fleet`` as JSON.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from packpilot.replay.fleet import flights, report

FLEET_HEADERS = {
    "Cache-Control": "no-store",
    "Content-Security-Policy": (
        "default-src 'none'; style-src 'unsafe-inline'; img-src data:; frame-ancestors 'none'; "
        "base-uri 'none'; form-action 'none'"
    ),
}
"""The fleet page runs no script: only its own inline style is allowed."""

CSS = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:1.5em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;width:100%}td,th{border:1px solid #ccc;padding:.25em .5em;
text-align:left;vertical-align:top}.flag{color:#b00;font-weight:600}.ok{color:#286b28}
.muted{color:#666}svg{max-width:100%;height:auto}
"""


def fleet_data(db: Path) -> dict[str, Any]:
    """What the page shows, as JSON: the report rows and every battery's flights."""
    return {"db": str(db), "batteries": report(db), "flights": flights(db)}


def _spark(values: Sequence[float | None], color: str, unit: str, scale: float) -> str:
    """A small line of one quantity flight by flight (gaps where a flight has none)."""
    pts = [(k, v * scale) for k, v in enumerate(values) if v is not None and math.isfinite(v)]
    if len(pts) < 2:
        return "<span class='muted'>–</span>"
    w, h, pad = 220, 48, 4
    lo, hi = min(v for _, v in pts), max(v for _, v in pts)
    span = (hi - lo) or abs(hi) or 1.0
    n = max(len(values) - 1, 1)
    xy = " ".join(
        f"{pad + k / n * (w - 2 * pad):.1f},{h - pad - (v - lo) / span * (h - 2 * pad):.1f}"
        for k, v in pts
    )
    label = f"{lo:.3g}..{hi:.3g} {unit}"
    return (
        f"<svg viewBox='0 0 {w} {h}' width='{w}' height='{h}' role='img' "
        f"aria-label='{html.escape(label)}'><polyline fill='none' stroke='{color}' "
        f"stroke-width='1.5' points='{xy}'/></svg><br><span class='muted'>{label}</span>"
    )


def fleet_page(db: Path) -> str:
    """The whole page (see the module docstring)."""
    data = fleet_data(db)
    rows = []
    for r in data["batteries"]:
        name = str(r["battery"])
        fl = data["flights"].get(name, [])
        flags = r["flags"]
        flag_html = (
            "".join(f"<div class='flag'>{html.escape(str(f))}</div>" for f in flags)
            if flags else "<span class='ok'>no flag</span>"
        )  # fmt: skip
        spread = (
            f"{r['cell_spread_first_mv']:.0f} → {r['cell_spread_recent_mv']:.0f} mV"
            if r.get("cell_spread_flights") else "no real cells in its logs"
        )  # fmt: skip
        cap = r.get("capacity_change_pct")
        rows.append(
            f"<tr id='battery-{html.escape(name)}'><td>{html.escape(name)}</td>"
            f"<td>{r['flights']}</td>"
            f"<td>{r['r0_first_mohm']:.2f} → {r['r0_recent_mohm']:.2f} mΩ "
            f"({r['r0_change_pct']:+.0f} %)<br>"
            f"{_spark([f['r0_ohm'] for f in fl], '#1f77b4', 'mΩ', 1000.0)}</td>"
            f"<td>{'–' if cap is None else f'{cap:+.0f} %'}</td>"
            f"<td>{spread}<br>"
            f"{_spark([f['cell_spread_v'] for f in fl], '#ff7f0e', 'mV', 1000.0)}</td>"
            f"<td>{r['lowest_cell_v']:.2f} V</td><td>{r['warned_flights']}</td>"
            f"<td>{flag_html}</td></tr>"
        )
    table = "<p>No flights recorded yet: <code>packpilot fleet add LOG...</code></p>"
    if rows:
        table = (
            "<table id='fleet'><tr><th>battery</th><th>flights</th><th>R0, first → recent"
            "</th><th>capacity change</th><th>cell spread, first → recent</th><th>lowest cell"
            "</th><th>flights the autopilot warned</th><th>flags</th></tr>" + "".join(rows)
            + "</table>"
        )  # fmt: skip
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>PackPilot fleet</title><style>{CSS}</style></head><body>"
        f"<h1>Fleet: battery health across flights</h1><p class='muted'>{html.escape(str(db))}"
        " · first flights = the median of each battery's first 10, recent = of its last 5 "
        "(see <code>packpilot fleet report</code>)</p>"
        f"{table}</body></html>\n"
    )


__all__ = ["FLEET_HEADERS", "fleet_data", "fleet_page"]
