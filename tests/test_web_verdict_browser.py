"""Issue #17 §1 on the live dashboard, in a real headless Chromium: the verdict badge and the
alarms table (from the same checks as the CLI and the report), and battery colours that are
never the alarm colour. Uses the browser harness of ``test_web_browser.py`` (loopback only).
"""

from __future__ import annotations

import base64
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from packpilot.config import parse_config
from packpilot.sim.runner import Runner
from packpilot.web.app import Dashboard
from tests import test_web_browser as wb
from tests.conftest import dual_pack

pytestmark = wb.pytestmark

browser = wb.browser
"""The module-scoped headless Chromium of the dashboard browser test (a fixture)."""

ARTIFACTS = "PACKPILOT_ARTIFACTS"
"""Set to a directory to keep the screenshot for a look (default: the test's tmp_path)."""


def _serve(data: dict[str, object], scenario: str) -> Iterator[Dashboard]:
    """A dashboard of ``data`` at 4x real time on a loopback port, until the fixture ends."""
    yield from wb.serve(Runner(parse_config(data), progress=False), scenario, 4.0)


@pytest.fixture(scope="module")
def cross_charge() -> Iterator[Dashboard]:
    """Two batteries 2 V apart, no controller, a hover load: A charges B far above 2C."""
    data = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0005}, duration_s=20.0, dt_s=0.1,
        load={"kind": "current", "value": 14.0},
    )  # fmt: skip
    yield from _serve(data, "cross_charge")


def test_dashboard_shows_the_verdict_and_the_alarms(
    browser: wb.Cdp, cross_charge: Dashboard, tmp_path: Path
) -> None:
    browser.call("Page.navigate", url=cross_charge.url)
    live = browser.wait_body(lambda d: d.get("verdict") == "ALARM", 60.0)
    assert live["state"] in ("running", "finished")
    rows = browser.eval(
        "[...document.querySelectorAll('#alarms tbody tr')].map(r =>"
        " [...r.cells].map(c => c.textContent))"
    )
    cross = [r for r in rows if r[3].startswith("CrossCharge")]
    assert cross and cross[0][1] == "B" and cross[0][2] == "alarm", rows
    assert "charge limit" in cross[0][4]
    badge = browser.eval("getComputedStyle(document.getElementById('verdict')).backgroundColor")
    assert badge == "rgb(211, 58, 44)"  # the alarm colour
    swatches = browser.eval(
        "[...document.querySelectorAll('.swatch')].map(e => getComputedStyle(e).backgroundColor)"
    )
    assert len(swatches) == 2 and badge not in swatches  # B is not drawn in the alarm colour
    data = browser.wait_body(lambda d: d.get("state") == "finished", 60.0)
    assert data["verdict"] == "ALARM"
    api = wb.get_json(cross_charge.url + "api/status")["verdict"]
    assert api["verdict"] == "ALARM" and any(a["battery"] == "B" for a in api["alarms"])
    shot = base64.b64decode(browser.call("Page.captureScreenshot", format="png")["data"])
    (Path(os.environ.get(ARTIFACTS, tmp_path)) / "dashboard_verdict.png").write_bytes(shot)
    assert len(shot) > 40_000


@pytest.fixture(scope="module")
def sensor_fault() -> Iterator[Dashboard]:
    """B's temperature sensor reads NaN from 2 s: the plant's B stays at a healthy 25 °C."""
    data = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0005}, v_a=24.0, v_b=23.9, duration_s=8.0,
        dt_s=0.1, load={"kind": "current", "value": 14.0},
    )  # fmt: skip
    data["controller"] = ["sequencing", "protection"]
    data["plausibility"] = {}
    data["faults"] = [{"kind": "sensor_nan", "at_s": 2.0, "battery": "B", "quantity": "temp_c"}]
    yield from _serve(data, "sensor_fault")


def test_a_card_shows_what_the_bms_measured_not_the_plant(
    browser: wb.Cdp, sensor_fault: Dashboard, tmp_path: Path
) -> None:
    """#17 §1: after B's temperature sensor fails, B's card says the BMS has no reading (with
    the plant's value in its tooltip), A's card shows A's measured temperature."""
    browser.call("Page.navigate", url=sensor_fault.url)
    browser.wait_body(lambda d: d.get("state") == "finished", 60.0)
    cards = browser.eval(
        "Object.fromEntries([...document.querySelectorAll('.panel.bat')].map(c =>"
        " [c.dataset.battery, [...c.querySelectorAll('.num .v')].map(v =>"
        " [v.textContent, v.className, v.title])]))"
    )
    temp_b = cards["B"][3]
    assert temp_b[0] == "no reading" and "sensorbad" in temp_b[1], cards
    assert "plant has 2" in temp_b[2]  # the plant's ~25 °C, for the post-mortem
    temp_a = cards["A"][3]
    assert "sensorbad" not in temp_a[1] and float(temp_a[0]) > 20.0, cards
    assert all("sensorbad" not in v[1] for v in cards["B"][:3]), cards  # V, A, SOC agree
    shot = base64.b64decode(browser.call("Page.captureScreenshot", format="png")["data"])
    (Path(os.environ.get(ARTIFACTS, tmp_path)) / "dashboard_sensor_fault.png").write_bytes(shot)
