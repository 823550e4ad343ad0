"""#17 §2 in a real headless Chromium against a real uvicorn on loopback: the pause / resume /
speed controls, the pack schematic, the per-cell voltage bars with their min / max and
balancing marks, the event filter, starting an example from the page, and a recorded run opened
and scrubbed. Uses the browser harness of ``test_web_browser.py``; screenshots are written to
``$PACKPILOT_ARTIFACTS`` (default: the test's tmp_path) for a look.
"""

from __future__ import annotations

import base64
import os
import re
import threading
import time
import tomllib
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.sim.runner import Runner
from packpilot.web.app import Dashboard
from packpilot.web.session import Library
from tests import test_web_browser as wb
from tests.conftest import EXAMPLES
from tests.test_web_security import recording

pytestmark = wb.pytestmark

__all__ = ["recording"]  # a module-scoped fixture of test_web_security, shared

browser = wb.browser
"""The module-scoped headless Chromium of the dashboard browser test (a fixture)."""


def shot(browser: wb.Cdp, name: str, tmp_path: Path) -> bytes:
    png = base64.b64decode(browser.call("Page.captureScreenshot", format="png")["data"])
    (Path(os.environ.get("PACKPILOT_ARTIFACTS", tmp_path)) / name).write_bytes(png)
    return png


def serve(dash: Dashboard) -> threading.Thread:
    thread = threading.Thread(target=dash.serve, name="uvicorn-controls", daemon=True)
    dash.start()
    thread.start()
    deadline = time.monotonic() + 10.0
    while dash.server is None or not dash.server.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.02)
    return thread


def short_example(path: Path) -> Runner:
    d = tomllib.loads(path.read_text(encoding="utf-8"))
    d["sim"].update(duration_s=60.0, progress=False)
    return Runner(parse_config(d), progress=False)


def spread_pack() -> dict[str, Any]:
    """Two 6S batteries whose cells differ, on a flight load, with protection."""
    data = wb.scenario()
    for b, soc in zip(data["pack"]["batteries"], (0.9, 0.7), strict=True):
        b.update(series_groups=6, cells_per_group=1, soc0=None)
        b["group_soc0"] = [soc, soc - 0.04, soc + 0.03, soc, soc - 0.01, soc + 0.01]
        b.pop("soc0")
    data["sim"]["duration_s"] = 900.0
    return data


@pytest.fixture(scope="module")
def live_server() -> Iterator[Dashboard]:
    runner = Runner(parse_config(spread_pack()), progress=False)
    dash = Dashboard(
        runner,
        scenario="controls_test",
        speed=5.0,
        port=0,
        library=Library.of_dirs([EXAMPLES], None),
        make_runner=short_example,
    )
    thread = serve(dash)
    yield dash
    dash.stop()
    thread.join(10.0)


def js(browser: wb.Cdp, expr: str) -> Any:
    return browser.eval(expr)


def test_controls_schematic_and_cell_bars_on_a_live_run(
    browser: wb.Cdp, live_server: Dashboard, tmp_path: Path
) -> None:
    browser.call("Page.navigate", url=live_server.url)
    browser.wait_body(lambda d: int(d.get("samples", 0)) > 0 and d.get("kind") == "live", 30.0)
    live = live_server.live
    # --- the schematic: a bus, a load, two FET pairs drawn with their live state
    fets = js(
        browser,
        "[...document.querySelectorAll('[data-fet]')].map(e => [e.dataset.fet, e.dataset.state])",
    )
    assert sorted(f for f, _ in fets) == ["A:CHG", "A:DSG", "B:CHG", "B:DSG"], fets
    assert dict(fets)["A:DSG"] == "on" and dict(fets)["B:DSG"] == "on"  # both fly the load
    assert all(s in ("on", "off", "diode") for _, s in fets)
    assert js(browser, "document.querySelector('[data-part=load]').dataset.state") == "on"
    assert js(browser, "document.querySelector('[data-part=charger]')") is None  # none here
    assert js(browser, "document.querySelectorAll('#pack-svg [data-battery]').length") == 2
    # --- per-cell bars: six per battery, one min and one max, in the right places
    bars = js(
        browser,
        "[...document.querySelectorAll('.panel.bat')].map(c =>"
        " [...c.querySelectorAll('.cellbar')].map(b =>"
        " [Number(b.dataset.v), b.classList.contains('min'),"
        " b.classList.contains('max')]))",
    )
    assert [len(b) for b in bars] == [6, 6], bars
    for card in bars:
        v = [x[0] for x in card]
        assert [x[1] for x in card] == [k == int(np.argmin(v)) for k in range(6)], card
        assert [x[2] for x in card] == [k == int(np.argmax(v)) for k in range(6)], card
    # drawn to scale on the cell set's absolute window (the axis the card ticks)
    scale = js(
        browser,
        "(() => { const c = document.querySelectorAll('.panel.bat')[0].querySelector('.cellbars');"
        " return [Number(c.dataset.axisLo), Number(c.dataset.axisHi), [...c.children].map(b =>"
        " [b.children[0].getBoundingClientRect().height, b.getBoundingClientRect().height -"
        " parseFloat(getComputedStyle(b).paddingTop)])]; })()",
    )
    a_lo, a_hi, hs = scale
    for (v, _, _), (h, track) in zip(bars[0], hs, strict=True):
        assert abs(h - (v - a_lo) / (a_hi - a_lo) * track) <= 1.0, (v, h, track, a_lo, a_hi)
    # --- headline: a flight load on both batteries has a time to go
    assert js(browser, "document.getElementById('hl-go').textContent") != "—"
    # --- pause from the page holds the run
    js(browser, "document.getElementById('btn-pause').click()")
    browser.wait_body(lambda d: d.get("paused") == "true", 10.0)
    assert live.paused
    time.sleep(0.3)
    t0 = live.status()["t_s"]
    time.sleep(0.6)
    assert live.status()["t_s"] == t0
    assert js(browser, "document.getElementById('btn-pause').textContent") == "resume"
    assert js(browser, "document.getElementById('run-state').textContent") == "paused"
    shot(browser, "dashboard_paused.png", tmp_path)
    # --- speed from the page
    js(
        browser,
        "(() => { const s = document.getElementById('speed-select'); s.value = '50';"
        " s.dispatchEvent(new Event('change')); })()",
    )
    browser.wait_body(lambda d: d.get("speed") == "50", 10.0)
    assert live.speed == 50.0 and live.paused
    js(browser, "document.getElementById('btn-pause').click()")
    browser.wait_body(lambda d: d.get("paused") == "false", 10.0)
    t0 = live.status()["t_s"]
    time.sleep(1.0)
    assert live.status()["t_s"] - t0 > 15.0  # ~50 s of flight per second now
    # --- the event filter: "important" by default, then "all"
    assert js(browser, "document.getElementById('filter-severity').value") == "important"
    js(
        browser,
        "(() => { const v = document.getElementById('filter-severity'); v.value = 'info';"
        " v.dispatchEvent(new Event('change')); })()",
    )
    n_all = int(browser.body()["eventsShown"])
    assert n_all > 0
    js(
        browser,
        "(() => { const s = document.getElementById('filter-battery'); s.value = 'B';"
        " s.dispatchEvent(new Event('change')); })()",
    )
    shown = js(
        browser,
        "[...document.querySelectorAll('#events tbody tr')].map(r => r.cells[2].textContent)",
    )
    assert set(shown) <= {"B"}
    js(
        browser,
        "(() => { const s = document.getElementById('filter-battery'); s.value = '*';"
        " s.dispatchEvent(new Event('change'));"
        " const v = document.getElementById('filter-severity'); v.value = 'warning';"
        " v.dispatchEvent(new Event('change')); })()",
    )
    sev = js(
        browser, "[...document.querySelectorAll('#events tbody tr')].map(r => r.dataset.severity)"
    )
    assert set(sev) <= {"warning", "alarm", "fault"} and len(sev) < n_all
    js(
        browser,
        "(() => { const v = document.getElementById('filter-severity'); v.value = 'info';"
        " v.dispatchEvent(new Event('change')); })()",
    )
    png = shot(browser, "dashboard_controls.png", tmp_path)
    assert len(png) > 60_000


def test_phone_layout_has_no_sideways_scroll(
    browser: wb.Cdp, live_server: Dashboard, tmp_path: Path
) -> None:
    browser.call(
        "Emulation.setDeviceMetricsOverride",
        width=390,
        height=1600,
        deviceScaleFactor=1,
        mobile=True,
    )
    try:
        browser.call("Page.navigate", url=live_server.url)
        browser.wait_body(lambda d: int(d.get("samples", 0)) > 0, 30.0)
        time.sleep(0.3)
        width = js(browser, "document.documentElement.scrollWidth")
        wide = js(
            browser,
            "[...document.querySelectorAll('body *')].filter(e =>"
            " e.getBoundingClientRect().right > 391).slice(0, 8).map(e =>"
            " e.tagName + '#' + e.id + '.' + e.className)",
        )
        assert width <= 390, (width, wide)
        svg_w = js(browser, "document.getElementById('pack-svg').getBoundingClientRect().width")
        assert 0 < svg_w <= 390
        shot(browser, "dashboard_phone.png", tmp_path)
    finally:
        browser.call(
            "Emulation.setDeviceMetricsOverride",
            width=wb.WIDTH,
            height=wb.HEIGHT,
            deviceScaleFactor=1,
            mobile=False,
        )


def test_starting_an_example_from_the_page(
    browser: wb.Cdp, live_server: Dashboard, tmp_path: Path
) -> None:
    browser.call("Page.navigate", url=live_server.url)
    browser.wait_body(lambda d: int(d.get("samples", 0)) > 0, 30.0)
    # the menu comes from /api/catalog, fetched once the page is greeted: it may land after
    # the first samples (it did once the server also predicts the state of power)
    browser.wait("document.getElementById('example-select').options.length > 1", 30.0)
    opts = js(browser, "[...document.getElementById('example-select').options].map(o => o.value)")
    assert "evtol_charging" in opts and "uav_mission" in opts
    js(
        browser,
        "(() => { const s = document.getElementById('example-select');"
        " s.value = 'evtol_charging'; s.dispatchEvent(new Event('change'));"
        " document.getElementById('btn-start').click(); })()",
    )
    # the run on show is running: the page asks before replacing it
    if not js(browser, "document.getElementById('confirm-start').hidden"):
        js(browser, "document.getElementById('btn-confirm-start').click()")
    deadline = time.monotonic() + 60.0
    source = "document.getElementById('source').textContent"
    while js(browser, source) != "(example evtol_charging)":
        assert time.monotonic() < deadline, js(
            browser, "document.getElementById('control-msg').textContent"
        )
        time.sleep(0.1)
    browser.wait_body(lambda d: int(d.get("samples", 0)) > 0, 30.0)
    assert live_server.live.source == "example evtol_charging"
    # the eVTOL pack has a charger and an auxiliary battery: both in the schematic
    assert js(browser, "document.querySelector('[data-part=charger]') !== null")
    names = js(browser, "[...document.querySelectorAll('#pack-svg text')].map(t => t.textContent)")
    assert any(n.endswith("(aux)") for n in names), names
    # the charging stage is said in words, not as a bare "S40"
    browser.wait(
        "[...document.querySelectorAll('.panel.bat .line')].some(l =>"
        " l.textContent.includes('charging'))",
        30.0,
    )
    stages = js(
        browser,
        "[...document.querySelectorAll('.panel.bat .line')].filter(l =>"
        " l.textContent.includes('charging')).map(l => l.textContent)",
    )
    assert stages and not any(re.search(r"charging\s*S\d0\s*$", x) for x in stages), stages
    time.sleep(1.0)
    shot(browser, "dashboard_evtol.png", tmp_path)


@pytest.fixture(scope="module")
def recorded_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Dashboard, Path]]:
    """The 12S equalization example, 300 s, recorded to SQLite and opened from a runs dir."""
    runs = tmp_path_factory.mktemp("runs")
    db = runs / "eq.sqlite"
    d = tomllib.loads((EXAMPLES / "equalization_uav12s.toml").read_text(encoding="utf-8"))
    d["sim"].update(duration_s=300.0, progress=False)
    with SQLiteRecorder(db) as rec:
        Runner(parse_config(d), recorder=rec, progress=False).run()
    (runs / "eq.html").write_text("<html><body>report of eq</body></html>", encoding="utf-8")
    dash = Dashboard(recording=db, port=0, library=Library.of_dirs([], runs, [db]))
    thread = serve(dash)
    yield dash, db
    dash.stop()
    thread.join(10.0)


def test_a_recording_scrubs_with_balancing_marks(
    browser: wb.Cdp, recorded_server: tuple[Dashboard, Path], tmp_path: Path
) -> None:
    dash, db = recorded_server
    raw = load_run(db)
    browser.call("Page.navigate", url=dash.url)
    data = browser.wait_body(lambda d: d.get("state") == "finished", 30.0)
    assert data["kind"] == "recorded"
    assert js(browser, "document.getElementById('scrub-controls').hidden") is False
    assert js(browser, "document.getElementById('btn-pause').hidden") is True
    # the report written beside the recording is linked
    assert js(browser, "document.getElementById('report-link').hidden") is False
    href = js(browser, "document.getElementById('report-link').href")
    assert href == dash.url + "report"
    with urllib.request.urlopen(href, timeout=5) as resp:
        assert b"report of eq" in resp.read()
    k = int(np.searchsorted(raw.trace.t_s, 150.0))
    t = float(raw.trace.t_s[k])
    js(
        browser,
        f"(() => {{ const s = document.getElementById('scrub'); s.value = '{t}';"
        " s.dispatchEvent(new Event('input')); })()",
    )
    browser.wait_body(lambda d: d.get("scrubbed") == str(k), 10.0)
    eq = np.array([raw.trace.status[f"eq_i_a_g{g}"][k][0] for g in range(12)], dtype=float)
    want = [bool(abs(x) > 1e-4) for x in eq]
    assert any(want) and not all(want)  # some groups balance at 150 s, some do not
    bars = js(
        browser,
        "[...document.querySelectorAll('.cellbar')].map(b =>"
        " [b.classList.contains('balancing'), b.classList.contains('min'),"
        " b.classList.contains('max')])",
    )
    assert [b[0] for b in bars] == want
    gv = raw.trace.group_v[k, 0]
    assert [b[1] for b in bars].index(True) == int(np.argmin(gv))
    assert [b[2] for b in bars].index(True) == int(np.argmax(gv))
    # events after the scrubbed moment are hidden; the table says how many of all
    js(
        browser,
        "(() => { const v = document.getElementById('filter-severity'); v.value = 'info';"
        " v.dispatchEvent(new Event('change')); })()",
    )
    shown = js(browser, "[...document.querySelectorAll('#events tbody tr')].length")
    assert shown == sum(1 for e in raw.events if e.t_s <= t) < len(raw.events)
    # moving the scrubber elsewhere changes the bars: nothing balances at 60 s
    k0 = int(np.searchsorted(raw.trace.t_s, 60.0))
    t0 = raw.trace.t_s[k0]
    js(
        browser,
        f"(() => {{ const s = document.getElementById('scrub'); s.value = '{t0}';"
        " s.dispatchEvent(new Event('input')); })()",
    )
    browser.wait_body(lambda d: d.get("scrubbed") == str(k0), 10.0)
    assert js(browser, "document.querySelectorAll('.cellbar.balancing').length") == 0
    js(
        browser,
        f"(() => {{ const s = document.getElementById('scrub'); s.value = '{t}';"
        " s.dispatchEvent(new Event('input')); })()",
    )
    browser.wait_body(lambda d: d.get("scrubbed") == str(k), 10.0)
    time.sleep(0.3)
    shot(browser, "dashboard_recording.png", tmp_path)


def test_the_page_follows_a_run_another_process_writes(
    browser: wb.Cdp, recording: Path, tmp_path: Path
) -> None:
    """`packpilot dashboard FILE` on a run still being written: the page says it is attached
    and read-only (no pace controls, no scrubber), grows with the file, and turns into the
    scrubbable recording when the writer finishes."""
    from tests.test_web_follow import PacedWriter

    writer = PacedWriter(recording, tmp_path / "growing.sqlite", holds=(50,))
    writer.start()
    dash = None
    thread = None
    try:
        assert writer.reached[50].wait(30.0)
        dash = Dashboard(recording=writer.dst, port=0)
        thread = serve(dash)
        browser.call("Page.navigate", url=dash.url)
        browser.wait_body(lambda d: d.get("kind") == "attached", 30.0)
        assert js(browser, "document.getElementById('kind').textContent") == (
            "attached (read-only)"
        )
        assert js(browser, "document.getElementById('pace-controls').hidden") is True
        assert js(browser, "document.getElementById('scrub-controls').hidden") is True
        assert js(browser, "document.getElementById('run-state').textContent") == "running"
        writer.go[50].set()
        browser.wait_body(lambda d: d.get("kind") == "recorded" and d.get("state") == "finished",
                          30.0)  # fmt: skip
        assert js(browser, "document.getElementById('kind').textContent") == "recording"
        assert js(browser, "document.getElementById('scrub-controls').hidden") is False
        n_events = js(browser, "document.querySelectorAll('#events tbody tr').length")
        assert n_events == len(writer.raw.events) > 0
    finally:
        writer.go[50].set()
        writer.join(30.0)
        if dash is not None:
            dash.stop()
        if thread is not None:
            thread.join(10.0)
    assert writer.error is None
