"""`packpilot run` and `packpilot hil` as a user runs them (real subprocesses)."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import can

from tests.conftest import EXAMPLES

CLI = [sys.executable, "-m", "packpilot.cli"]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


def test_run_alone_fails_safe_logs_and_stops(tmp_path: Path) -> None:
    """No pack on the bus: every battery is never heard (NaN, infinitely old) → faults, the
    supervisor's safe state; the run keeps its period, logs every frame, records, exits 0."""
    db, log = tmp_path / "run.sqlite", tmp_path / "frames.blf"
    proc = _run("run", str(EXAMPLES / "uav_mission.toml"), "--can-interface", "virtual",
                "--can-channel", "alone", "--duration", "1.5", "--db", str(db),
                "--can-log", str(log), "--json")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    assert m["steps"] == m["periods"] == 15
    assert m["can_received"] == 0 and m["can_sent"] > 0
    with sqlite3.connect(db) as c:
        assert c.execute("select count(*) from pack_samples").fetchone()[0] == 15
        kinds = {r[0] for r in c.execute("select kind from events")}
    assert "Fault" in kinds
    frames = list(can.LogReader(log))
    assert len(frames) == m["can_sent"] + m["published_frames"] + m["charger_frames_sent"]


def test_run_refuses_a_pack_without_plausibility() -> None:
    proc = _run("run", str(EXAMPLES / "evtol_charging.toml"), "--can-interface", "virtual",
                "--duration", "0.1")  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: plausibility: `run` needs a [plausibility] section, which turns stale or lost "
        "telemetry into a fault and a safe state (or pass --allow-unmonitored)"
    ]


def test_run_bad_interface_is_one_line() -> None:
    proc = _run("run", str(EXAMPLES / "uav_mission.toml"), "--can-interface", "nosuchbus",
                "--duration", "0.1")  # fmt: skip
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "--can-interface nosuchbus" in proc.stderr


def test_hil_alone_steps_and_times_out_its_switches() -> None:
    """The twin with no BMS: its switch nodes hear nothing and open after 5 periods."""
    proc = _run("hil", "uav_mission", "--can-interface", "virtual", "--can-channel", "twin",
                "--speed", "0", "--duration", "5")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    assert m["steps"] == 25
    assert m["switch_timeouts"] == 2


def test_run_stops_cleanly_on_sigterm(tmp_path: Path) -> None:
    """A service manager's SIGTERM: the run ends as on Ctrl-C, the record says so."""
    import signal
    import time

    db = tmp_path / "run.sqlite"
    proc = subprocess.Popen([*CLI, "run", str(EXAMPLES / "uav_mission.toml"), "--can-interface",
                             "virtual", "--can-channel", "term", "--db", str(db), "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        while not (db.exists() and _rows(db) >= 5) and time.monotonic() < deadline:
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert json.loads(out)["steps"] >= 5
    with sqlite3.connect(db) as c:
        assert c.execute("select status from runs").fetchone()[0] == "interrupted"


def _rows(db: Path) -> int:
    try:
        with sqlite3.connect(db) as c:
            return int(c.execute("select count(*) from pack_samples").fetchone()[0])
    except sqlite3.Error:
        return 0
