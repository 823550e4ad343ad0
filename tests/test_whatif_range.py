"""A what-if on a fitted cell set that leaves the range the set was fitted on says so (#27 §4):
a warning row ``OutsideFit`` (category ``extrapolated``) per battery in the run's verdict,
naming SOC, cell current or temperature, the fitted range and when the run left it. The real
underpowered.log fitted, then flown again through the closed loop as the issue's variants:
the same flight, at -10 degC, a longer mission."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.config import parse_config
from packpilot.sim.fit_range import battery_excursions, excursions
from packpilot.sim.runner import simulate
from packpilot.sim.verdict import CATEGORIES, parse_fail_on, run_verdict

LOG = (
    Path(__file__).resolve().parents[1]
    / "examples"
    / "logs"
    / "real"
    / "ardupilot_3x_underpowered.log"
)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("fit") / "mine.json"
    res = CliRunner().invoke(app, ["fit", str(LOG), "--cells", "3", "--out", str(out)])
    assert res.exit_code == 0, res.output
    return out


def _outside(fitted: Path, ambient_c: float = 25.0, duration_s: float = 429.0,
             repeat: bool = False) -> list[Any]:  # fmt: skip
    notes = json.loads(fitted.read_text())["notes"]
    (soc0,) = [p["value"] for p in notes["initial_soc"].values()]
    cfg = parse_config({
        "pack": {"cell": str(fitted), "ambient_c": ambient_c,
                 "batteries": [{"name": "A", "series_groups": 3, "soc0": min(soc0, 1.0)}]},
        "load": {"kind": "current", "profile": str(LOG), "repeat": repeat},
        "sim": {"dt_s": 1.0, "duration_s": duration_s, "progress": False},
    })  # fmt: skip
    verdict = run_verdict(simulate(cfg), cfg.model_dump(mode="json"))
    return [a for a in verdict.alarms if a.kind == "OutsideFit"]


def test_the_cold_and_the_longer_mission_are_flagged(fitted: Path) -> None:
    window = json.loads(fitted.read_text())["notes"]["window"]
    same = _outside(fitted)
    # the same flight at 25 degC: only its part past the fit's training window (SOC)
    assert len(same) == 1 and "start temperature" not in same[0].cause
    assert f"fitted on {100 * window['soc_min']:.0f}-" in same[0].cause
    # the set's OCV was corrected on the training window: beyond it the row says so
    ocv = json.loads(fitted.read_text())["notes"]["ocv"]
    lo, hi = ocv["window_soc"]
    assert f"OCV was corrected from the data on {100 * lo:.0f}-{100 * hi:.0f} %" in same[0].cause
    assert "held at its edge value" in same[0].cause
    cold = _outside(fitted, ambient_c=-10.0)
    assert len(cold) == 1 and cold[0].t_s == 0.0, cold
    assert "start temperature -10.0 degC" in cold[0].cause and "fitted as at 25.0" in cold[0].cause
    assert cold[0].severity.label == "warning" and cold[0].category == "extrapolated"
    longer = _outside(fitted, duration_s=1200.0, repeat=True)
    low = float(longer[0].cause.split("SOC down to ")[1].split(" %")[0])
    same_low = float(same[0].cause.split("SOC down to ")[1].split(" %")[0])
    assert low < same_low - 20


def test_current_and_logged_temperature_ranges() -> None:
    notes = {"window": {"soc_min": 0.4, "soc_max": 0.9, "current_min_a": 0.0,
                        "current_max_a": 20.0, "temp_min_c": 15.0, "temp_max_c": 30.0}}  # fmt: skip
    t = np.arange(5.0)
    inside = battery_excursions(notes, t, np.full(5, 0.6), np.full(5, 20.9), np.full(5, 34.0))
    assert inside == []  # within the margins (5 % of current, 5 K)
    out = battery_excursions(
        notes, t, np.full(5, 0.6), np.array([10, 10, 30, 10, -3.0]), np.array([20, 20, 20, 36, 9.0])
    )
    whats = [w for _, w in out]
    assert [tt for tt, _ in out] == [2.0, 3.0, 4.0, 4.0]
    assert any("cell current 30.0 A" in w for w in whats)
    assert any("cell current -3.0 A" in w for w in whats)
    assert any("temperature 36.0 degC, fitted on 15.0..30.0" in w for w in whats)
    assert any("temperature 9.0 degC" in w for w in whats)


def test_shipped_sets_are_never_flagged_and_fail_on_knows_the_category() -> None:
    cfg = {"pack": {"cell": "uav_5ah", "batteries": [{"name": "A"}]}}
    battery = np.zeros((3, 1, 10))
    assert excursions(cfg, ["A"], np.arange(3.0), battery) == {}
    assert "extrapolated" in CATEGORIES and parse_fail_on("extrapolated") == ["extrapolated"]
