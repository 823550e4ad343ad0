"""The command line's bad input (issues #17 §4, #18 §3): one line on stderr, exit code 2,
and every output checked before the run, not after it."""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from typer.testing import CliRunner

from packpilot.cli import app
from tests.conftest import EXAMPLES, ROOT

RUNNER = CliRunner()
BASE = tomllib.loads((EXAMPLES / "uav_dual_parallel.toml").read_text())


def _scenario(tmp_path: Path, **sections: Any) -> Path:
    cfg = copy.deepcopy(BASE)
    cfg.update(sections)
    p = tmp_path / "scenario.toml"
    p.write_text(tomli_w.dumps(cfg))
    return p


def _one_line_error(res: Any, *needles: str) -> str:
    assert res.exit_code == 2, (res.exit_code, res.output, res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("error: ")
    for n in needles:
        assert n in lines[0], (n, lines[0])
    return lines[0]


@pytest.mark.parametrize("duration", ["0", "-5", "nan", "1e300"])
def test_a_bad_duration_is_one_line(tmp_path: Path, duration: str) -> None:
    p = _scenario(tmp_path)
    res = RUNNER.invoke(app, ["simulate", str(p), f"--duration={duration}", "--json"])
    _one_line_error(res, "--duration", "sim.duration_s")


def test_a_bad_duration_is_refused_by_campaign_and_dashboard_too(tmp_path: Path) -> None:
    p = _scenario(tmp_path)
    res = RUNNER.invoke(app, ["campaign", str(p), "--runs", "1", "--duration=0", "--json"])
    _one_line_error(res, "--duration")
    res = RUNNER.invoke(app, ["dashboard", str(p), "--duration=-5", "--port", "0"])
    _one_line_error(res, "--duration")


@pytest.mark.parametrize(
    ("option", "name", "needle"),
    [
        ("--plot", "missing/run.png", "does not exist"),
        ("--trace-csv", "missing/trace.csv", "does not exist"),
        ("--report", "missing/report.html", "does not exist"),
        ("--can-log", "missing/frames.blf", "does not exist"),
        ("--plot", "run.txt", "must end in .png or .svg or .pdf"),
        ("--can-log", "frames.txt", "must end in .blf or .asc"),
        ("--trace-csv", ".", "is a directory"),
    ],
)
def test_every_output_is_checked_before_the_run(
    tmp_path: Path, option: str, name: str, needle: str
) -> None:
    """The run would create the database first: no database file means nothing ran. (A CAN
    log needs a scenario with a charger: without one, ``--can-*`` is refused first.)"""
    if option == "--can-log":
        p = tmp_path / "scenario.toml"
        p.write_text((EXAMPLES / "uav_mission.toml").read_text())
    else:
        p = _scenario(tmp_path)
    db = tmp_path / "run.sqlite"
    out = tmp_path / name
    res = RUNNER.invoke(app, ["simulate", str(p), "--db", str(db), option, str(out), "--json"])
    _one_line_error(res, option, needle)
    assert not db.exists()


def test_db_pointing_at_a_directory_is_one_line(tmp_path: Path) -> None:
    p = _scenario(tmp_path)
    res = RUNNER.invoke(app, ["simulate", str(p), "--db", str(tmp_path), "--json"])
    _one_line_error(res, "--db", "is a directory")


def test_a_cutoff_above_a_full_cell_names_the_file_and_field(tmp_path: Path) -> None:
    """4.5 V is within protection's 2..4.5 V bounds but above a full uav_5ah cell."""
    prot = {
        "parameters": [{"name": "P1", "cutoff_v": 4.5, "t_max_s": 10}],
        "table": [{"param": "P1"}],
    }
    p = _scenario(tmp_path, controller=["protection"], protection=prot)
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    _one_line_error(res, "scenario.toml", "protection.parameters.0.cutoff_v", "full cell")


@pytest.mark.parametrize(
    ("charging", "needle"),
    [
        ({"voltage_basis": "cell", "v_sat_v": 10.0}, "10 V per cell"),
        ({"v_sat_v": 120.0}, "20 V per cell"),  # a 100 V battery's value on a 6S battery
    ],
)
def test_a_saturation_voltage_beyond_the_cell_limit_is_refused(
    tmp_path: Path, charging: dict[str, Any], needle: str
) -> None:
    p = _scenario(tmp_path, controller=["charging"], charging=charging)
    res = RUNNER.invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    _one_line_error(res, "scenario.toml", "charging.v_sat_v", needle)


def test_a_can_charger_with_a_later_error_is_one_clean_line(tmp_path: Path) -> None:
    """The python-can bus was opened before a bad load profile failed; python-can then logged
    "VirtualBus was not properly shut down" twice under the error (at exit: a real process)."""
    prof = tmp_path / "prof.csv"
    prof.write_text("t_s,current_a\n0,abc\n")
    cfg = tomllib.loads((EXAMPLES / "uav_mission.toml").read_text())
    cfg["load"] = {"kind": "current", "value": 1.0, "profile": str(prof)}
    p = tmp_path / "mission.toml"
    p.write_text(tomli_w.dumps(cfg))
    log = tmp_path / "frames.asc"
    res = _cli("simulate", str(p), "--can-log", str(log), "--json")
    assert res.returncode == 2
    assert res.stderr.splitlines() == [
        f"error: {prof}: row 2, column current_a: 'abc' is not a number"
    ], res.stderr


def _cli(*args: str, code: str | None = None) -> subprocess.CompletedProcess[str]:
    """``packpilot`` (or ``code``) in a fresh interpreter: what a user's shell shows."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT)])}
    cmd = [sys.executable, "-c", code] if code else [sys.executable, "-m", "packpilot.cli", *args]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)


GUARDED = """
import numpy as np
from packpilot.cli import _guard
from packpilot.errors import InputError

def bad():
    np.array([1e308]) * 10  # RuntimeWarning: overflow
    raise InputError("log.csv: row 2: absurd")

try:
    _guard(bad)
except SystemExit:
    raise
except Exception as exc:  # typer.Exit outside an app
    raise SystemExit(exc.exit_code)
"""


def test_a_warning_on_the_way_to_a_clean_error_does_not_leak() -> None:
    """A NumPy RuntimeWarning printed above the one-line error made it two lines (a real
    interpreter: pytest records warnings instead of printing them)."""
    res = _cli(code=GUARDED)
    assert res.returncode == 2
    assert res.stderr.splitlines() == ["error: log.csv: row 2: absurd"], res.stderr


# ------------------------------------------------- issue #26 §3: every numeric option checked


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["run", "uav_mission", "--duration", "nan"], "--duration nan: must be"),
        (["run", "uav_mission", "--duration", "-5"], "--duration -5.0: must be"),
        (["run", "uav_mission", "--duration", "inf"], "--duration inf: must be"),
        (["run", "uav_mission", "--node-id", "200"], "--node-id 200: must be 1..127"),
        (["run", "uav_mission", "--node-id", "-1"], "--node-id -1: must be 1..127"),
        (["run", "uav_mission", "--node-id", "0"], "--node-id 0: must be 1..127"),
        (["run", "uav_mission", "--period", "0"], "--period 0.0: must be"),
        (["run", "uav_mission", "--period", "nan"], "--period nan: must be"),
        (["hil", "uav_mission", "--speed", "inf"], "--speed inf: must be"),
        (["hil", "uav_mission", "--bms-period", "1e-9"], "--bms-period 1e-09: must be"),
        (["hil", "uav_mission", "--timeout-periods", "0"], "--timeout-periods 0: must be"),
        (["can-hub", "--port", "70000"], "--port 70000: must be 0..65535"),
        (["can-hub", "--port", "-1"], "--port -1: must be 0..65535"),
        (["dashboard", "--max-connections", "0"], "--max-connections 0: must be"),
        (["dashboard", "--max-websockets", "-3"], "--max-websockets -3: must be"),
        (["dashboard", "--speed", "nan"], "--speed nan: must be"),
        (["dashboard", "--run-id", str(2**63)], f"--run-id {2**63}: must be 1..{2**63 - 1}"),
        (["report", "x.sqlite", "--run-id", str(2**63)], f"--run-id {2**63}: must be"),
        (["report", "x.sqlite", "--run-id", "0"], "--run-id 0: must be"),
        (["replay", "can", "x.blf", "uav_mission", "--period", "nan"], "--period nan: must be"),
        (["calibrate", "protection", "--cell", "uav_5ah", "--parallel", "0"], "--parallel 0"),
        (["calibrate", "protection", "--cell", "uav_5ah", "--min-temp", "nan"], "--min-temp"),
    ],
)
def test_a_numeric_option_out_of_range_is_one_line(args: list[str], needle: str) -> None:
    """``run --duration nan`` / ``-5`` ran 0 steps and exited 0; ``--node-id 200`` and ``-1``
    were accepted; ``report --run-id 2**63`` was a traceback (SQLite overflow). Each is refused
    before anything opens a bus, a port or a file."""
    res = RUNNER.invoke(app, args)
    _one_line_error(res, needle)


def test_a_run_id_beyond_sqlite_is_one_line_from_the_reader(tmp_path: Path) -> None:
    """The reader itself refuses it (the dashboard's and report's common path)."""
    from packpilot.errors import InputError
    from packpilot.io.telemetry.reader import load_run

    db = tmp_path / "run.sqlite"
    res = RUNNER.invoke(
        app, ["simulate", "uav_dual_parallel", "--duration", "0.3", "--db", str(db)]
    )
    assert res.exit_code == 0, res.output
    with pytest.raises(InputError, match=r"run id 9223372036854775808 is not 1\.\."):
        load_run(db, 2**63)
