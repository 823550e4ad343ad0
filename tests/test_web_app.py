"""The dashboard app on a real paced run, through FastAPI's TestClient (no sockets).

The scenario has two batteries with 6 and 5 series groups, so every sample carries a NaN
(``group_v`` of the 5-group battery is padded): the wire must show it as null, never NaN.
"""

from __future__ import annotations

import json
import math
import threading
import time
import warnings
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

with warnings.catch_warnings():  # starlette >= 1.x nags to use httpx2; httpx still works
    warnings.filterwarnings("ignore", message="Using `httpx` with")
    from fastapi.testclient import TestClient

from packpilot.config import parse_config
from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, StepSample
from packpilot.sim.runner import Runner
from packpilot.web.app import create_app
from packpilot.web.live import CHART_CHANNELS, LiveRun, SimThread, jsonable

DURATION_S = 30.0
DT_S = 0.2
SPEED = 20.0  # 30 s of simulated time in ~1.5 s


def scenario(duration_s: float = DURATION_S) -> dict[str, Any]:
    return {
        "controller": ["protection"],
        "pack": {
            "name": "web_test",
            "cell": "uav_5ah",
            "switch": {"kind": "mosfet_pair", "on_ohm": 0.0005, "diode_drop_v": 0.6},
            "batteries": [
                {"name": "A", "series_groups": 6, "cells_per_group": 1, "soc0": 0.9},
                {"name": "B", "series_groups": 5, "cells_per_group": 1, "soc0": 0.95},
            ],
        },
        "load": {"kind": "current", "value": 10.0, "profile": "uav_hover", "start_s": 1.0},
        "supervisor": {},
        "limits": {},
        "sim": {"dt_s": DT_S, "duration_s": duration_s, "progress": False},
    }


WS_URL = "ws://127.0.0.1/ws"
"""TestClient joins a relative WebSocket path to ``ws://testserver``: name the host."""


def local(app: Any) -> TestClient:
    """A test client that looks like a script on this machine: ``Host: 127.0.0.1`` (the Host
    check refuses TestClient's default ``testserver``) and a loopback peer address (a
    WebSocket without an ``Origin`` is accepted from loopback only)."""
    return TestClient(app, base_url="http://127.0.0.1", client=("127.0.0.1", 50000))


def strict_loads(text: str) -> Any:
    """json.loads that fails on NaN / Infinity tokens instead of accepting them."""

    def bad(token: str) -> Any:
        raise AssertionError(f"non-JSON token {token} on the wire")

    return json.loads(text, parse_constant=bad)


def start(
    speed: float = SPEED, duration_s: float = DURATION_S, *, begin: bool = True
) -> tuple[LiveRun, SimThread]:
    """A live run of the test scenario in its thread; ``begin=False`` leaves the thread unstarted,
    so a caller can attach callbacks before the run can finish."""
    runner = Runner(parse_config(scenario(duration_s)), progress=False)
    live = LiveRun(
        scenario="web_test",
        duration_s=duration_s,
        dt_s=DT_S,
        speed=speed,
        battery_names=list(runner.pack.names),
    )
    sim = SimThread(runner, live)
    if begin:
        sim.start()
    return live, sim


@pytest.fixture
def paced() -> Iterator[tuple[LiveRun, SimThread, TestClient]]:
    live, sim = start()
    with local(create_app(live, push_interval_s=0.05)) as client:
        yield live, sim, client
    sim.stop()
    assert not sim.is_alive()


def test_status_progresses_and_finishes(paced: tuple[LiveRun, SimThread, TestClient]) -> None:
    _, _, client = paced
    seen: list[tuple[str, float]] = []
    # Cold kernels (CI) compile at the first step, for minutes on a loaded machine; the paced
    # run (1.5 s at SPEED) starts after that, so the deadline covers a cold compile.
    deadline = time.monotonic() + 600.0
    st: dict[str, Any] = {}
    while time.monotonic() < deadline:
        r = client.get("/api/status")
        assert r.status_code == 200
        st = strict_loads(r.text)
        seen.append((st["state"], st["t_s"]))
        if st["state"] != "running" and st["state"] != "starting":
            break
        time.sleep(0.05)
    assert st["state"] == "finished", st.get("error")
    running_t = [t for s, t in seen if s == "running"]
    assert any(0.0 < t < DURATION_S - 1.0 for t in running_t), seen  # seen mid-run
    ts = [t for _, t in seen]
    assert ts == sorted(ts)  # time never goes back
    assert st["t_s"] == pytest.approx(DURATION_S - DT_S, abs=1e-6)  # start of the last step
    assert st["progress"] == pytest.approx(1.0)
    assert st["metrics"]["steps"] == round(DURATION_S / DT_S)
    assert st["metrics"]["events"]["ModeChanged"] >= 1
    assert st["n_events"] == sum(st["metrics"]["events"].values())
    latest = st["latest"]
    assert [b["name"] for b in latest["batteries"]] == ["A", "B"]
    assert latest["mode"] in {"idle", "discharge", "charge", "fault"}
    b = latest["batteries"][1]
    assert set(BATTERY_CHANNELS) <= set(b)
    assert b["group_v"][-1] is None and all(v is not None for v in b["group_v"][:5])  # NaN→null
    assert "protection_param" in b["status"]
    # a finished run stays viewable
    time.sleep(0.1)
    assert strict_loads(client.get("/api/status").text)["state"] == "finished"


def test_events_endpoint_pages() -> None:
    live, sim = start(speed=0.0)  # as fast as possible
    sim.join(20.0)
    assert live.state == "finished"
    client = local(create_app(live))
    body = strict_loads(client.get("/api/events").text)
    evs = body["events"]
    assert len(evs) == body["next"] == live.status()["n_events"] >= 3
    assert [e["index"] for e in evs] == list(range(len(evs)))
    assert {"t_s", "kind", "battery", "battery_name", "message", "data"} <= set(evs[0])
    trips = [e for e in evs if e["battery"] is not None]
    assert trips and all(e["battery_name"] == ["A", "B"][e["battery"]] for e in trips)
    page = strict_loads(client.get("/api/events", params={"since": 1, "limit": 2}).text)
    assert page["events"] == evs[1:3] and page["next"] == 3
    assert client.get("/api/events", params={"since": -1}).status_code == 422


def test_ws_streams_samples_and_events(paced: tuple[LiveRun, SimThread, TestClient]) -> None:
    live, sim, client = paced
    points: list[dict[str, Any]] = []
    events: list[dict[str, Any]] = []
    updates: list[dict[str, Any]] = []
    with client.websocket_connect(WS_URL) as ws:
        hello = strict_loads(ws.receive_text())
        assert hello["type"] == "hello"
        assert hello["battery_names"] == ["A", "B"]
        assert hello["chart_channels"] == list(CHART_CHANNELS)
        for _ in range(2000):  # bounded: ~1.5 s run at 20 pushes/s, plus slack
            msg = strict_loads(ws.receive_text())
            assert msg["type"] == "update"
            updates.append(msg)
            points += msg["points"]
            events += msg["events"]
            if msg["state"] == "finished":
                break
    assert updates[-1]["state"] == "finished"
    assert updates[-1]["metrics"]["steps"] == round(DURATION_S / DT_S)
    assert len(updates) >= 3  # streamed while running, not one dump at the end
    steps = [p["step"] for p in points]
    assert steps == sorted(set(steps)) and steps[-1] == round(DURATION_S / DT_S) - 1
    assert len(points) > 20
    p = points[-1]
    assert len(p["voltage_v"]) == 2 and all(isinstance(v, float) for v in p["voltage_v"])
    assert 0.0 < p["soc"][0] < 1.0
    assert [e["index"] for e in events] == list(range(len(events)))
    assert [e["kind"] for e in events] == [e.kind for e in live._events]
    assert "ModeChanged" in {e["kind"] for e in events}
    sim.join(5.0)


def test_ws_disconnect_does_not_stop_the_run() -> None:
    live, sim = start(speed=20.0)
    try:
        with local(create_app(live, push_interval_s=0.05)) as client:
            for _ in range(3):  # several browsers come and go mid-run
                with client.websocket_connect(WS_URL) as ws:
                    assert strict_loads(ws.receive_text())["type"] == "hello"
                    assert strict_loads(ws.receive_text())["type"] == "update"
            t_mid = live.status()["t_s"]
            assert live.state == "running" and t_mid < DURATION_S
            sim.join(20.0)
            assert live.state == "finished"
            with client.websocket_connect(WS_URL) as ws:  # a late browser gets the history
                ws.receive_text()
                first = strict_loads(ws.receive_text())
                assert first["state"] == "finished" and first["metrics"] is not None
                assert first["points"][0]["step"] == 0
                assert len(first["events"]) == live.status()["n_events"]
    finally:
        sim.stop()


def test_stop_ends_the_run_as_stopped() -> None:
    live, sim = start(speed=1.0, duration_s=600.0)
    deadline = time.monotonic() + 10.0
    while live.state != "running" and time.monotonic() < deadline:
        time.sleep(0.01)
    t0 = time.monotonic()
    sim.stop(timeout_s=5.0)
    assert time.monotonic() - t0 < 1.0  # paced sleep wakes up at once
    assert not sim.is_alive()
    st = live.status()
    assert st["state"] == "stopped" and "stopped" in st["error"]
    assert st["t_s"] < 10.0


def test_history_is_bounded_and_keeps_the_end() -> None:
    live = LiveRun(scenario="x", battery_names=["A"], max_points=8)
    live.on_start(["A"])
    rows = np.zeros((1, len(BATTERY_CHANNELS)))
    for k in range(100):
        live.on_sample(
            StepSample(k, 0.1 * k, 1, 0, 0, 0, 0, rows, np.zeros((1, 1)), status={"m": [None]})
        )
    live.on_finish({"steps": 100}, "finished")
    steps = [p["step"] for p in live.points()]
    assert len(steps) <= 9 and steps[0] == 0 and steps[-1] == 99
    gaps = np.diff(steps[:-1])
    assert len(set(gaps.tolist())) == 1  # evenly spaced overview
    assert [p["step"] for p in live.points(after_step=steps[-3])] == steps[-2:]


def test_nan_and_inf_become_null() -> None:
    rows = np.full((1, len(BATTERY_CHANNELS)), 1.0)
    rows[0, BATTERY_CHANNELS.index("temp_c")] = math.nan
    rows[0, BATTERY_CHANNELS.index("current_a")] = math.inf
    live = LiveRun(scenario="x", duration_s=10.0, battery_names=["A"])
    live.on_start(["A"])
    live.on_sample(
        StepSample(
            0,
            0.1,
            math.nan,
            0,
            0,
            0,
            0,
            rows,
            np.array([[np.nan]]),
            status={"est": [math.nan], "mode": ["idle"]},
        )
    )
    live.on_events([Event(0.1, "X", 0, "m", {"v": math.nan, "w": -math.inf})])
    live.on_finish({"min_cell_v": math.nan, "final_soc": [np.float64("nan")]}, "finished")
    client = local(create_app(live))
    st = strict_loads(client.get("/api/status").text)
    bat = st["latest"]["batteries"][0]
    assert st["latest"]["bus_v"] is None and bat["temp_c"] is None and bat["current_a"] is None
    assert bat["status"]["est"] is None and bat["group_v"] == [None]
    assert st["metrics"] == {"min_cell_v": None, "final_soc": [None]}
    ev = strict_loads(client.get("/api/events").text)["events"][0]
    assert ev["data"] == {"v": None, "w": None}
    with client.websocket_connect(WS_URL) as ws:
        ws.receive_text()
        up = strict_loads(ws.receive_text())
    assert up["points"][0]["temp_c"] == [None]
    assert jsonable({"a": (np.int64(3), np.bool_(True))}) == {"a": [3, True]}


def test_page_and_static_files_are_served() -> None:
    client = local(create_app(LiveRun()))
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    for ref in ("/static/dashboard.js", "/static/dashboard.css"):
        assert ref in page.text
        assert client.get(ref).status_code == 200
    text = page.text + client.get("/static/dashboard.js").text
    assert "http://" not in text.replace("http://www.w3.org", "")  # nothing from the network
    assert "https://" not in text
    for cid in CHART_CHANNELS:
        assert f'id="chart-{cid}"' in page.text


def test_ws_sends_an_event_backlog_in_full() -> None:
    live = LiveRun(scenario="x", battery_names=["A"])
    live.on_start(["A"])
    live.on_events([Event(0.1 * k, "BalancingUpdated", 0, f"#{k}") for k in range(1234)])
    live.on_finish({"steps": 0}, "finished")  # nothing will change any more
    client = local(create_app(live, push_interval_s=0.05))
    got: list[dict[str, Any]] = []

    def read() -> None:
        with client.websocket_connect(WS_URL) as ws:
            ws.receive_text()
            for _ in range(3):  # 500 + 500 + 234
                got.extend(strict_loads(ws.receive_text())["events"])

    reader = threading.Thread(target=read, daemon=True)  # a stalled stream must fail, not hang
    reader.start()
    reader.join(10.0)
    assert [e["message"] for e in got] == [f"#{k}" for k in range(1234)]


def test_dashboard_and_report_name_an_event_battery_alike_with_the_aux_listed_first() -> None:
    """Events count traction batteries only; with the auxiliary battery listed first, event
    battery 0 is the first traction battery on the dashboard as in the report (not "AUX")."""
    import tomllib

    from packpilot.report.html import RunInfo
    from packpilot.web.live import DashboardRecorder
    from tests.conftest import EXAMPLES

    d = tomllib.loads((EXAMPLES / "evtol_charging.toml").read_text())
    bats = d["pack"]["batteries"]
    d["pack"]["batteries"] = [b for b in bats if b.get("role") == "aux"] + [
        b for b in bats if b.get("role") != "aux"
    ]
    d["sim"].update(duration_s=120.0, progress=False)
    d["plausibility"] = {}
    d["faults"] = [{"kind": "sensor_nan", "battery": "B1", "quantity": "voltage_v", "at_s": 20.0}]
    cfg = parse_config(d)
    live = LiveRun(scenario="aux first", battery_names=[])
    res = Runner(cfg, recorder=DashboardRecorder(live)).run()
    assert res.battery_names[0] == "AUX"
    shown = [(x["kind"], x["battery_name"]) for x in live.events() if x["battery"] is not None]
    report = RunInfo(config=cfg.model_dump(mode="json")).event_names(res.battery_names)
    expected = [(e.kind, report[e.battery]) for e in res.events if e.battery is not None]
    assert shown == expected and ("Fault", "B1") in shown
