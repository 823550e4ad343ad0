"""Physically absurd input is refused with the field named (issue #18 §3): each case below
was accepted, crashed or hung before, and each fails if its check is removed.

Fast: configs are validated, CSVs parsed; nothing here simulates."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest

from packpilot.config import load_config, parse_config
from packpilot.errors import ConfigError, InputError
from packpilot.model import loads
from tests.conftest import dual_pack


def _with(path: str, value: Any, base: dict[str, Any] | None = None) -> dict[str, Any]:
    """``dual_pack()`` with the dotted ``path`` set to ``value`` (list indices as numbers)."""
    cfg = copy.deepcopy(base or dual_pack())
    node: Any = cfg
    keys: list[Any] = [int(k) if k.isdigit() else k for k in path.split(".")]
    for key in keys[:-1]:
        node = node[key] if isinstance(node, list) else node.setdefault(key, {})
    node[keys[-1]] = value
    return cfg


def _refused(cfg: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        parse_config(cfg, "c.toml")
    assert "\n" not in str(info.value)


BAT = "pack.batteries.0"


@pytest.mark.parametrize(
    ("path", "value", "match"),
    [
        # booleans are not numbers (pydantic's lax mode read true as 1)
        ("sim.dt_s", True, r"sim\.dt_s: must not be a boolean"),
        (f"{BAT}.ocv0_v", True, r"batteries\.0\.ocv0_v: must not be a boolean"),
        ("pack.thermal_nodes", True, r"pack\.thermal_nodes: must not be a boolean"),
        (f"{BAT}.series_groups", False, r"series_groups: must not be a boolean"),
        ("plausibility.cell_v_range", [0.5, True], r"cell_v_range: must not be a boolean"),
        ("protection.charge_detect_s", True, r"protection\.charge_detect_s: must not be a bool"),
        # durations and periods
        ("sim.duration_s", 1e-300, r"sim\.duration_s: .*greater than or equal to 0\.0001"),
        ("sim.duration_s", 0.0, r"sim\.duration_s"),
        ("sim.duration_s", 1e12, r"sim\.duration_s: a time of at most 1e\+09 s"),
        ("charger.connect_s", 1e300, r"charger\.connect_s"),
        ("charger.heartbeat_timeout_s", 1e300, r"charger\.heartbeat_timeout_s"),
        ("faults", [{"kind": "can_silence", "at_s": 1e300}], r"faults\.0\.at_s"),
        # per-battery physics
        (f"{BAT}.capacity_ah", 1e-300, r"capacity_ah: .*greater than or equal to 0\.001"),
        (f"{BAT}.capacity_ah", 1e308, r"capacity_ah: .*less than or equal to 10000"),
        (f"{BAT}.resistance_ohm", 1e6, r"resistance_ohm: 1e\+06 Ohm is .* per cell"),
        (f"{BAT}.resistance_ohm", 1e-9, r"resistance_ohm: 1e-09 Ohm"),
        (f"{BAT}.ocv0_v", 1e9, r"ocv0_v: 1e\+09 V is .* per cell \(6 in series\)"),
        (f"{BAT}.ocv0_v", 3.0, r"ocv0_v: 3 V is 0\.5 V per cell"),
        (f"{BAT}.ambient_offset_c", 1e300, r"ambient_offset_c"),
        ("pack.seed", -1, r"pack\.seed"),
        # switches, loads, charger
        ("pack.switch.diode_drop_v", 1e9, r"pack\.switch\.diode_drop_v: .*less than or equal"),
        ("pack.switch.on_ohm", 1e9, r"pack\.switch\.on_ohm"),
        ("load", {"kind": "current", "value": 1e24}, r"load: value: 1e\+24 A is more than"),
        ("load", {"kind": "power", "value": 1e24}, r"load: value: 1e\+24 W is more than"),
        ("load", {"kind": "resistance", "value": 1e-30}, r"load: value: 1e-30 Ohm is outside"),
        ("charger.rated_v", 1e9, r"charger\.rated_v"),
        ("charger.rated_a", 1e9, r"charger\.rated_a"),
        # method and safety sections
        ("protection.parameters", [{"name": "P1", "cutoff_v": 3.0, "t_max_s": 1e308}], "t_max_s"),
        ("limits.rows", [], r"limits\.rows: .*at least 1 item"),
        ("charging.cell_v_limit_v", 10.0, r"charging\.cell_v_limit_v"),
        ("plausibility.cell_v_range", [-1e9, 1e9], r"cell_v_range \(-1e\+09, 1e\+09\) must lie"),
        ("plausibility.temp_range_c", [-1e9, 1e9], r"temp_range_c .* must lie"),
        (
            "plausibility.clear_after_s",
            1e300,
            r"plausibility\.clear_after_s: a time of at most",
        ),
        ("equalization.t2_s", 1e-300, r"equalization\.t2_s: .*t2_s must be a time of at least"),
        ("equalization.t1_s", 1e300, r"equalization\.t1_s: a time of at most 1e\+09 s"),
    ],
)
def test_absurd_values_are_refused_with_the_field_named(path: str, value: Any, match: str) -> None:
    _refused(_with(path, value), match)


def test_a_limits_trip_row_at_100_volts_is_refused() -> None:
    row = {
        "limit": "over_voltage",
        "quantity": "cell_v_max",
        "direction": "above",
        "path": "charge",
        "tier": "trip",
        "threshold": 100.0,
        "reset": 4.1,
    }
    _refused(_with("limits.rows", [row]), r"threshold 100\.0 is outside 0\.\.5")


def test_a_t_max_lcm_too_large_is_refused() -> None:
    params = [
        {"name": "P1", "cutoff_v": 2.8, "t_max_s": 86_399.999},
        {"name": "P2", "cutoff_v": 3.0, "t_max_s": 86_399.997},
        {"name": "P3", "cutoff_v": 3.2, "t_max_s": 86_399.993},
    ]
    _refused(_with("protection.parameters", params), r"m = LCM of t_max .* too large")


def test_minus_zero_spread_reads_as_plus_zero() -> None:
    """``cell_soc_spread = -0.0`` passed ``>= 0`` and NumPy refused ``uniform(0.0, -0.0)``."""
    cfg = parse_config(_with(f"{BAT}.cell_soc_spread", -0.0))
    spread = cfg.pack.batteries[0].cell_soc_spread
    assert spread == 0.0 and str(spread) == "0.0"


def test_valid_booleans_and_numbers_still_pass() -> None:
    cfg = parse_config(_with("charger.present", True))
    assert cfg.charger.present is True
    assert parse_config(_with("sim.dt_s", 1)).sim.dt_s == 1.0  # an integer is a number


def test_a_huge_name_is_clipped_in_the_error() -> None:
    name = "x" * 1_000_000
    with pytest.raises(ConfigError) as info:
        parse_config(_with(f"{BAT}.name", name), "c.toml")
    text = str(info.value)
    assert len(text) < 400, len(text)
    assert "1,000,002 chars" in text  # repr adds the quotes


def test_a_toml_nested_500_deep_is_a_clear_error(tmp_path: Path) -> None:
    p = tmp_path / "deep.toml"
    for body in ("x = " + "[" * 500 + "]" * 500, "x = " + "{a = " * 500 + "1" + "}" * 500):
        p.write_text(body + "\n")
        with pytest.raises(ConfigError, match=r"deep\.toml: nested more than 16 levels deep"):
            load_config(p)
    p.write_text("x = " + "[" * 20 + "]" * 20 + "\n")  # parses, but deeper than any schema
    with pytest.raises(ConfigError, match="nested more than 16"):
        load_config(p)


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("t_s,current_a\n0,1e24\n", r"row 2, column current_a: 1e\+24 is outside"),
        ("t_s,power_w\n0,1e24\n", r"row 2, column power_w: 1e\+24 is outside"),
        ("t_s,resistance_ohm\n0,0\n", r"row 2, column resistance_ohm: 0 is outside"),
        ("t_s,current_a\n0,1\n1e306,2\n", r"row 3, column t_s: 1e\+306 is outside"),
    ],
)
def test_load_profile_values_are_bounded(tmp_path: Path, body: str, match: str) -> None:
    p = tmp_path / "prof.csv"
    p.write_text(body)
    with pytest.raises(InputError, match=match):
        loads.from_csv(p)


def test_replay_log_cells_are_bounded(tmp_path: Path) -> None:
    """``t_s = 1e306`` in a protection replay overflowed when turned into milliseconds."""
    from packpilot.replay.common import read_log

    p = tmp_path / "log.csv"
    p.write_text("t_s,current_a\n0,1\n1e306,2\n")
    with pytest.raises(InputError, match=r"row 3, column t_s: 1e\+306 is beyond"):
        read_log(p, ["t_s", "current_a"])


def test_an_equalization_replay_gap_is_bounded(tmp_path: Path) -> None:
    """A 1e8 s gap at T2 = 60 s would apply formula 2 ~1.7 million times in one row."""
    import numpy as np

    from packpilot.config.equalization import EqualizationConfig
    from packpilot.replay.common import row_durations
    from packpilot.replay.equalization import _check_gaps

    cfg = EqualizationConfig()
    ok = row_durations(np.array([0.0, 86_400.0, 86_401.0]))
    _check_gaps(tmp_path / "log.csv", ok, cfg)
    bad = row_durations(np.array([0.0, 1e8, 1e8 + 1]))
    with pytest.raises(InputError, match=r"log\.csv: row 2, column t_s: a gap of 1e\+08 s"):
        _check_gaps(tmp_path / "log.csv", bad, cfg)


@pytest.mark.parametrize(
    ("section", "value", "match"),
    [
        ("supervisor", {"fault_hold_s": 1e308}, r"supervisor\.fault_hold_s: a time of at most"),
        ("soc", {"rest_time_s": 1e308}, r"soc\.rest_time_s: a time of at most"),
        ("protection", {"filter_tau_s": {"temp_c": 1e300}}, r"protection\.filter_tau_s: a time"),
        ("sequencing", {"t_on": 1e300}, r"sequencing\.t_on: a time of at most"),
        ("charging", {"r_settle_s": 1e300}, r"charging\.r_settle_s: a time of at most"),
    ],
)
def test_every_time_setting_is_bounded(section: str, value: dict[str, Any], match: str) -> None:
    """One rule in the shared base: a field named ``*_s`` or ``t_*`` is at most 1e9 s."""
    _refused({**dual_pack(), section: value}, match)
