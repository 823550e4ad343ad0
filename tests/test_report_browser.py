"""The HTML report in a real headless Chromium with no network: charts draw offline, zoom by drag
and wheel, hover shows values, nominal channels are one line each.

Chromium comes from Debian (``make browser``, which ``make test`` runs first). Networking is cut
(see ``tests/cdp.py``) and every request the page makes is recorded: the report may load nothing
but its own file. Screenshots land in the test's tmp directory (``PACKPILOT_SHOTS=dir`` keeps
them) so a person can look at them.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from packpilot.report.html import SECTION_IDS
from tests.cdp import CHROMIUM, Cdp, chromium, open_page

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="headless Chromium not installed at /usr/bin/chromium (run `make browser`)",
)

RICH_PROTECTION = """
[limits]

[protection]
parameters = [
  { name = "P1", cutoff_v = 4.0, t_max_s = 4.0 },
  { name = "P2", cutoff_v = 3.9, t_max_s = 6.0 },
  { name = "P3", cutoff_v = 3.8, t_max_s = 8.0 },
]
"""
READY = "document.body.dataset.ready === '1'"


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded run with events, protection, sequencing and limits, reported by the CLI."""
    tmp = tmp_path_factory.mktemp("browser")
    text = (EXAMPLES / "sequencing_dual_hover.toml").read_text(encoding="utf-8")
    cfg = tmp / "rich.toml"
    cfg.write_text(
        text.replace('controller = ["sequencing"]', 'controller = ["protection", "sequencing"]')
        + RICH_PROTECTION,
        encoding="utf-8",
    )
    db, out = tmp / "run.sqlite", tmp / "report.html"
    env = {**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true", "MPLBACKEND": "Agg"}
    for args in (
        ["simulate", str(cfg), "--duration", "30", "--db", str(db), "--no-progress", "--json"],
        ["report", str(db), "--out", str(out)],
    ):
        r = subprocess.run(
            [sys.executable, "-m", "packpilot.cli", *args],
            capture_output=True,
            text=True,
            timeout=180,
            env=env,
            cwd=ROOT,
        )
        assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="module")
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cdp]:
    with chromium(tmp_path_factory.mktemp("chromium"), 1280, 900) as cdp:
        yield cdp


@pytest.fixture
def loaded(browser: Cdp, report: Path) -> Cdp:
    open_page(browser, report.resolve().as_uri(), READY)
    return browser


def shots_dir(tmp_path: Path) -> Path:
    keep = os.environ.get("PACKPILOT_SHOTS")
    out = Path(keep) if keep else tmp_path
    out.mkdir(parents=True, exist_ok=True)
    return out


def x_range(cdp: Cdp, chart: str) -> list[float]:
    rng: list[float] = cdp.eval(
        f"[ppCharts['{chart}'].scales.x.min, ppCharts['{chart}'].scales.x.max]"
    )
    return rng


def over_box(cdp: Cdp, chart: str) -> dict[str, float]:
    """The plotting area of a chart, scrolled into view, in viewport coordinates."""
    box: dict[str, float] = cdp.eval(
        f"(() => {{ const o = ppCharts['{chart}'].over; o.scrollIntoView({{block: 'center'}});"
        " const r = o.getBoundingClientRect();"
        " return {x: r.left, y: r.top, w: r.width, h: r.height}; })()"
    )
    return box


def test_loads_offline_with_every_section_and_chart(loaded: Cdp, tmp_path: Path) -> None:
    cdp = loaded
    assert [u for u in cdp.requests if not u.startswith("file://")] == []  # nothing fetched
    assert len(cdp.requests) == 1
    ids = cdp.eval("[...document.querySelectorAll('section')].map(s => s.id)")
    assert set(SECTION_IDS) <= set(ids) and {"sequencing", "protection"} <= set(ids)
    assert ids[:2] == ["verdict", "summary"]  # the verdict and the KPIs first
    drawn, total = map(int, cdp.eval("document.body.dataset.charts").split("/"))
    folded = cdp.eval("document.querySelectorAll('details:not([open]) .chart').length")
    assert drawn == total - folded and drawn >= 8
    errors = cdp.eval("document.querySelectorAll('.chart[data-state=error]').length")
    assert errors == 0
    inked = cdp.eval(
        "(() => { const c = ppCharts['current'].ctx.canvas;"
        " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " let n = 0; for (let i = 3; i < d.length; i += 4) { if (d[i] > 0) n++; } return n; })()"
    )
    assert inked > 2000  # lines were drawn, not an empty canvas
    shot = shots_dir(tmp_path) / "report_top.png"
    cdp.screenshot(shot)
    raw = shot.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n" and struct.unpack(">II", raw[16:24]) == (1280, 900)


def test_drag_selects_a_time_range_and_all_charts_follow(loaded: Cdp, tmp_path: Path) -> None:
    cdp = loaded
    full = x_range(cdp, "current")
    box = over_box(cdp, "current")
    y = box["y"] + box["h"] / 2
    x0, x1 = box["x"] + box["w"] * 0.25, box["x"] + box["w"] * 0.5
    cdp.mouse("mouseMoved", x0, y)
    cdp.mouse("mousePressed", x0, y, button="left", clickCount=1)
    for k in range(1, 6):
        cdp.mouse("mouseMoved", x0 + (x1 - x0) * k / 5, y, button="left", buttons=1)
    cdp.mouse("mouseReleased", x1, y, button="left", clickCount=1)
    lo, hi = x_range(cdp, "current")
    span = full[1] - full[0]
    assert full[0] + 0.2 * span < lo < hi < full[0] + 0.55 * span, (full, lo, hi)
    assert x_range(cdp, "voltage") == [lo, hi]  # the group follows
    assert cdp.eval("document.querySelector('[data-range=run]').textContent") != "whole run"
    cdp.screenshot(shots_dir(tmp_path) / "report_zoomed.png")
    cdp.eval("document.querySelector('button[data-reset=run]').click()")
    assert x_range(cdp, "current") == pytest.approx(full)


def test_wheel_zooms_around_the_cursor(loaded: Cdp) -> None:
    cdp = loaded
    full = x_range(cdp, "voltage")
    box = over_box(cdp, "voltage")
    x, y = box["x"] + box["w"] * 0.5, box["y"] + box["h"] / 2
    cdp.mouse("mouseMoved", x, y)
    cdp.mouse("mouseWheel", x, y, deltaX=0, deltaY=-120)
    lo, hi = x_range(cdp, "voltage")
    assert full[0] < lo < hi < full[1] and hi - lo == pytest.approx(0.75 * (full[1] - full[0]))
    cdp.mouse("mouseWheel", x, y, deltaX=0, deltaY=120)
    assert x_range(cdp, "voltage") == pytest.approx(full)


def test_hover_shows_the_values_at_the_cursor(loaded: Cdp, tmp_path: Path) -> None:
    cdp = loaded
    before = cdp.eval(
        "[...ppCharts['current'].root.querySelectorAll('.u-value')].map(e => e.textContent)"
    )
    assert all(v in ("–", "") for v in before[1:]), before
    box = over_box(cdp, "current")
    cdp.mouse("mouseMoved", box["x"] + box["w"] * 0.6, box["y"] + box["h"] / 2)
    cdp.wait("ppCharts['current'].cursor.idx != null")
    values = cdp.eval(
        "[...ppCharts['current'].root.querySelectorAll('.u-value')].map(e => e.textContent)"
    )
    assert values[0].count(":") == 2  # the time, h:mm:ss.s
    assert all(v.endswith(" A") for v in values[1:3]), values  # A and B, in amperes
    # the other charts of the group show the same moment (shared cursor)
    soc = cdp.eval("[...ppCharts['soc'].root.querySelectorAll('.u-value')].map(e => e.textContent)")
    assert soc[0] == values[0] and soc[1].endswith(" %")
    cdp.screenshot(shots_dir(tmp_path) / "report_hover.png")


def test_nominal_channels_are_one_line_each(loaded: Cdp) -> None:
    cdp = loaded
    lines = cdp.eval("[...document.querySelectorAll('ul.nominal li')].map(e => e.textContent)")
    lim = [x for x in lines if x.startswith("lim_")]
    assert lim and all(x.endswith("nominal (ok throughout)") for x in lim), lines
    charted = cdp.eval(
        "Object.keys(JSON.parse(document.getElementById('pp-data').textContent).charts)"
    )
    assert not [c for c in charted if c.startswith("st-lim_")]
    # the channels that did change are folded away until asked for, then drawn
    n = cdp.eval("document.querySelectorAll('details .chart[data-state=drawn]').length")
    assert n == 0
    cdp.eval("document.querySelectorAll('#controllers details').forEach(d => d.open = true)")
    cdp.wait("document.querySelectorAll('details .chart[data-state=drawn]').length > 0")
