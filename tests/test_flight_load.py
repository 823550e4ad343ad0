"""A flight log as a scenario's load profile (#27 §4, what-if): the aircraft's total demand on
the log's own time base."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from packpilot.config.scenario import load_config
from packpilot.errors import InputError
from packpilot.io.flightlog import read_flight_log
from packpilot.sim.flight_load import flight_load
from packpilot.sim.loop import load_profile

LOGS = Path(__file__).resolve().parents[1] / "examples" / "logs"


def test_current_and_power_of_a_real_log() -> None:
    log = LOGS / "real" / "ardupilot_3x_underpowered.log"
    b = read_flight_log(log).batteries[0]
    cur = flight_load(log, "current")
    assert cur.kind == "current" and cur.t_s[0] == 0.0
    np.testing.assert_allclose(cur.value, b.current_a)
    pw = flight_load(log, "power")
    np.testing.assert_allclose(pw.value, b.current_a * b.voltage_v)
    # zero-order hold between the log's samples, as a CSV profile
    k = 100
    assert cur.at(float(cur.t_s[k]) + 0.5) == pytest.approx(float(b.current_a[k]))


def test_two_batteries_sum_and_charge_flowing_back_is_no_demand() -> None:
    prof = flight_load(LOGS / "px4_two_batteries.ulg", "current")
    table = read_flight_log(LOGS / "px4_two_batteries.ulg").table()
    total = table.columns["A_current_a"] + table.columns["B_current_a"]
    np.testing.assert_allclose(prof.value, np.maximum(total, 0.0))
    assert np.all(prof.value >= 0.0)


def test_resistance_from_a_log_is_refused() -> None:
    with pytest.raises(InputError, match="'current' or 'power'"):
        flight_load(LOGS / "real" / "ardupilot_3x_underpowered.log", "resistance")


def test_scenario_resolves_a_relative_flight_log(tmp_path: Path) -> None:
    (tmp_path / "logs").mkdir()
    src = LOGS / "real" / "ardupilot_3x_underpowered.log"
    (tmp_path / "logs" / "f.log").write_bytes(src.read_bytes())
    toml = tmp_path / "s.toml"
    toml.write_text(
        '[pack]\nname = "p"\ncell = "uav_5ah"\n[[pack.batteries]]\nname = "A"\n'
        'series_groups = 3\nsoc0 = 0.9\n[load]\nkind = "current"\nprofile = "logs/f.log"\n'
        "[sim]\ndt_s = 1.0\nduration_s = 60.0\n"
    )
    cfg = load_config(toml)
    assert cfg.load.profile == str((tmp_path / "logs" / "f.log").resolve())
    prof = load_profile(cfg)
    assert prof.kind == "current" and prof.t_s.size == 430
