"""`replay flight`'s pilot section (#27 §6): charge used against the autopilot's own counter,
the autopilot's remaining and warnings next to what PackPilot would have done, the flight modes
on the charts' time axis, voltage sag against current. Real logs and the shipped samples."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from packpilot.control.protection import ProtectionConfig
from packpilot.control.sequencing import SequencingConfig
from packpilot.replay.common import LogOptions
from packpilot.replay.flight import replay_flight
from packpilot.replay.flight_report import flight_html
from packpilot.replay.pilot import charge_mah, sag
from packpilot.report.flight import flight_page

LOGS = Path(__file__).resolve().parents[1] / "examples" / "logs"
TLOG = LOGS / "real" / "arducopter_dronekit_flight_battery.tlog"


def _replay(path: Path, cells: int | None = None, temp: float | None = None):  # type: ignore[no-untyped-def]
    return replay_flight(
        path, ProtectionConfig(), SequencingConfig(), LogOptions(None, temp, cells)
    )


def test_charge_against_the_autopilots_counter() -> None:
    fr = _replay(LOGS / "px4_one_battery.ulg")
    a = fr.summary["pilot"]["charge"]["A"]  # type: ignore[index]
    # the log's own discharged_mah (5825 mAh) against the trapezoid of its 1 Hz current
    assert a["autopilot_mah"] == pytest.approx(5825.0, abs=1.0)
    assert a["packpilot_mah"] == pytest.approx(a["autopilot_mah"], rel=0.01)
    assert a["remaining_start"] > 0.99 and a["remaining_end"] == 0.0
    page = flight_page(fr)
    row = re.search(r"<table id='pilot'>.*?</table>", page, re.S)
    assert row is not None and "5821 mAh" in row.group(0) and "5825 mAh" in row.group(0)
    assert "would have opened the discharge path at 526.0 s" in row.group(0)


def test_real_tlog_the_autopilots_low_battery_next_to_packpilots_trip() -> None:
    fr = _replay(TLOG, cells=3, temp=15.0)
    pilot = fr.summary["pilot"]
    a = pilot["charge"]["A"]  # type: ignore[index]
    assert a["autopilot_mah"] is None  # SYS_STATUS has no counter
    # PackPilot's count against what the autopilot's remaining implies of BATT_CAPACITY 2650
    implied = (a["remaining_start"] - a["remaining_end"]) * 2650.0
    assert a["packpilot_mah"] == pytest.approx(implied, rel=0.05)
    modes = [m for _, m in pilot["flight_modes"]]  # type: ignore[index]
    assert modes[0] == "STABILIZE" and "RTL" in modes and len(modes) == 9
    html = flight_page(fr)
    assert "&#x27;Low Battery!&#x27; at 483.2 s" in html or "'Low Battery!' at 483.2 s" in html
    assert "would have opened the discharge path at 480.8 s" in html
    data = json.loads(re.search(r'id="pp-data">(.*?)</script>', html, re.S).group(1))  # type: ignore[union-attr]
    marks = [m[2] for c in data["charts"].values() for m in c.get("marks", [])]
    assert "RTL" in marks and "AUTO" in marks  # the modes on the time axis of the charts
    assert "voltage against current" in html and "<svg class='sag'" in html
    static = flight_html(fr)
    assert "id='pilot'" in static and "RTL" in static


def test_sag_line_and_charge_count_on_known_data() -> None:
    t = np.arange(0.0, 100.0)
    i = np.where(t < 50, 10.0, 30.0)
    v = 12.0 - 0.05 * i + np.random.default_rng(1).normal(0.0, 0.005, t.size)
    fit = sag(v, i)
    assert fit is not None and fit["resistance_ohm"] == pytest.approx(0.05, rel=0.02)
    assert fit["sag_at_peak_v"] == pytest.approx(1.5, rel=0.02)
    # trapezoid: 49 s at 10 A, the step between averages 20 A, 49 s at 30 A
    assert charge_mah(t, i) == pytest.approx((49 * 10 + 20 + 49 * 30) / 3.6, rel=1e-9)
    assert sag(v, np.full(t.size, 10.0)) is None  # a current that never moves draws no line
