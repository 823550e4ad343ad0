"""What a person sees (#29), in a real headless Chromium against real servers and real files:
the example picker shows the scenario on show and *start* asks before replacing a running run;
the per-cell bars stand on the cell set's absolute voltage window with horizontal labels on the
card's white; a recording does not say "live" and finds its report whatever it is called; the
events table hides routine noise by default; the run report's voltage axis spans the batteries
(the bus's drops marked) and has no "run ok" badge beside the verdict; the replay report's
charts zoom like the run report's; and no page scrolls sideways at 390 px.

Screenshots go to ``$PACKPILOT_ARTIFACTS`` (default: the test's tmp directory).
"""

from __future__ import annotations

import base64
import os
import re
import threading
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.model.cell import load_parameter_set
from packpilot.report.html import report_from_db
from packpilot.sim.runner import Runner
from packpilot.web.app import Dashboard
from packpilot.web.session import Library
from tests import test_web_browser as wb
from tests.cdp import open_page
from tests.conftest import EXAMPLES

pytestmark = wb.pytestmark
browser = wb.browser
"""The module-scoped headless Chromium of the dashboard browser test (a fixture)."""

PHONE_W = 390
SMART = EXAMPLES / "smart_battery.toml"
MISSION = EXAMPLES / "uav_mission.toml"


def shot(cdp: wb.Cdp, name: str, tmp_path: Path) -> None:
    png = base64.b64decode(cdp.call("Page.captureScreenshot", format="png")["data"])
    (Path(os.environ.get("PACKPILOT_ARTIFACTS", tmp_path)) / name).write_bytes(png)


def serve(dash: Dashboard) -> threading.Thread:
    thread = threading.Thread(target=dash.serve, name="uvicorn-ux", daemon=True)
    dash.start()
    thread.start()
    deadline = time.monotonic() + 10.0
    while dash.server is None or not dash.server.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    return thread


def example_runner(path: Path, duration_s: float = 120.0) -> Runner:
    d = tomllib.loads(path.read_text(encoding="utf-8"))
    d["sim"].update(duration_s=duration_s, progress=False)
    return Runner(parse_config(d), progress=False)


def click(cdp: wb.Cdp, element_id: str) -> None:
    cdp.eval(f"document.getElementById('{element_id}').click()")


def choose(cdp: wb.Cdp, select_id: str, value: str) -> None:
    cdp.eval(
        f"(() => {{ const s = document.getElementById('{select_id}'); s.value = '{value}';"
        " s.dispatchEvent(new Event('change')); })()"
    )


def phone(cdp: wb.Cdp, on: bool) -> None:
    w, h = (PHONE_W, 1600) if on else (wb.WIDTH, wb.HEIGHT)
    cdp.call("Emulation.setDeviceMetricsOverride", width=w, height=h, deviceScaleFactor=1,
             mobile=on)  # fmt: skip


def sideways(cdp: wb.Cdp) -> tuple[int, list[str]]:
    """The page's scroll width and the elements sticking out past the phone's width."""
    width = int(cdp.eval("document.documentElement.scrollWidth"))
    # sticking out and not inside a box that scrolls (a wide table may scroll in its panel)
    wide = cdp.eval(
        "(() => { const scrolls = (e) => { for (let p = e.parentElement; p && p !== document.body;"
        " p = p.parentElement) { if (['auto', 'scroll', 'hidden'].includes("
        " getComputedStyle(p).overflowX)) return true; } return false; };"
        f" return [...document.querySelectorAll('body *')].filter(e => {{"
        f" const r = e.getBoundingClientRect(); return r.width > 0 && r.right > {PHONE_W + 1}"
        " && !scrolls(e); }).slice(0, 8).map(e => e.tagName + '#' + e.id + '.' +"
        " e.className); })()"
    )
    return width, wide


# --------------------------------------------------------------------------- live example


@pytest.fixture(scope="module")
def example_server() -> Iterator[Dashboard]:
    """uav_mission (two batteries of six one-cell groups), started from its example file (as
    `packpilot dashboard uav_mission`), slowly, so it is still running while the tests look."""
    dash = Dashboard(
        example_runner(MISSION, 600.0),
        scenario="uav_mission",
        source=str(MISSION),
        speed=2.0,
        port=0,
        library=Library.of_dirs([EXAMPLES], None),
        make_runner=lambda p: example_runner(p, 600.0),
    )
    thread = serve(dash)
    yield dash
    dash.stop()
    thread.join(10.0)


def test_cell_bars_stand_on_the_cell_sets_window(
    browser: wb.Cdp, example_server: Dashboard, tmp_path: Path
) -> None:
    browser.call("Page.navigate", url=example_server.url)
    browser.wait_body(lambda d: int(d.get("samples", 0)) > 0, 30.0)
    browser.wait("document.querySelectorAll('.cellbar[data-v]:not([data-v=\"\"])').length === 12")
    prm = load_parameter_set("uav_5ah")
    lo, hi = float(prm.v_min_v), float(prm.v_max_v)  # six groups of one cell each
    axis = browser.eval(
        "(() => { const b = document.querySelector('.cellbars');"
        " return [Number(b.dataset.axisLo), Number(b.dataset.axisHi),"
        " [...document.querySelector('.cellaxis').children].map(t => t.textContent)]; })()"
    )
    assert axis[0] == pytest.approx(lo) and axis[1] == pytest.approx(hi), axis
    assert axis[2] == [f"{lo:.1f}", f"{(lo + hi) / 2:.2f}", f"{hi:.1f}"]
    bars = browser.eval(
        "[...document.querySelector('.cellbars').children].map(b => { const f = b.children[0],"
        " l = b.children[1], fr = f.getBoundingClientRect(), lr = l.getBoundingClientRect(),"
        " br = b.getBoundingClientRect(), cs = getComputedStyle(b);"
        " return {v: Number(b.dataset.v), fill: fr.height, track: br.height -"
        " parseFloat(cs.paddingTop), lab: l.textContent, labBottom: lr.bottom,"
        " fillTop: fr.top, labW: lr.width, barW: br.width,"
        " transform: getComputedStyle(l).transform}; })"
    )
    assert len(bars) == 6
    for b in bars:
        # the fill is the voltage's share of the cell set's window: absolute, not the spread
        want = (b["v"] - lo) / (hi - lo) * b["track"]
        assert abs(b["fill"] - want) <= 1.0, (b, want)
        # the label: horizontal (no rotation), the bar's voltage, above the fill, inside the bar
        m = re.fullmatch(r"matrix\(([-\d.e]+), ([-\d.e]+), ([-\d.e]+), ([-\d.e]+), .*\)",
                         b["transform"])  # fmt: skip
        assert b["transform"] == "none" or (m and float(m[2]) == 0 and float(m[3]) == 0), b
        assert abs(float(b["lab"]) - b["v"]) <= 0.0005 + 1e-9  # the voltage, 3 decimals
        assert b["labBottom"] <= b["fillTop"] + 0.5 and b["labW"] <= b["barW"], b
    # six groups within a few mV of each other: the bars are nearly equal, as they should look
    fills = [b["fill"] for b in bars]
    assert max(fills) - min(fills) < 0.1 * max(fills)
    shot(browser, "ux_live.png", tmp_path)


def test_picker_shows_the_scenario_on_show_and_start_asks_first(
    browser: wb.Cdp, example_server: Dashboard, tmp_path: Path
) -> None:
    browser.call("Page.navigate", url=example_server.url)
    browser.wait_body(lambda d: int(d.get("samples", 0)) > 0, 30.0)
    browser.wait("document.getElementById('example-select').options.length > 3")
    assert browser.eval("document.getElementById('example-select').value") == "uav_mission"
    assert browser.eval("document.getElementById('btn-start').textContent") == "restart"
    choose(browser, "example-select", "uav_dual_parallel")
    click(browser, "btn-start")
    # a running run is not replaced on one click: the page asks, naming both
    assert browser.eval("document.getElementById('confirm-start').hidden") is False
    text = browser.eval("document.getElementById('confirm-text').textContent")
    assert "uav_mission is running" in text and "uav_dual_parallel" in text, text
    shot(browser, "ux_confirm.png", tmp_path)
    time.sleep(0.5)
    assert example_server.live.source == str(MISSION)
    click(browser, "btn-cancel-start")
    assert browser.eval("document.getElementById('confirm-start').hidden") is True
    time.sleep(0.3)
    assert example_server.live.source == str(MISSION)
    click(browser, "btn-start")
    click(browser, "btn-confirm-start")
    deadline = time.monotonic() + 60.0
    while example_server.live.source != "example uav_dual_parallel":
        assert time.monotonic() < deadline, browser.eval(
            "document.getElementById('control-msg').textContent"
        )
        time.sleep(0.1)
    # after the switch the picker shows the example now on show
    browser.wait("document.getElementById('source').textContent === '(example uav_dual_parallel)'")
    browser.wait("document.getElementById('example-select').value === 'uav_dual_parallel'")


def test_a_page_without_an_example_on_show_offers_no_default() -> None:
    """A scenario that is not a shipped example: the picker's first entry is a placeholder and
    *start* is disabled until an example is chosen (no one-click replacement by accident)."""
    from packpilot.web.live import LiveRun
    from packpilot.web.session import Session

    live = LiveRun(scenario="mine", source="/somewhere/mine.toml")
    session = Session(live, library=Library.of_dirs([EXAMPLES], None), make_runner=lambda p: p)
    assert session.catalog()["current"] is None
    live.source = str(SMART)
    assert session.catalog()["current"] == "smart_battery"
    live.source = "example uav_mission"
    assert session.catalog()["current"] == "uav_mission"


# --------------------------------------------------------------------------- a recording


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Dashboard, Path]]:
    """smart_battery's whole flight (it drains the battery below empty: alarms), recorded, its
    report written as ``report.html`` (not the default name), opened as a recording."""
    runs = tmp_path_factory.mktemp("ux_runs")
    db = runs / "flight.sqlite"
    d = tomllib.loads(SMART.read_text(encoding="utf-8"))
    d["sim"]["progress"] = False
    with SQLiteRecorder(db) as rec:
        Runner(parse_config(d), recorder=rec, progress=False).run()
    report_from_db(db, runs / "report.html")
    (runs / "other.html").write_text("<html><head><title>x</title></head></html>")
    dash = Dashboard(recording=db, port=0, library=Library.of_dirs([], runs, [db]))
    thread = serve(dash)
    yield dash, db
    dash.stop()
    thread.join(10.0)


def test_a_recording_finds_its_report_and_does_not_say_live(
    browser: wb.Cdp, recorded: tuple[Dashboard, Path], tmp_path: Path
) -> None:
    dash, db = recorded
    browser.call("Page.navigate", url=dash.url)
    browser.wait_body(lambda d: d.get("state") == "finished", 60.0)
    assert dash.session.report_path == db.with_name("report.html")
    assert browser.eval("document.getElementById('report-link').hidden") is False
    assert browser.eval("document.getElementById('kind').textContent") == "recording"
    text = browser.eval("document.body.innerText")
    assert not re.search(r"\blive\b", text, re.I), re.findall(r".{30}\blive\b.{30}", text, re.I)
    # the events table leads with what matters: routine events only under "all"
    assert browser.eval("document.getElementById('filter-severity').value") == "important"
    raw = load_run(db)
    important = re.compile(r"Mode|Stage|Joined|Reset|Resupplied", re.I)
    from packpilot.contract.severity import Severity, row_of

    want = [e for e in raw.events
            if row_of(e.kind).severity > Severity.INFO or important.search(e.kind)]  # fmt: skip
    assert int(browser.body()["eventsShown"]) == min(len(want), 1000)
    choose(browser, "filter-severity", "info")
    assert int(browser.body()["eventsShown"]) == min(len(raw.events), 1000)
    choose(browser, "filter-severity", "important")
    shot(browser, "ux_recording.png", tmp_path)


def test_no_page_scrolls_sideways_at_390_px(
    browser: wb.Cdp,
    example_server: Dashboard,
    recorded: tuple[Dashboard, Path],
    run_report: Path,
    flight_report: Path,
    tmp_path: Path,
) -> None:
    dash = recorded[0]
    phone(browser, True)
    try:
        pages: list[tuple[str, str, str]] = [
            ("live", example_server.url, "Number(document.body.dataset.samples) > 0"),
            ("recording", dash.url, "document.body.dataset.state === 'finished'"),
            ("report", run_report.resolve().as_uri(), "document.body.dataset.ready === '1'"),
            ("replay", flight_report.resolve().as_uri(), "document.body.dataset.ready === '1'"),
        ]
        for name, url, ready in pages:
            open_page(browser, url, ready)
            time.sleep(0.4)
            width, wide = sideways(browser)
            assert width <= PHONE_W, (name, width, wide, browser.eval(
                "[...document.querySelectorAll('body, body *')].filter(e =>"
                " e.scrollWidth > e.clientWidth + 1 && getComputedStyle(e).overflowX =="
                " 'visible').slice(0, 6).map(e => e.tagName + '.' + e.className + ' ' +"
                " e.scrollWidth + '/' + e.clientWidth)"
            ))  # fmt: skip
            assert not wide, (name, wide)
            shot(browser, f"ux_phone_{name}.png", tmp_path)
        # the recording's alarms at phone width: every row's text inside its panel, not cut off
        open_page(browser, dash.url, "document.body.dataset.state === 'finished'")
        time.sleep(0.3)
        cut = browser.eval(
            "(() => { const p = document.getElementById('alarms-panel');"
            " const r = p.getBoundingClientRect();"
            " return [p.scrollWidth - p.clientWidth, document.querySelectorAll('#alarms tbody tr')"
            ".length, [...p.querySelectorAll('td')].filter(td => td.getBoundingClientRect().right"
            " > r.right + 0.5).length]; })()"
        )
        assert cut[1] >= 1 and cut[0] <= 1 and cut[2] == 0, cut
        # the schematic's text is drawn at a readable size (compact layout at phone width)
        sizes = browser.eval(
            "[...document.querySelectorAll('#pack-svg text')].map(t =>"
            " t.getBoundingClientRect().height)"
        )
        assert sizes and min(sizes) >= 11.0, sizes
        assert browser.eval("document.getElementById('pack-svg').dataset.layout") == "compact"
    finally:
        phone(browser, False)


# --------------------------------------------------------------------------- the reports


@pytest.fixture(scope="module")
def run_report(recorded: tuple[Dashboard, Path]) -> Path:
    return recorded[1].with_name("report.html")


def test_the_run_reports_voltage_axis_spans_the_batteries(
    browser: wb.Cdp, run_report: Path, recorded: tuple[Dashboard, Path], tmp_path: Path
) -> None:
    raw = load_run(recorded[1])
    open_page(browser, run_report.resolve().as_uri(), "document.body.dataset.ready === '1'")
    y = browser.eval("[ppCharts.voltage.scales.y.min, ppCharts.voltage.scales.y.max]")
    volts = raw.trace.channel("voltage_v")
    lo, hi = float(np.nanmin(volts)), float(np.nanmax(volts))
    margin = 0.06 * (hi - lo) + 1e-6
    assert lo - margin - 0.06 <= y[0] <= lo and hi <= y[1] <= hi + margin + 0.06, (y, lo, hi)
    # the header: the verdict, and no "run ok" badge beside it
    badges = browser.eval("[...document.querySelectorAll('.sub .badge')].map(b => b.textContent)")
    assert badges == [browser.eval("document.querySelector('.sub .badge').textContent")]
    assert badges[0] in ("OK", "WARNING", "ALARM", "FAULT") and "run ok" not in browser.eval(
        "document.querySelector('.sub').textContent"
    )
    shot(browser, "ux_report.png", tmp_path)


@pytest.fixture(scope="module")
def flight_report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    pytest.importorskip("pyulog")
    from packpilot.control.protection import ProtectionConfig
    from packpilot.control.sequencing import SequencingConfig
    from packpilot.replay.common import LogOptions
    from packpilot.replay.flight import replay_flight
    from packpilot.report.flight import write_flight_page

    fr = replay_flight(EXAMPLES / "logs" / "px4_two_batteries.ulg", ProtectionConfig(),
                       SequencingConfig(), LogOptions(assume_temp_c=25.0),
                       parallel=("A", "B"))  # fmt: skip  # the sample's two packs were in parallel
    out = tmp_path_factory.mktemp("flight") / "flight.html"
    write_flight_page(fr, out)
    return out


def test_the_replay_reports_charts_zoom_like_the_run_reports(
    browser: wb.Cdp, flight_report: Path, tmp_path: Path
) -> None:
    open_page(browser, flight_report.resolve().as_uri(), "document.body.dataset.ready === '1'")
    assert [u for u in browser.requests if not u.startswith("file://")] == []
    ids = browser.eval("Object.keys(ppCharts)")
    assert {"A-cell", "B-cell", "seq-voltage", "seq-fets"} <= set(ids), ids
    full = browser.eval(
        "[ppCharts['seq-voltage'].scales.x.min, ppCharts['seq-voltage'].scales.x.max]"
    )
    box: dict[str, float] = browser.eval(
        "(() => { const o = ppCharts['seq-voltage'].over; o.scrollIntoView({block: 'center'});"
        " const r = o.getBoundingClientRect(); return {x: r.left, y: r.top, w: r.width,"
        " h: r.height}; })()"
    )
    x, y = box["x"] + box["w"] * 0.5, box["y"] + box["h"] / 2
    browser.mouse("mouseMoved", x, y)
    browser.mouse("mouseWheel", x, y, deltaX=0, deltaY=-120)
    lo, hi = browser.eval(
        "[ppCharts['seq-voltage'].scales.x.min, ppCharts['seq-voltage'].scales.x.max]"
    )
    assert full[0] < lo < hi < full[1]
    # every chart of the page follows (one group, as in the run report)
    assert browser.eval("[ppCharts['A-cell'].scales.x.min, ppCharts['A-cell'].scales.x.max]") == [
        lo, hi,
    ]  # fmt: skip
    heads = browser.eval("[...document.querySelectorAll('#verdict li')].map(e => e.textContent)")
    assert any("39.5 A flowing into B" in h for h in heads), heads
    assert not any(re.search(r"\bbattery \d\b", h) for h in heads), heads
    shot(browser, "ux_replay.png", tmp_path)
