"""The dashboard's controls and views (#17 §2) through the app, on real runs and real SQLite
recordings: pause / resume / speed, starting a shipped example, opening a recording and
scrubbing it, the report link, headline times, and battery names in event messages."""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.bms import Event
from packpilot.contract.topology import Topology
from packpilot.io.telemetry import load_run
from packpilot.sim.runner import Runner
from packpilot.web.app import create_app
from packpilot.web.guard import Guard
from packpilot.web.live import (
    BATTERY_CHANNELS,
    DashboardRecorder,
    LiveRun,
    headline,
    name_batteries,
)
from packpilot.web.recorded import Recording
from packpilot.web.session import Library, Session
from tests.conftest import EXAMPLES
from tests.test_web_app import WS_URL, start, strict_loads
from tests.test_web_security import TOKEN, recording

__all__ = ["recording"]  # the module-scoped fixture, shared

OK = {"Origin": "http://127.0.0.1", "X-PackPilot-Token": TOKEN}


def app_client(session: Session) -> Any:
    from fastapi.testclient import TestClient

    app = create_app(session, push_interval_s=0.05, guard=Guard(token=TOKEN))
    return TestClient(app, base_url="http://127.0.0.1", client=("127.0.0.1", 1))


def sim_time_after(live: LiveRun, wait_s: float) -> tuple[float, float]:
    t0 = live.status()["t_s"]
    time.sleep(wait_s)
    return t0, live.status()["t_s"]


def wait_running(live: LiveRun, t_min_s: float = 0.5, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while live.status()["t_s"] < t_min_s and time.monotonic() < deadline:
        time.sleep(0.02)
    assert live.state == "running", live.error


# ---------------------------------------------------------------- pace
def test_pause_holds_the_run_and_resume_and_speed_pace_it() -> None:
    live, sim = start(speed=20.0, duration_s=600.0)
    try:
        c = app_client(Session(live, sim))
        wait_running(live)
        assert c.post("/api/pause", json={}, headers=OK).status_code == 200
        time.sleep(0.2)  # the step in flight finishes
        t0, t1 = sim_time_after(live, 0.6)
        assert t1 == t0 and live.state == "running"  # held still, not stopped
        st = c.get("/api/status").json()
        assert st["paused"] is True and st["speed"] == 20.0
        assert c.post("/api/speed", json={"speed": 2.0}, headers=OK).status_code == 200
        assert c.post("/api/resume", json={}, headers=OK).status_code == 200
        t0, t1 = sim_time_after(live, 1.0)
        assert 0.8 <= t1 - t0 <= 3.0, (t0, t1)  # 2x: about 2 s in 1 s of wall time
        c.post("/api/speed", json={"speed": 100.0}, headers=OK)
        t0, t1 = sim_time_after(live, 1.0)
        assert t1 - t0 > 30.0, (t0, t1)  # no catching up on the time spent at 2x either
        assert t1 - t0 < 200.0
        # pause, then stop: a paused run still stops at once
        c.post("/api/pause", json={}, headers=OK)
        begun = time.monotonic()
        sim.stop(timeout_s=5.0)
        assert time.monotonic() - begun < 1.0 and not sim.is_alive()
        assert live.state == "stopped"
    finally:
        sim.stop()


# ---------------------------------------------------------------- start an example
def test_the_page_starts_a_shipped_example_and_clients_follow() -> None:
    live, sim = start(speed=20.0, duration_s=600.0)
    built: list[Path] = []

    def make_runner(path: Path) -> Runner:
        built.append(path)
        d = tomllib.loads(path.read_text(encoding="utf-8"))
        d["sim"].update(duration_s=20.0, progress=False)
        return Runner(parse_config(d), progress=False)

    session = Session(live, sim, library=Library.of_dirs([EXAMPLES], None), make_runner=make_runner)
    c = app_client(session)
    try:
        assert "smart_battery" in c.get("/api/catalog").json()["examples"]
        with c.websocket_connect(WS_URL) as ws:
            assert strict_loads(ws.receive_text())["scenario"] == "web_test"
            r = c.post("/api/start", json={"example": "smart_battery", "speed": 0}, headers=OK)
            assert r.status_code == 200, r.text
            assert not sim.is_alive() and live.state == "stopped"  # the old run ended
            for _ in range(200):
                msg = strict_loads(ws.receive_text())
                if msg["type"] == "hello":
                    break
            assert msg["type"] == "hello" and msg["kind"] == "live"
            assert msg["scenario"] == session.live.scenario != "web_test"
            assert msg["layout"]["batteries"][0]["switch"] in ("mosfet_pair", "relay")
        assert built == [EXAMPLES / "smart_battery.toml"]
        for name in ("../examples/smart_battery", "/etc/passwd", "nope"):
            r = c.post("/api/start", json={"example": name}, headers=OK)
            assert r.status_code == 403, name
        r = c.post("/api/start", json={"example": "uav_mission", "speed": -2}, headers=OK)
        assert r.status_code == 422
    finally:
        session.stop()
        sim.stop()


# ---------------------------------------------------------------- recordings
def test_a_recording_opens_whole_and_scrubs_at_full_rate(recording: Path) -> None:
    rec = Recording(recording)
    raw = load_run(recording)
    live = rec.live
    assert live.kind == "recorded" and live.state == "finished"
    assert live.battery_names == ["A", "B"] == raw.battery_names
    assert [e["kind"] for e in live.events()] == [e.kind for e in raw.events]
    pts = live.points()
    assert pts[0]["step"] == 0 and pts[-1]["step"] == len(raw.trace.t_s) - 1
    c = app_client(Session(LiveRun()))
    c.app.state.session.open_path(recording)
    st = c.get("/api/status").json()
    assert st["kind"] == "recorded" and st["state"] == "finished" and st["verdict"]["verdict"]
    k = 77
    t = float(raw.trace.t_s[k])
    at = c.get("/api/at", params={"t_s": t + 1e-9}).json()
    assert at["index"] == k and at["t_s"] == pytest.approx(t)
    v = at["latest"]["batteries"][1]["voltage_v"]
    assert v == pytest.approx(raw.trace.channel("voltage_v")[k, 1])
    gv = at["latest"]["batteries"][0]["group_v"]
    assert np.allclose(gv, raw.trace.group_v[k, 0], equal_nan=True)
    assert at["n_events"] == sum(1 for e in raw.events if e.t_s <= t)
    assert c.get("/api/at", params={"t_s": -5}).json()["index"] == 0  # clamped
    assert c.get("/api/at", params={"t_s": 1e9}).json()["index"] == len(raw.trace.t_s) - 1
    # the controls of a live run do not apply to a recording
    assert c.post("/api/pause", json={}, headers=OK).status_code == 409


def test_scrubbing_needs_a_recording() -> None:
    c = app_client(Session(LiveRun()))
    assert c.get("/api/at", params={"t_s": 1.0}).status_code == 409


def test_a_recording_links_its_report_when_one_exists(recording: Path, tmp_path: Path) -> None:
    copy = tmp_path / "flight.sqlite"
    copy.write_bytes(recording.read_bytes())
    c = app_client(Session(LiveRun()))
    c.app.state.session.open_path(copy)
    assert c.get("/api/status").json()["report"] is None
    assert c.get("/report").status_code == 404
    (tmp_path / "flight.html").write_text("<html>the report</html>", encoding="utf-8")
    c.app.state.session.open_path(copy)
    assert c.get("/api/status").json()["report"] == "/report"
    assert "the report" in c.get("/report").text


def test_a_finished_live_run_links_the_report_written_for_it(tmp_path: Path) -> None:
    from packpilot.cli import _dashboard_report

    out = tmp_path / "live.html"
    # the callback is attached before the thread starts: at speed 0 on a warm cache the 10 s run
    # can finish before a later assignment (CI 2026-11-28: "report" None, the callback missed)
    live, sim = start(speed=0.0, duration_s=10.0, begin=False)
    session = Session(live, None, write_report=_dashboard_report(out))
    sim.on_result = session._on_result
    session.sim = sim
    sim.start()
    # the report is written in the run's thread after it finishes; on a cold kernel cache that
    # compiles the report's kernels (state of power) first: 30 s was not always enough in CI
    sim.join(300.0)
    assert live.state == "finished" and not sim.is_alive()
    c = app_client(session)
    assert c.get("/api/status").json()["report"] == "/report"
    r = c.get("/report")
    assert r.status_code == 200 and "<html" in r.text.lower() and out.is_file()


def test_a_stopped_run_gets_no_report(tmp_path: Path) -> None:
    calls: list[Any] = []
    live, sim = start(speed=1.0, duration_s=600.0)
    session = Session(live, None, write_report=lambda res, lv: calls.append(res))
    sim.on_result = session._on_result
    wait_running(live, 0.1)
    sim.stop()
    assert live.state == "stopped" and calls == [] and live.report is None


# ---------------------------------------------------------------- headline numbers
def summary(bats: list[dict[str, Any]]) -> dict[str, Any]:
    return {"batteries": bats}


def test_headline_times() -> None:
    a = {"current_a": 10.0, "remaining_ah": 2.0, "full_ah": 5.0,
         "status": {"protection_time_to_trip_s": 400.0}}  # fmt: skip
    b = {"current_a": 5.0, "remaining_ah": 1.0, "full_ah": 5.0,
         "status": {"protection_time_to_trip_s": float("nan")}}  # fmt: skip
    aux = {"current_a": 3.0, "remaining_ah": 9.0, "full_ah": 9.0, "status": {}}
    h = headline(summary([aux, a, b]), ["aux", "traction", "traction"])
    assert h["time_to_go_s"] == pytest.approx(3.0 * 3600 / 15.0)  # aux excluded
    assert h["time_to_cutoff_s"] == 400.0 and h["time_to_full_s"] is None
    charging = [{**a, "current_a": -2.0}, {**b, "current_a": -1.0}]
    h = headline(summary(charging), ["traction", "traction"])
    assert h["time_to_full_s"] == pytest.approx((3.0 + 4.0) * 3600 / 3.0)
    assert h["time_to_go_s"] is None
    rest = [{**a, "current_a": 0.01, "status": {}}]
    assert headline(summary(rest), ["traction"]) == {
        "time_to_go_s": None, "time_to_cutoff_s": None, "time_to_full_s": None,
    }  # fmt: skip
    assert headline(None, [])["time_to_go_s"] is None


def test_headline_times_from_the_observer() -> None:
    """With the SOC observer's channels the times are its (recent average load), not the
    present current's; the soonest battery's time to cut-off."""
    def bat(cur: float, soc: float, avg: float, ttc: float) -> dict[str, Any]:
        return {"current_a": cur, "remaining_ah": 9.0, "full_ah": 9.0,
                "status": {"soc_est": soc, "soc_capacity_ah": 5.0, "soc_load_avg_a": avg,
                           "soc_time_to_cutoff_s": ttc}}  # fmt: skip

    h = headline(summary([bat(30.0, 0.5, 10.0, 700.0), bat(0.0, 0.4, 5.0, 650.0)]),
                 ["traction", "traction"])  # fmt: skip
    assert h["time_to_go_s"] == pytest.approx((2.5 + 2.0) * 3600 / 15.0)
    assert h["time_to_cutoff_s"] == 650.0 and h["time_to_full_s"] is None
    h = headline(summary([bat(-3.0, 0.5, -2.0, float("nan"))]), ["traction"])
    assert h["time_to_full_s"] == pytest.approx(2.5 * 3600 / 2.0)
    assert h["time_to_go_s"] is None and h["time_to_cutoff_s"] is None
    # the core's CC/CV time to full where every battery has it: the last one to finish
    two = [bat(-3.0, 0.5, -2.0, math.nan), bat(-3.0, 0.6, -2.0, math.nan)]
    two[0]["status"]["soc_time_to_full_s"], two[1]["status"]["soc_time_to_full_s"] = 900.0, 1200.0
    assert headline(summary(two), ["traction", "traction"])["time_to_full_s"] == 1200.0
    two[1]["status"]["soc_time_to_full_s"] = math.nan  # one unknown: the Ah-based bound
    assert headline(summary(two), ["traction", "traction"])["time_to_full_s"] == pytest.approx(
        (2.5 + 2.0) * 3600 / 4.0)


def test_headline_on_a_live_protected_run() -> None:
    live, sim = start(speed=0.0)
    sim.join(30.0)
    st = live.status()
    bats = st["latest"]["batteries"]
    cur = sum(b["current_a"] for b in bats)
    assert cur > 1.0  # the hover load is on at the end
    want = sum(b["remaining_ah"] for b in bats) * 3600 / cur
    assert st["headline"]["time_to_go_s"] == pytest.approx(want)


# ---------------------------------------------------------------- names in messages
def test_messages_name_batteries_as_the_page_does() -> None:
    topo = Topology(("AUX", "A", "B"), ("aux", "traction", "traction"))
    msg = "battery 0: charge FET off, 1.20 A would flow into it from battery 1"
    assert name_batteries(msg, topo) == (
        "battery A: charge FET off, 1.20 A would flow into it from battery B"
    )
    assert name_batteries("R1 battery 1 inserted", topo) == "R1 battery B inserted"
    keep = "BMU browned out: aux battery 11.500 V < 12.000 V, every switch open"
    assert name_batteries(keep, topo) == keep
    assert name_batteries("battery 7: out of range", topo) == "battery 7: out of range"
    live = LiveRun(scenario="x", battery_names=["AUX", "A", "B"])
    live.on_start(["AUX", "A", "B"], {"pack": {"batteries": [{"name": "AUX", "role": "aux"}]}})
    live.on_events([Event(1.0, "SequencingRefused", 1, msg)])
    shown = live.events()[0]
    assert shown["message"].startswith("battery A:") and shown["battery_name"] == "B"
    # an event's message is also the cause in the alarms table
    risk = "battery 1: 2.47 A (above its 2.45 A charge limit) would flow into it"
    live.on_events([Event(2.0, "CrossCurrentRisk", 1, risk)])
    causes = [a["cause"] for a in live.verdict()["alarms"] if a["kind"] == "CrossCurrentRisk"]
    assert causes == ["battery B: 2.47 A (above its 2.45 A charge limit) would flow into it"]


def test_no_battery_number_reaches_the_page_on_a_sequencing_run() -> None:
    d = tomllib.loads((EXAMPLES / "sequencing_dual_hover.toml").read_text(encoding="utf-8"))
    d["sim"].update(duration_s=60.0, progress=False)
    live = LiveRun(scenario="seq", battery_names=[])
    res = Runner(parse_config(d), recorder=DashboardRecorder(live)).run()
    import re

    # the core names batteries in its messages; the page's renaming is for older recordings
    assert any(re.search(r"\bbattery [AB]\b", e.message) for e in res.events)
    shown = [e["message"] for e in live.events()]
    assert not [m for m in shown if re.search(r"\bbattery \d\b", m)]
    assert any(re.search(r"\bbattery [AB]\b", m) for m in shown)


# ---------------------------------------------------------------- schematic layout
def test_layout_tells_the_schematic_what_to_draw() -> None:
    d = tomllib.loads((EXAMPLES / "evtol_charging.toml").read_text(encoding="utf-8"))
    d["sim"].update(duration_s=1.0, progress=False)
    cfg = parse_config(d)
    live = LiveRun(scenario="evtol", battery_names=[])
    Runner(cfg, recorder=DashboardRecorder(live)).run()
    lay = live.layout
    assert lay["charger"] is cfg.charger.present
    assert lay["load"] is (cfg.load.kind != "none")
    roles = [b["role"] for b in lay["batteries"]]
    assert roles == [b.role for b in cfg.pack.batteries]
    kinds = {b["switch"] for b in lay["batteries"]}
    assert kinds <= {"mosfet_pair", "relay"}
    assert BATTERY_CHANNELS  # the channels the page reads exist
