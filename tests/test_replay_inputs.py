"""Replay inputs of issue #26 §3: a flight CSV without ``t_s`` (KeyError), a CSV with a UTF-8
BOM (refused by every replay), and a sequencing scenario's own trace CSV (its status columns
``A_seq_chg_on`` / ``A_seq_dsg_on`` made a phantom battery ``A_seq``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from packpilot.cli import app

RUNNER = CliRunner()

LOGS = {
    "protection": "t_s,current_a,temp_c,min_cell_v\n0,10,25,3.6\n0.1,30,25,3.1\n0.2,30,25,2.9\n",
    "sequencing": "t_s,v_0,v_1,i_0,i_1\n0,24.2,22.2,5,0\n0.1,24.1,22.2,5,0\n0.2,24,22.2,5,0\n",
    "equalization": "t_s,current_a,v_0,v_1,v_2\n0,2,3.3,3.31,3.29\n1,2,3.3,3.31,3.29\n",
    "flight": "t_s,A_voltage_v,A_current_a,A_temp_c,A_min_cell_v,B_voltage_v,B_current_a,"
    "B_temp_c,B_min_cell_v\n0,24,5,25,4,22,0,25,3.7\n0.1,24,5,25,4,22,0,25,3.7\n",
}


@pytest.mark.parametrize("method", sorted(LOGS))
def test_a_csv_with_a_bom_replays_as_without(tmp_path: Path, method: str) -> None:
    plain, bom = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_text(LOGS[method], encoding="utf-8")
    bom.write_text(LOGS[method], encoding="utf-8-sig")  # Excel's "CSV UTF-8"
    assert bom.read_bytes().startswith(b"\xef\xbb\xbf")
    out = []
    for p in (plain, bom):
        res = RUNNER.invoke(app, ["replay", method, str(p), "--json"])
        assert res.exit_code == 0, (p.name, res.output)
        summary = json.loads(res.stdout)
        summary.pop("log", None)
        out.append(summary)
    assert out[0] == out[1]


def test_a_scenario_file_with_a_bom_loads(tmp_path: Path) -> None:
    from packpilot.config import load_config

    p = tmp_path / "bom.toml"
    p.write_text('[pack]\n[[pack.batteries]]\nname = "A"\nsoc0 = 0.5\n', encoding="utf-8-sig")
    assert load_config(p).pack.batteries[0].name == "A"


@pytest.mark.parametrize(
    "text",
    [
        "voltage_v,current_a,temp_c,min_cell_v\n24,5,25,4\n24,5,25,4\n",  # was a KeyError
        "A_voltage_v,A_current_a,B_voltage_v,B_current_a\n24,5,22,0\n24,5,22,0\n",
    ],
)
def test_a_flight_csv_without_time_is_one_line(tmp_path: Path, text: str) -> None:
    p = tmp_path / "no_t.csv"
    p.write_text(text)
    res = RUNNER.invoke(app, ["replay", "flight", str(p)])
    assert res.exit_code == 2, (res.output, res.exception)
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "t_s" in lines[0], res.stderr


def test_status_columns_of_a_method_are_not_a_battery(tmp_path: Path) -> None:
    from packpilot.replay.common import read_log

    p = tmp_path / "trace.csv"
    p.write_text(
        "t_s,A_voltage_v,A_current_a,A_chg_on,A_seq_chg_on,A_seq_dsg_on,A_seq_state,"
        "B_voltage_v,B_current_a,B_seq_chg_on,B_seq_dsg_on\n"
        "0,24,5,1,1,1,2,22,0,0,1\n0.1,24,5,1,1,1,2,22,0,0,1\n"
    )
    assert read_log(p).batteries() == ["A", "B"]


def test_a_sequencing_scenarios_trace_replays(tmp_path: Path) -> None:
    trace = tmp_path / "trace.csv"
    res = RUNNER.invoke(
        app,
        ["simulate", "sequencing_dual_hover", "--duration", "1", "--trace-csv", str(trace)],
    )
    assert res.exit_code == 0, res.output
    assert "A_seq_chg_on" in trace.read_text().splitlines()[0]
    res = RUNNER.invoke(app, ["replay", "sequencing", str(trace), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["final_states"] == ["DISCHARGING", "STANDBY"]
    res = RUNNER.invoke(app, ["replay", "flight", str(trace), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["batteries"] == ["A", "B"]
