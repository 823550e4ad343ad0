"""`simulate --trace-csv` replays as is (#17 §5): the trace of protection_cold_heavy, which
tripped at 525 s, replays to the same trip within one sample; so does the trace of the same
flight flown without protection (what a user's own log is); the text and JSON outputs; the
--config forms a replay's own output takes; the README's log exists and replays."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import Result
from packpilot.io.telemetry import trace_to_csv
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES

ROOT = EXAMPLES.parent
RUNNER = CliRunner()
COLD = EXAMPLES / "protection_cold_heavy.toml"
DT_S = 0.5  # the example's sim.dt_s: "within one sample"


def _trip_time(result: Result) -> float:
    trips = [e.t_s for e in result.events if e.kind == "ProtectionTripped"]
    assert trips, "the example must trip"
    return trips[0]


def _run(cfg: ScenarioConfig) -> Result:
    return Runner(cfg, progress=False).run()


@pytest.fixture(scope="module")
def cold(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, float]:
    """The example's trace CSV through the CLI, and the closed loop's trip time."""
    out = tmp_path_factory.mktemp("cold") / "trace.csv"
    res = RUNNER.invoke(app, ["simulate", str(COLD), "--duration", "600", "--trace-csv",
                              str(out), "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    verdict = json.loads(res.stdout)["verdict"]
    trip = next(a["t_s"] for a in verdict["alarms"] if a["kind"] == "ProtectionTripped")
    assert trip == pytest.approx(525.0, abs=5.0)
    return out, float(trip)


def _replay_json(*args: str) -> dict[str, object]:
    res = RUNNER.invoke(app, ["replay", *args, "--json"])
    assert res.exit_code == 0, res.output
    out: dict[str, object] = json.loads(res.stdout)
    return out


def test_the_examples_trace_replays_to_its_own_trip(cold: tuple[Path, float]) -> None:
    trace, trip = cold
    assert "main_current_a" in trace.read_text().splitlines()[0]  # the trace's own names
    s = _replay_json("protection", str(trace))
    assert s["tripped"] is True and s["battery"] == "main"
    assert abs(float(s["trip_time_s"]) - trip) <= DT_S  # type: ignore[arg-type]
    assert s["param_at_trip"] == "P1"
    # The one row where the recorded BMS opened the path is read as that BMS saw it: said so.
    assert any("switched the battery" in a for a in s["assumed"])  # type: ignore[attr-defined]


def test_the_same_flight_without_protection_replays_to_the_same_trip(
    cold: tuple[Path, float], tmp_path: Path
) -> None:
    """A user's log is a flight without PackPilot: the discharge goes on past the trip."""
    cfg = load_config(COLD)
    data = cfg.model_dump()
    data["controller"] = []
    data["sim"]["duration_s"] = 560.0
    bare = _run(ScenarioConfig.model_validate(data))
    assert not [e for e in bare.events if e.kind == "ProtectionTripped"]
    trace = tmp_path / "bare.csv"
    trace_to_csv(bare, trace)
    s = _replay_json("protection", str(trace))
    assert abs(float(s["trip_time_s"]) - cold[1]) <= DT_S  # type: ignore[arg-type]
    assert s["assumed"] == []  # no FET switched in this log: nothing read differently


def test_without_json_a_short_summary_not_the_rows(
    cold: tuple[Path, float], tmp_path: Path
) -> None:
    trace, _ = cold
    res = RUNNER.invoke(app, ["replay", "protection", str(trace)])
    assert res.exit_code == 0, res.output
    lines = res.stdout.splitlines()
    assert len(lines) < 40, "a summary, not one line per row"
    assert "tripped: True" in lines and any(ln.startswith("trip_time_s: 525") for ln in lines)
    res = RUNNER.invoke(app, ["replay", "protection", str(trace), "--out", "-"])
    assert res.exit_code == 0
    assert res.stdout.splitlines()[0] == "t_s,param,cutoff_v,weighted_s,tripped"
    assert len(res.stdout.splitlines()) == 1 + 1200  # 600 s at 0.5 s
    out = tmp_path / "rows.csv"
    res = RUNNER.invoke(app, ["replay", "protection", str(trace), "--out", str(out)])
    assert res.exit_code == 0 and f"wrote {out}" in res.stdout
    assert len(out.read_text().splitlines()) == 1201


def test_config_takes_the_replays_own_json(cold: tuple[Path, float], tmp_path: Path) -> None:
    trace, _ = cold
    first = _replay_json("protection", str(trace))
    saved = tmp_path / "replay.json"
    saved.write_text(json.dumps(first))
    again = _replay_json("protection", str(trace), "--config", str(saved))
    assert again["trip_time_s"] == first["trip_time_s"]
    # m_s and weights copied into a TOML section: accepted when they agree ...
    toml = tmp_path / "p.toml"
    toml.write_text("[protection]\nm_s = 30.0\nweights = { P1 = 2, P2 = 3, P3 = 6 }\n")
    assert _replay_json("protection", str(trace), "--config", str(toml))["m_s"] == 30.0
    # ... and refused, naming the field, when they do not (derived: checked, never set).
    for bad, field in (("m_s = 31.0", "protection.m_s"), ("weights = { P1 = 3 }", "weights")):
        toml.write_text(f"[protection]\n{bad}\n")
        res = RUNNER.invoke(app, ["replay", "protection", str(trace), "--config", str(toml)])
        assert res.exit_code == 2 and field in res.stderr, res.output
    # An edited parameter in the JSON is used, not the default.
    edited = dict(first)
    cfg = dict(edited["config"])  # type: ignore[call-overload]
    cfg["parameters"] = [{"name": "P1", "cutoff_v": 2.8, "t_max_s": 30.0}]
    cfg["table"] = [{"param": "P1"}]
    edited.update(config=cfg, m_s=30.0, weights={"P1": 1})
    saved.write_text(json.dumps(edited))
    later = _replay_json("protection", str(trace), "--config", str(saved))
    # 30 s allowed below 2.8 V: the recorded run opened the path after ~15 s, so no trip.
    assert later["tripped"] is False and later["weights"] == {"P1": 1}
    # The output of another method's replay is not a protection config.
    saved.write_text(json.dumps({"method": "sequencing", "config": {}}))
    res = RUNNER.invoke(app, ["replay", "protection", str(trace), "--config", str(saved)])
    assert res.exit_code == 2 and "sequencing" in res.stderr


def test_pre_switch_rule_is_what_reproduces_the_trip(tmp_path: Path) -> None:
    """A trace whose BMS opened the path at the row where its sum reached m: without reading
    that row as the BMS saw it (the previous row), the replay stops one row short."""
    header = "t_s,B_current_a,B_temp_c,B_min_cell_v,B_dsg_on,B_chg_on\n"
    rows = [f"{k * 1.0},10,25,3.1,1,1" for k in range(4)] + [
        "4.0,0,25,3.15,0,1",
        "5.0,0,25,3.3,0,1",
    ]
    log = tmp_path / "t.csv"
    log.write_text(header + "\n".join(rows) + "\n")
    assert _replay_json("protection", str(log))["trip_time_s"] == 5.0
    bare = [",".join(r.split(",")[:4]) for r in rows]
    log.write_text(header.replace(",B_dsg_on,B_chg_on", "") + "\n".join(bare) + "\n")
    assert _replay_json("protection", str(log))["tripped"] is False


def test_readme_names_a_log_that_exists_and_replays() -> None:
    readme = (ROOT / "README.md").read_text()
    logs = re.findall(r"packpilot replay protection (\S+)", readme)
    assert logs, "the README's tour replays a log"
    for name in logs:
        path = ROOT / name
        assert path.is_file(), name
        s = _replay_json("protection", str(path))
        assert s["tripped"] is True
