"""``packpilot dashboard`` as a user runs it: a real process, a real port, Ctrl-C to stop."""

from __future__ import annotations

import json
import os
import queue
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "smart_battery.toml"
ENV = {**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true", "MPLBACKEND": "Agg"}


def cli(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "packpilot.cli", "dashboard", *args],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
        cwd=ROOT,
    )


def lines(proc: subprocess.Popen[str]) -> queue.Queue[str]:
    q: queue.Queue[str] = queue.Queue()

    def pump() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            q.put(line)

    threading.Thread(target=pump, daemon=True).start()
    return q


def get_json(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5) as resp:
        return json.loads(resp.read())


def test_ctrl_c_stops_the_run_and_the_server(tmp_path: Path) -> None:
    db = tmp_path / "run.sqlite"
    proc = cli(str(EXAMPLE), "--port", "0", "--speed", "2", "--db", str(db))
    try:
        out = lines(proc)
        first = out.get(timeout=60)
        m = re.search(r"on (http://127\.0\.0\.1:\d+/)", first)
        assert m, first
        url = m.group(1)
        deadline = time.monotonic() + 20.0
        st = get_json(url + "api/status")
        while st["t_s"] <= 0.5 and time.monotonic() < deadline:
            time.sleep(0.1)
            st = get_json(url + "api/status")
        assert st["state"] == "running" and st["t_s"] > 0.5
        proc.send_signal(signal.SIGINT)
        assert proc.wait(15) == 0
        rest = "".join(out.get(timeout=5) for _ in range(out.qsize() or 1))
        assert re.search(r"run stopped at t = \d+\.\d s", rest), rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
    with sqlite3.connect(db) as conn:
        (status, n), *_ = conn.execute(
            "SELECT status, (SELECT count(*) FROM pack_samples) FROM runs"
        ).fetchall()
    assert status == "stopped" and n > 0  # finished as stopped, samples flushed


def test_bad_arguments_are_one_line_errors(tmp_path: Path) -> None:
    (tmp_path / "bad.sqlite").write_text("not a database", encoding="utf-8")
    for args, needle in (
        (["--speed", "-1"], "--speed -1.0: must be 0.."),
        (["--port", "70000"], "--port 70000: must be 0..65535"),
        (["--db", str(tmp_path / "no" / "dir.sqlite")], "does not exist"),
        (["--db", str(tmp_path / "bad.sqlite")], "not a PackPilot telemetry database"),
    ):
        r = subprocess.run(
            [sys.executable, "-m", "packpilot.cli", "dashboard", str(EXAMPLE), *args],
            capture_output=True,
            text=True,
            env=ENV,
            cwd=ROOT,
            timeout=60,
        )
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.startswith("error: ") and needle in r.stderr, (args, r.stderr)
        assert "Traceback" not in r.stderr


def serve_and_stop(args: list[str], check: Any) -> str:
    """Start ``packpilot dashboard ARGS``, call ``check(url)``, Ctrl-C it; its stderr."""
    proc = cli(*args)
    try:
        out = lines(proc)
        first = out.get(timeout=60)
        m = re.search(r"on (http://127\.0\.0\.1:\d+/)", first)
        assert m, first
        check(m.group(1))
        proc.send_signal(signal.SIGINT)
        assert proc.wait(15) == 0
        return first + "".join(out.get(timeout=5) for _ in range(out.qsize()))
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)


def test_a_recorded_run_opens_from_the_command_line(tmp_path: Path) -> None:
    """`packpilot dashboard out/demo.sqlite` used to fail with "not a UTF-8 text file"."""
    from packpilot.config import parse_config
    from packpilot.io.telemetry import SQLiteRecorder
    from packpilot.sim.runner import Runner
    from tests.test_web_app import scenario

    db = tmp_path / "demo.sqlite"
    with SQLiteRecorder(db) as rec:
        Runner(parse_config(scenario(10.0)), recorder=rec, progress=False).run()

    def check(url: str) -> None:
        st = get_json(url + "api/status")
        assert st["kind"] == "recorded" and st["state"] == "finished"
        assert st["battery_names"] == ["A", "B"] and st["source"] == "demo.sqlite, run 1"
        assert abs(get_json(url + "api/at?t_s=5")["t_s"] - 5.0) < 1e-6
        assert get_json(url + "api/catalog")["recordings"] == ["demo.sqlite"]

    err = serve_and_stop([str(db), "--port", "0"], check)
    assert "Traceback" not in err and "dashboard for web_test" in err


def test_without_a_scenario_the_page_offers_the_examples(tmp_path: Path) -> None:
    def check(url: str) -> None:
        assert get_json(url + "api/status")["state"] == "idle"
        cat = get_json(url + "api/catalog")
        assert "uav_mission" in cat["examples"] and cat["recordings"] == []
        assert cat["runs_dir"] == str(tmp_path.resolve())

    err = serve_and_stop(["--port", "0", "--runs-dir", str(tmp_path)], check)
    assert "Traceback" not in err and "run idle" not in err


def test_unsafe_or_bad_serving_options_are_one_line_errors(tmp_path: Path) -> None:
    (tmp_path / "text.sqlite").write_text("not a database", encoding="utf-8")
    for args, needle in (
        ([str(EXAMPLE), "--host", "0.0.0.0"], "--allow-remote"),
        ([str(EXAMPLE), "--host", "0.0.0.0", "--allow-remote", "--token", "short"], "--token"),
        ([str(EXAMPLE), "--allowed-host", "evil.example.com"], "--allowed-host"),
        ([str(EXAMPLE), "--max-websockets", "0"], "--max-websockets"),
        ([str(EXAMPLE), "--runs-dir", str(tmp_path / "nope")], "--runs-dir"),
        ([str(tmp_path / "text.sqlite")], "not a PackPilot telemetry database"),
        ([str(tmp_path / "missing.sqlite")], "not found"),
    ):
        r = subprocess.run(
            [sys.executable, "-m", "packpilot.cli", "dashboard", *args, "--port", "0"],
            capture_output=True,
            text=True,
            env=ENV,
            cwd=ROOT,
            timeout=60,
        )
        assert r.returncode == 2, (args, r.stderr)
        assert r.stderr.startswith("error: ") and needle in r.stderr, (args, r.stderr)
        assert "Traceback" not in r.stderr and r.stderr.count("\n") == 1, r.stderr


def test_ctrl_c_names_the_run_on_show_after_the_page_switched(tmp_path: Path) -> None:
    """Started with one scenario, switched from the page to an example: Ctrl-C's last line
    names the example that was running, not the scenario the command line named (#29)."""
    proc = cli(str(EXAMPLE), "--port", "0", "--speed", "2")
    try:
        out = lines(proc)
        first = out.get(timeout=60)
        m = re.search(r"on (http://127\.0\.0\.1:\d+/)", first)
        assert m, first
        url = m.group(1)
        with urllib.request.urlopen(url, timeout=5) as resp:
            page = resp.read().decode()
        token = re.search(r'name="packpilot-token" content="([^"]+)"', page)
        assert token
        req = urllib.request.Request(
            url + "api/start", data=json.dumps({"example": "uav_dual_parallel"}).encode(),
            headers={"Content-Type": "application/json", "X-PackPilot-Token": token.group(1)},
            method="POST",
        )  # fmt: skip
        with urllib.request.urlopen(req, timeout=120) as resp:
            assert resp.status == 200
        deadline = time.monotonic() + 60.0
        st = get_json(url + "api/status")
        while st["t_s"] <= 0.5 and time.monotonic() < deadline:
            time.sleep(0.1)
            st = get_json(url + "api/status")
        assert st["source"] == "example uav_dual_parallel" and st["state"] == "running"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(15) == 0
        rest = "".join(out.get(timeout=5) for _ in range(out.qsize() or 1))
        last = rest.strip().splitlines()[-1]
        want = r"run stopped at t = \d+\.\d s \(.*example uav_dual_parallel\)$"
        assert re.search(want, last), rest
        assert "smart_battery" not in last
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(5)
