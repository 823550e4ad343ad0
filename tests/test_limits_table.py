"""LimitsConfig: the default table's values and load-time rejection of bad rows (ConfigError)."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import pytest

from packpilot.control.limits import DEFAULT_ROWS, CurveTable, LimitsConfig
from packpilot.errors import ConfigError


def _rows() -> list[dict[str, Any]]:
    return [r.model_dump() for r in DEFAULT_ROWS]


def _thresholds(limit: str) -> dict[str, float]:
    return {r.tier: r.threshold for r in DEFAULT_ROWS if r.limit == limit}


def test_default_table_has_three_tiers_for_each_of_eight_limits() -> None:
    cfg = LimitsConfig()
    names = {r.limit for r in cfg.rows}
    assert names == {
        "over_voltage",
        "under_voltage",
        "over_current_charge",
        "over_current_discharge",
        "over_temp_charge",
        "over_temp_discharge",
        "under_temp_charge",
        "under_temp_discharge",
    }
    assert all(sorted(_thresholds(n)) == ["derate", "trip", "warn"] for n in names)


def test_default_values_follow_the_nmc_reasoning() -> None:
    assert _thresholds("over_voltage") == {"warn": 4.20, "derate": 4.22, "trip": 4.25}
    assert _thresholds("under_voltage") == {"warn": 2.9, "derate": 2.8, "trip": 2.7}
    assert _thresholds("over_temp_discharge") == {"warn": 50.0, "derate": 55.0, "trip": 60.0}
    assert _thresholds("over_temp_charge") == {"warn": 40.0, "derate": 43.0, "trip": 45.0}
    assert _thresholds("under_temp_charge")["trip"] == 0.0
    assert _thresholds("over_current_discharge")["trip"] == 20.0  # C
    paths = {r.limit: r.path for r in DEFAULT_ROWS}
    assert paths["over_voltage"] == paths["over_current_charge"] == "charge"
    assert paths["under_voltage"] == paths["over_temp_discharge"] == "discharge"


def _load_with(k: int, **change: Any) -> LimitsConfig:
    rows = _rows()
    rows[k].update(change)
    return LimitsConfig.load({"rows": rows}, "pack.toml")


def _index(limit: str, tier: str) -> int:
    return next(k for k, r in enumerate(DEFAULT_ROWS) if r.limit == limit and r.tier == tier)


@pytest.mark.parametrize(
    ("limit", "tier", "change", "needle"),
    [
        ("over_voltage", "trip", {"reset": 4.30}, "reset 4.3 must be below threshold 4.25"),
        ("under_voltage", "trip", {"reset": 2.6}, "reset 2.6 must be above threshold 2.7"),
        ("over_voltage", "warn", {"debounce": 0}, "debounce must be >= 1"),
        ("over_voltage", "warn", {"delay_s": -1.0}, "delay_s must be a finite time >= 0"),
        ("over_voltage", "trip", {"latch_s": -5.0}, "latch_s must be"),
        ("over_voltage", "warn", {"direction": "below"}, "only limited 'above'"),
        ("over_voltage", "warn", {"limit": "Over-Voltage"}, "lower-case"),
        ("over_voltage", "warn", {"threshold": float("nan")}, "threshold must be a finite"),
    ],
)
def test_bad_row_is_a_config_error_naming_the_row(
    limit: str, tier: str, change: dict[str, Any], needle: str
) -> None:
    k = _index(limit, tier)
    with pytest.raises(ConfigError) as err:
        _load_with(k, **change)
    msg = str(err.value)
    assert msg.startswith(f"pack.toml: limits.rows.{k}")
    assert needle in msg
    assert "\n" not in msg


def test_tiers_out_of_order_name_the_offending_row() -> None:
    k = _index("over_voltage", "derate")
    with pytest.raises(ConfigError, match=rf"rows\[{k}\] \(over_voltage/derate\).*warn before"):
        _load_with(k, threshold=4.19, reset=4.1)
    k = _index("under_voltage", "trip")
    with pytest.raises(ConfigError, match=rf"rows\[{k}\] \(under_voltage/trip\).*must lie below"):
        _load_with(k, threshold=2.85)


def test_ladder_rows_must_agree_and_not_repeat_a_tier() -> None:
    k = _index("over_voltage", "trip")
    with pytest.raises(ConfigError, match=rf"rows\[{k}\].*path 'discharge' differs"):
        _load_with(k, path="discharge")
    with pytest.raises(ConfigError, match=r"tier 'warn' repeats"):
        _load_with(k, tier="warn")


def test_derating_tables_are_validated() -> None:
    with pytest.raises(ConfigError, match=r"limits.derating.charge_vs_soc: x: must be strictly"):
        LimitsConfig.load({"derating": {"charge_vs_soc": {"x": [0.5, 0.2], "c_rate": [1, 1]}}})
    with pytest.raises(ConfigError, match=r"c_rate: values must be finite and >= 0"):
        LimitsConfig.load({"derating": {"discharge_vs_cell_v": {"x": [3.0], "c_rate": [-1.0]}}})
    with pytest.raises(ConfigError, match=r"derate_fraction must be within 0\.\.1"):
        LimitsConfig.load({"derate_fraction": 1.5})


def test_curve_table_interpolates_and_clamps() -> None:
    t = CurveTable(x=(0.0, 10.0, 20.0), c_rate=(0.0, 2.0, 1.0))
    assert t.at(-5.0) == 0.0 and t.at(25.0) == 1.0
    assert t.at(5.0) == pytest.approx(1.0) and t.at(15.0) == pytest.approx(1.5)
    assert t.at(float("nan")) == 0.0  # unknown input: the table's safest value


def test_toml_table_round_trip() -> None:
    text = """
    derate_fraction = 0.25
    [[rows]]
    limit = "ov"
    quantity = "cell_v_max"
    direction = "above"
    path = "charge"
    tier = "warn"
    threshold = 3.55
    reset = 3.5
    debounce = 2
    [[rows]]
    limit = "ov"
    quantity = "cell_v_max"
    direction = "above"
    path = "charge"
    tier = "trip"
    threshold = 3.65
    reset = 3.5
    debounce = 2
    delay_s = 1.0
    """
    cfg = LimitsConfig.load(tomllib.loads(text), "lfp.toml")
    assert [r.tier for r in cfg.rows] == ["warn", "trip"]
    assert cfg.rows[1].latch_s == 0.0 and cfg.derate_fraction == 0.25
    with pytest.raises(ConfigError, match=r"lfp\.toml: limits\.bogus: unknown key"):
        LimitsConfig.load({"bogus": 1}, "lfp.toml")


def test_docs_limit_table_matches_the_defaults() -> None:
    """docs/safety.md shows DEFAULT_ROWS; regenerate the table there if this fails."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "safety.md").read_text()
    block = text.split("<!-- limits-table")[1].split("<!-- /limits-table -->")[0]
    lines = [ln for ln in block.splitlines() if ln.startswith("| ") and ln[2].isdigit()]
    assert len(lines) == len(DEFAULT_ROWS)
    for k, (line, r) in enumerate(zip(lines, DEFAULT_ROWS, strict=True)):
        latch = "manual" if r.latch_s is None else f"{r.latch_s:g}"
        cells = [
            str(k),
            r.limit,
            r.quantity,
            r.direction,
            r.path,
            r.when,
            r.tier,
            f"{r.threshold:g}",
            f"{r.reset:g}",
            str(r.debounce),
            f"{r.delay_s:g}",
            latch,
        ]
        assert [c.strip() for c in line.strip("|").split("|")] == cells, line
