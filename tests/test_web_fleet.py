"""The dashboard's fleet view (#27 §5: "the dashboard can open a fleet"): ``/fleet`` shows one
row per battery with its R0 and cell-spread trend and flags, ``/api/fleet`` the same as JSON;
a dashboard without ``--fleet`` says how to get one. Real SQLite fleet, real FastAPI app."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from packpilot.cli import app as cli_app
from packpilot.model.fit.synthetic import Truth, synthetic_log
from packpilot.replay.fleet import connect, flight_record, store
from packpilot.web.app import create_app
from packpilot.web.live import LiveRun
from packpilot.web.session import Session


def _client(fleet: Path | None) -> TestClient:
    session = Session(LiveRun(scenario="no run yet", state="idle"))
    app = create_app(session, fleet=fleet)
    return TestClient(app, base_url="http://127.0.0.1", client=("127.0.0.1", 50000))


def _fleet(db: Path) -> None:
    con = connect(db)
    for name in ("P1", "P2"):
        for k in range(14):
            raised = name == "P2" and k >= 9
            prof = synthetic_log(Truth(r0_ohm=0.012 * (1.4 if raised else 1.0), soc0=0.95), 1.0,
                                 seconds=300, seed=10 * k + len(name))  # fmt: skip
            d = 0.05 if raised else 0.006
            cells = prof.voltage_v[:, None] + np.array([0.0, -d, 0.0])
            store(con, flight_record(name, f"{name}-{k}", f"{name}-{k}", "A", prof, 3, "", cells))
    con.close()


def test_fleet_page_and_json(tmp_path: Path) -> None:
    db = tmp_path / "fleet.sqlite"
    _fleet(db)
    client = _client(db)
    page = client.get("/fleet")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert "script-src" not in page.headers["content-security-policy"]  # the page runs none
    text = page.text
    p1 = re.search(r"<tr id='battery-P1'>.*?</tr>", text, re.S).group(0)  # type: ignore[union-attr]
    p2 = re.search(r"<tr id='battery-P2'>.*?</tr>", text, re.S).group(0)  # type: ignore[union-attr]
    assert "no flag" in p1 and "R0 up" in p2 and "cell spread growing: 6 -&gt; 50 mV" in p2
    assert p2.count("<polyline") == 2  # R0 and cell spread, flight by flight
    data = client.get("/api/fleet").json()
    assert [b["battery"] for b in data["batteries"]] == ["P1", "P2"]
    assert len(data["flights"]["P2"]) == 14 and data["flights"]["P2"][-1]["cell_spread_v"] > 0.04


def test_without_a_fleet_the_page_says_how(tmp_path: Path) -> None:
    client = _client(None)
    res = client.get("/fleet")
    assert res.status_code == 404 and "--fleet" in res.json()["error"]
    gone = _client(tmp_path / "nothing.sqlite").get("/api/fleet")
    assert gone.status_code == 400 and "no such fleet database" in gone.json()["error"]
    out = CliRunner().invoke(cli_app, ["dashboard", "--fleet", str(tmp_path / "x.sqlite")])
    assert out.exit_code == 2 and "--fleet" in out.stderr and "Traceback" not in out.output
