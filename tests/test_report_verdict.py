"""Issue #17 §1 in the HTML report: the verdict and the alarms table come first, and no battery is
drawn in the alarm colour (report and dashboard)."""

from __future__ import annotations

import re
import tomllib

from matplotlib.colors import to_rgb

from packpilot.config import parse_config
from packpilot.report.html import SECTION_IDS, RunInfo, build_html
from packpilot.report.style import ALARM_COLOR, battery_color
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES, ROOT


def section(page: str, sid: str) -> str:
    m = re.search(rf'<section id="{sid}">(.*?)</section>', page, re.S)
    assert m, sid
    return m.group(1)


def page_of(name: str, duration_s: float) -> str:
    with (EXAMPLES / f"{name}.toml").open("rb") as fh:
        data = tomllib.load(fh)
    data["sim"].update(duration_s=duration_s, progress=False)
    cfg = parse_config(data)
    result = Runner(cfg, progress=False).run()
    return build_html(result, RunInfo.from_config(cfg.model_dump(mode="json"), status="ok"))


def test_cross_charge_run_reads_alarm_first() -> None:
    """The issue: uav_dual_parallel's report said "ok, No events were recorded"."""
    page = page_of("uav_dual_parallel", 10.0)
    assert SECTION_IDS[0] == "verdict"
    assert page.index('<section id="verdict">') < page.index('<section id="summary">')
    verdict = section(page, "verdict")
    assert 'id="verdict-word">ALARM<' in verdict
    assert "CrossCharge" in verdict and "(2C)" in verdict
    assert re.search(r"<td>[AB]</td><td><span class=\"sev alarm\">", verdict)
    header = page[: page.index("<main>")]
    assert "verdict-alarm" in header and ">ALARM<" in header


def test_a_clean_run_says_ok() -> None:
    verdict = section(page_of("smart_battery", 5.0), "verdict")
    assert 'id="verdict-word">OK<' in verdict and "No warning, alarm or fault" in verdict


def distance(a: str, b: str) -> float:
    return float(sum((x - y) ** 2 for x, y in zip(to_rgb(a), to_rgb(b), strict=True)) ** 0.5)


def test_no_battery_wears_the_alarm_colour() -> None:
    for b in range(20):
        assert distance(battery_color(b), ALARM_COLOR) > 0.25, (b, battery_color(b))
    js = (ROOT / "src/packpilot/web/static/dashboard.js").read_text()
    colors = re.findall(r"#[0-9a-f]{6}", js.split("const COLORS = [")[1].split("]")[0])
    alarm = re.search(r'const ALARM = "(#[0-9a-f]{6})"', js)
    assert alarm and len(colors) >= 6
    assert all(distance(c, alarm.group(1)) > 0.25 for c in colors), colors
