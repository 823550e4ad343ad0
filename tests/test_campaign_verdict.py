"""A campaign gets the same verdict as a run (#29): per-run verdict and alarm categories in the
Parquet, a summary counting runs per verdict and the over-discharged ones, ``--fail-on``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq

from packpilot.contract.severity import Severity
from packpilot.sim.verdict import counted_verdict

ROOT = Path(__file__).resolve().parents[1]
SMART = ROOT / "examples" / "smart_battery.toml"
SPREAD = "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35"


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PACKPILOT_CAMPAIGN_FAIL_RUNS"}
    env["PYBAMM_DISABLE_TELEMETRY"] = "true"
    return subprocess.run(
        [sys.executable, "-m", "packpilot.cli", *args],
        capture_output=True, text=True, timeout=600, env=env, cwd=ROOT,
    )  # fmt: skip


def test_counted_verdict_takes_the_worst_of_events_and_physics() -> None:
    assert counted_verdict({"BalancingUpdated": 40}, []) == ("OK", [])
    assert counted_verdict({"BalancingUpdated": 3, "CommandRefused": 1}, []) == (
        "WARNING", ["refused"],
    )  # fmt: skip
    word, cats = counted_verdict(
        {"ProtectionTripped": 1, "Fault": 0}, [("overdischarge", Severity.WARNING)]
    )
    assert (word, cats) == ("ALARM", ["overdischarge", "trip"])  # a zero count is no alarm
    assert counted_verdict({"Fault": 2}, [])[0] == "FAULT"


def test_a_campaign_run_gets_the_verdict_simulate_gives_it(tmp_path: Path) -> None:
    """Without spreads every campaign run is the scenario itself: its row's verdict and alarm
    categories must be those of ``simulate --json`` on the same scenario."""
    run = _cli("simulate", str(SMART), "--json", "--no-progress")
    assert run.returncode == 0, run.stderr
    verdict = json.loads(run.stdout)["verdict"]
    cats = sorted({a["category"] for a in verdict["alarms"]})
    out = tmp_path / "one.parquet"
    camp = _cli("campaign", str(SMART), "--runs", "1", "--scheduler", "sync", "--out", str(out),
                "--json")  # fmt: skip
    assert camp.returncode == 0, camp.stderr
    row = pq.read_table(out).to_pylist()[0]
    assert row["verdict"] == verdict["verdict"]
    assert row["alarms"].split(",") == cats
    # the scenario drains its battery below empty: the "failures: 0" at -3.7 % SOC
    assert "overdischarge" in cats and row["overdischarged_at_end"] is True


def test_summary_counts_verdicts_and_fail_on_exits_3(tmp_path: Path) -> None:
    out = tmp_path / "mc.parquet"
    args = ["campaign", str(SMART), "--runs", "12", "--spread", SPREAD, "--scheduler", "sync",
            "--out", str(out)]  # fmt: skip
    proc = _cli(*args, "--fail-on", "overdischarge")
    assert proc.returncode == 3, proc.stderr
    table = pq.read_table(out)
    verdicts = table.column("verdict").to_pylist()
    over = sum("overdischarge" in a.split(",") for a in table.column("alarms").to_pylist())
    ended = sum(table.column("overdischarged_at_end").to_pylist())
    assert over >= 1 and ended <= over
    counts = {v: verdicts.count(v) for v in ("OK", "WARNING", "ALARM", "FAULT")}
    assert f"verdicts: OK {counts['OK']}, WARNING {counts['WARNING']}, ALARM {counts['ALARM']}" in (
        proc.stdout
    )
    assert f"overdischarge in {over} run(s)" in proc.stdout
    assert f"over-discharged at the end: {ended} run(s)" in proc.stdout
    assert f"fail-on: overdischarge in {over} run(s) (exit code 3)" in proc.stderr
    assert not list(tmp_path.glob("*.png"))  # no histograms unless --plot
    # JSON carries the same counts; a category no run had does not fail the campaign
    js = _cli(*args, "--json", "--fail-on", "fault")
    assert js.returncode == 0, js.stderr
    rep = json.loads(js.stdout)
    assert rep["verdicts"] == counts and rep["categories"]["overdischarge"] == over
    assert rep["overdischarged_at_end"] == ended
    bad = _cli(*args, "--fail-on", "overdischarg")
    assert bad.returncode == 2 and "overdischarge" in bad.stderr
