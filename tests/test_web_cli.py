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
        (["--speed", "-1"], "--speed -1.0: must be >= 0"),
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
