"""The CLI end to end, as a user runs it (a real subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from tests.conftest import EXAMPLES

CLI = [sys.executable, "-m", "packpilot.cli"]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


def test_simulate_json_has_the_promised_metrics(tmp_path: Path) -> None:
    proc = _run(
        "simulate",
        str(EXAMPLES / "uav_dual_parallel.toml"),
        "--duration",
        "20",
        "--json",
        "--db",
        str(tmp_path / "run.sqlite"),
        "--trace-csv",
        str(tmp_path / "t.csv"),
        "--plot",
        str(tmp_path / "p.png"),
    )
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    for key in (
        "sim_time_s",
        "wall_time_s",
        "energy_out_wh",
        "energy_in_wh",
        "min_cell_v",
        "max_cell_v",
        "max_temp_c",
        "peak_string_current_a",
        "peak_cross_current_a",
        "joule_heat_j",
        "events",
    ):
        assert key in m, key
    assert len(m["peak_string_current_a"]) == 2
    assert m["sim_time_s"] == 20.0
    # No controller: the 2 V apart batteries cross-charge hard while supplying the hover load.
    assert m["peak_cross_current_a"] > 20.0
    assert (tmp_path / "run.sqlite").stat().st_size > 0
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert len((tmp_path / "t.csv").read_text().splitlines()) == 201


def test_charger_current_is_not_cross_current() -> None:
    """A single float-charged string has no battery to push into it: charging is not crossing."""
    proc = _run("simulate", str(EXAMPLES / "telecom_string.toml"), "--json")
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    assert m["energy_in_wh"] > 0.0 and m["energy_out_wh"] > 0.0  # rectifier and load both ran
    assert m["peak_cross_current_a"] == 0.0


def test_bad_config_exits_2_with_one_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text('[pack]\ncell = "ecm_example"\n[[pack.batteries]]\nname = "A"\nsoc0 = 2\n')
    proc = _run("simulate", str(p))
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1
    assert "bad.toml: pack.batteries.0.soc0" in lines[0]
