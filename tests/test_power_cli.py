"""``packpilot plan-join CONFIG`` (issue #28 item 4): the designer's table of admissible join
voltage differences, and its bad input (one ``error:`` line, exit code 2)."""

from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path
from typing import Any

import pytest
import tomli_w
from typer.testing import CliRunner

from packpilot.cli import app
from tests.conftest import EXAMPLES

RUNNER = CliRunner()
BASE = tomllib.loads((EXAMPLES / "uav_dual_parallel.toml").read_text())


def _rows(*args: str) -> list[dict[str, Any]]:
    res = RUNNER.invoke(app, ["plan-join", *args, "--json"])
    assert res.exit_code == 0, (res.output, res.exception)
    rows: list[dict[str, Any]] = json.loads(res.stdout)
    return rows


def test_admissible_dv_is_the_limit_times_the_loop_resistance() -> None:
    rows = _rows("uav_dual_parallel", "--soc", "0.5", "--temp", "25")
    assert [r["battery"] for r in rows] == ["A", "B"]
    for r in rows:
        # no [limits]: the default table's trips, 3 C charge = 15 A into the other battery
        # (joining above the bus) or into the joining one (below)
        assert r["dv_up_v"] == pytest.approx(15.0 * r["r_loop_ohm"], rel=1e-6)
        assert r["dv_down_v"] == pytest.approx(15.0 * r["r_loop_ohm"], rel=1e-6)
        # the supervisor's fixed 3 V would drive 3 V / R_loop: far beyond 15 A
        assert r["peak_at_fixed_a"] == pytest.approx(3.0 / r["r_loop_ohm"], rel=1e-6)
        assert r["peak_at_fixed_a"] > 60.0
        # two batteries stated 20 mOhm at 25 degC and their initial SOC (A 0.90, B 0.61 from
        # their ocv0_v), which the plant scales its cells to: at 50 % SOC 16.7 and 19.7 mOhm
        # (model.pack.Pack's nominal_r_scale), plus two FET pairs of 0.2 mOhm each. Until
        # 2026-11-29 the prediction held 20 mOhm at SOC 0.5 (40.4 mOhm), not the plant's
        assert r["r_loop_ohm"] == pytest.approx(0.0368, abs=3e-4)


def test_a_switch_rating_and_the_cold_tighten_or_loosen_it(tmp_path: Path) -> None:
    warm = _rows("uav_dual_parallel", "--soc", "0.5", "--temp", "25")[0]
    cold = _rows("uav_dual_parallel", "--soc", "0.5", "--temp", "0")[0]
    assert cold["r_loop_ohm"] > 1.5 * warm["r_loop_ohm"]  # a cold pack may join further apart
    assert cold["dv_down_v"] > 1.5 * warm["dv_down_v"]
    rated = _rows("uav_dual_parallel", "--soc", "0.5", "--temp", "25", "--switch-a", "5")[0]
    assert rated["dv_down_v"] == pytest.approx(5.0 * rated["r_loop_ohm"], rel=1e-6)
    # a relay instead of the MOSFET pairs: one contact per battery instead of two channels
    cfg = copy.deepcopy(BASE)
    cfg["pack"]["switch"] = {"kind": "relay", "on_ohm": 0.005}
    p = tmp_path / "relay.toml"
    p.write_text(tomli_w.dumps(cfg))
    relay = _rows(str(p), "--soc", "0.5", "--temp", "25")[0]
    assert relay["r_loop_ohm"] == pytest.approx(warm["r_loop_ohm"] - 0.0004 + 0.01, rel=1e-6)


def test_the_table_prints(tmp_path: Path) -> None:
    res = RUNNER.invoke(app, ["plan-join", "uav_dual_parallel", "--soc", "0.5"])
    assert res.exit_code == 0, res.output
    assert "admissible dV" in res.stdout
    assert len([ln for ln in res.stdout.splitlines() if ln.strip().startswith(("A ", "B "))]) == 4


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["uav_dual_parallel", "--soc", "1.5"], "--soc 1.5: must be 0..1"),
        (["uav_dual_parallel", "--soc", "x"], "--soc 'x': not a comma-separated list"),
        (["uav_dual_parallel", "--soc", ","], "give at least one number"),
        (["uav_dual_parallel", "--temp", "500"], "--temp 500.0: must be"),
        (["uav_dual_parallel", "--switch-a", "nan"], "--switch-a nan"),
        (["uav_dual_parallel", "--load-a", "inf"], "--load-a inf"),
        (["smart_battery"], "at least two traction batteries"),
        (["no_such_pack.toml"], "no_such_pack.toml: file not found"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: list[str], needle: str) -> None:
    res = RUNNER.invoke(app, ["plan-join", *args])
    assert res.exit_code == 2, (res.output, res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), res.stderr
    assert needle in lines[0], lines[0]
