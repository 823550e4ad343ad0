"""`packpilot fleet` (#27 §5): one record per flight per battery in real SQLite; the report
flags a battery whose resistance rose by 25 % in its last 10 of 40 flights, and no battery of
a fleet without such a change."""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.model.fit.synthetic import Truth, synthetic_log
from packpilot.replay.fleet import connect, flight_record, report, store

REAL = Path(__file__).resolve().parents[1] / "examples" / "logs" / "real"
RUNNER = CliRunner()


def _fleet(db: Path, raised: str | None) -> None:
    con = connect(db)
    for name, r0 in (("A", 0.012), ("B", 0.010), ("C", 0.014)):
        for k in range(40):
            factor = 1.25 if name == raised and k >= 30 else 1.0
            truth = Truth(r0_ohm=r0 * factor, soc0=0.95)
            prof = synthetic_log(truth, 1.0, seconds=420, seed=100 * k + ord(name))
            store(con, flight_record(name, f"{name}{k}.ulg", f"{name}{k}", "A", prof, 1))
    con.close()


@pytest.mark.parametrize("raised", ["B", None])
def test_report_flags_only_the_battery_whose_resistance_rose(
    tmp_path: Path, raised: str | None
) -> None:
    db = tmp_path / "fleet.sqlite"
    _fleet(db, raised)
    rows = {r["battery"]: r for r in report(db)}
    assert {k: r["flights"] for k, r in rows.items()} == {"A": 40, "B": 40, "C": 40}
    for name, r in rows.items():
        flagged = any(str(f).startswith("R0 up") for f in r["flags"])  # type: ignore[attr-defined]
        assert flagged == (name == raised), (name, r)
    if raised:
        assert rows["B"]["r0_change_pct"] == pytest.approx(25.0, abs=5.0)
    assert not any("outlier" in str(f) for r in rows.values() for f in r["flags"])  # type: ignore[attr-defined]


def test_cli_fleet_add_real_log_once_and_report(tmp_path: Path) -> None:
    db = tmp_path / "f.sqlite"
    log = str(REAL / "ardupilot_3x_underpowered.log")
    res = RUNNER.invoke(app, ["fleet", "add", log, "--db", str(db), "--cells", "3",
                              "--label", "pack-7"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "-> pack-7: R0" in res.stdout
    again = RUNNER.invoke(app, ["fleet", "add", log, "--db", str(db), "--cells", "3",
                                "--label", "pack-7"])  # fmt: skip
    assert again.exit_code == 0 and "already recorded" in again.stdout
    with sqlite3.connect(db) as con:
        n, e, ah = con.execute("SELECT count(*), energy_wh, charge_ah FROM flights").fetchone()
    assert n == 1 and 20 < e < 30 and ah == pytest.approx(2.276, abs=0.01)
    res = RUNNER.invoke(app, ["fleet", "report", "--db", str(db), "--json"])
    assert res.exit_code == 0, res.output
    rows = json.loads(res.stdout)
    assert rows[0]["battery"] == "pack-7" and rows[0]["flights"] == 1


def test_cli_fleet_add_without_identity_is_one_line(tmp_path: Path) -> None:
    res = RUNNER.invoke(app, ["fleet", "add", str(REAL / "ardupilot_3x_underpowered.log"),
                              "--db", str(tmp_path / "f.sqlite"), "--cells", "3"])  # fmt: skip
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "--label" in lines[0]


def test_cell_spread_trend_flags_the_battery_whose_cells_drift_apart(tmp_path: Path) -> None:
    """Two 3-cell batteries, 16 flights each; D's cells drift apart (spread 8 -> 45 mV) in its
    last 5 flights, E's stay within 8 mV: only D is flagged. A battery without real cells gets
    no spread and no flag."""
    import numpy as np

    from packpilot.replay.fleet import cell_spread

    db = tmp_path / "spread.sqlite"
    con = connect(db)
    for name in ("D", "E", "F"):
        for k in range(16):
            prof = synthetic_log(Truth(soc0=0.95), 1.0, seconds=300, seed=10 * k + ord(name))
            d = 0.045 if name == "D" and k >= 11 else 0.008
            cells = None if name == "F" else prof.voltage_v[:, None] + np.array([0.0, -d, 0.0])
            store(con, flight_record(name, f"{name}{k}", f"{name}{k}", "A", prof, 3, "", cells))
    con.close()
    rows = {r["battery"]: r for r in report(db)}
    spread = [f for f in rows["D"]["flags"] if "cell spread" in f]  # type: ignore[union-attr]
    assert spread == ["cell spread growing: 8 -> 45 mV"], rows["D"]
    assert not any("cell spread" in f for f in rows["E"]["flags"])  # type: ignore[union-attr]
    assert rows["E"]["cell_spread_recent_mv"] == pytest.approx(8.0, abs=0.5)
    assert rows["F"]["cell_spread_flights"] == 0 and rows["F"]["flags"] == []
    # a glitched sample does not set the spread; one real cell is no spread
    x = np.full((100, 2), 3.8)
    x[50, 1] = 3.0
    assert cell_spread(x) == pytest.approx(0.0)
    assert cell_spread(np.full((10, 3), np.nan) + np.array([3.8, np.nan, np.nan])) is None


def test_a_fleet_recorded_before_the_cell_spread_column_opens(tmp_path: Path) -> None:
    db = tmp_path / "old.sqlite"
    with sqlite3.connect(db) as con:
        con.execute(
            "CREATE TABLE flights (id INTEGER PRIMARY KEY, battery TEXT NOT NULL, log TEXT NOT "
            "NULL, log_sha256 TEXT NOT NULL, log_battery TEXT NOT NULL, r0_ohm REAL, r0_rel REAL,"
            " capacity_ah REAL, capacity_rel REAL, capacity_ok INTEGER, energy_wh REAL, "
            "charge_ah REAL, lowest_cell_v REAL, peak_current_a REAL, max_temp_c REAL, warnings "
            "TEXT, verdict TEXT, heldout_rmse_v REAL, UNIQUE (battery, log_sha256, log_battery))"
        )
        con.execute(
            "INSERT INTO flights (battery, log, log_sha256, log_battery, r0_ohm, capacity_ah, "
            "capacity_ok, lowest_cell_v, warnings) "
            "VALUES ('old', 'x', 'x', 'A', 0.01, 5, 1, 3.5, '')"
        )
    rows = report(db)
    assert rows[0]["battery"] == "old" and rows[0]["cell_spread_flights"] == 0
