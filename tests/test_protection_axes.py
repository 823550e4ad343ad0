"""Internal resistance (estimated online from current steps) and cycle count as optional
table axes beside SOH (#15 §4)."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from packpilot.control.protection import ProtectionConfig
from tests.test_protection_controller import Driver, _bm

R_TABLE = ProtectionConfig.model_validate(
    {
        "parameters": [
            {"name": "LOW_R", "cutoff_v": 3.0, "t_max_s": 10},
            {"name": "HIGH_R", "cutoff_v": 3.2, "t_max_s": 5},
        ],
        "table": [
            {"param": "LOW_R", "ranges": {"resistance_ohm": "(-inf, 0.01]"}},
            {"param": "HIGH_R", "ranges": {"resistance_ohm": "(0.01, inf)"}},
        ],
    }
)
CYCLE_TABLE = ProtectionConfig.model_validate(
    {
        "parameters": [
            {"name": "NEW", "cutoff_v": 3.0, "t_max_s": 10},
            {"name": "AGED", "cutoff_v": 3.1, "t_max_s": 5},
        ],
        "table": [
            {"param": "NEW", "ranges": {"cycle_count": "(-inf, 300)"}},
            {"param": "AGED", "ranges": {"cycle_count": "[300, inf)"}},
        ],
    }
)


def _param(d: Driver) -> str:
    return d.outputs[-1].status["protection_param"][0]  # type: ignore[no-any-return]


def test_resistance_estimated_from_a_current_step() -> None:
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    assert math.isnan(d.ctl.battery(0).resistance_ohm)
    d.step(_bm(25.0, 25.0, 3.50), 1.0)  # 20 A step, 100 mV: 5 mOhm
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.005)
    d.step(_bm(26.0, 25.0, 3.40), 1.0)  # 1 A < the 2 A step: ignored
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.005)
    d.step(_bm(6.0, 25.0, 3.70), 1.0)  # from (26 A, 3.40 V): 300 mV / 20 A = 15 mOhm
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.005 + 0.25 * (0.015 - 0.005))


def test_resistance_step_and_gain_are_configurable() -> None:
    d = Driver(R_TABLE.model_copy(update={"resistance_step_a": 0.5, "resistance_gain": 1.0}))
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    d.step(_bm(6.0, 25.0, 3.59), 1.0)  # 1 A step now counts: 10 mOhm
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.01)
    d.step(_bm(8.0, 25.0, 3.55), 1.0)  # gain 1: the last step alone, 20 mOhm
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.02)


def test_exactly_the_step_threshold_counts() -> None:
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    d.step(_bm(7.0, 25.0, 3.58), 1.0)  # exactly 2 A
    assert d.ctl.battery(0).resistance_ohm == pytest.approx(0.01)


def test_a_non_physical_step_is_ignored() -> None:
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    d.step(_bm(25.0, 25.0, 3.70), 1.0)  # voltage up with more load: negative R
    assert math.isnan(d.ctl.battery(0).resistance_ohm)


def test_resistance_axis_selects_the_row() -> None:
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    assert _param(d) == "HIGH_R"  # unknown: the most conservative row
    assert d.events("Fault") == []  # an estimate pending is no sensor fault
    d.step(_bm(25.0, 25.0, 3.50), 1.0)  # 5 mOhm, used from the next tick
    d.step(_bm(25.0, 25.0, 3.50), 1.0)
    assert _param(d) == "LOW_R"
    d2 = Driver(R_TABLE.model_copy(update={"resistance_gain": 1.0}))
    d2.step(_bm(5.0, 25.0, 3.60), 1.0)
    d2.step(_bm(25.0, 25.0, 3.30), 1.0)  # 15 mOhm
    d2.step(_bm(25.0, 25.0, 3.30), 1.0)
    assert _param(d2) == "HIGH_R"


def test_resistance_forgotten_when_the_battery_leaves() -> None:
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    d.step(_bm(25.0, 25.0, 3.50), 1.0)
    d.step(_bm(25.0, 25.0, 3.50, present=False), 1.0)
    assert math.isnan(d.ctl.battery(0).resistance_ohm)


@pytest.mark.parametrize(("cycles", "param"), [(0.0, "NEW"), (299.0, "NEW"), (300.0, "AGED")])
def test_cycle_count_axis(cycles: float, param: str) -> None:
    d = Driver(CYCLE_TABLE)
    d.step(replace(_bm(10.0, 25.0, 3.6), cycle_count=cycles), 1.0)
    assert _param(d) == param


def test_cycle_count_unknown_is_a_fault_and_most_conservative() -> None:
    d = Driver(CYCLE_TABLE)
    d.step(_bm(10.0, 25.0, 3.6), 1.0)  # not reported
    assert _param(d) == "AGED"
    (f,) = d.events("Fault")
    assert f.data["field"] == "cycle_count"  # type: ignore[attr-defined]


def test_resistance_config_validated() -> None:
    for kw in ({"resistance_step_a": 0.0}, {"resistance_gain": 0.0}, {"resistance_gain": 1.5}):
        with pytest.raises(ValueError):
            ProtectionConfig(**kw)  # type: ignore[arg-type]


def test_no_estimate_from_a_fallback_voltage() -> None:
    """Only the min cell voltage (one cell's reading) gives a resistance; the mean cell of a
    fallback is a different quantity."""
    d = Driver(R_TABLE)
    d.step(replace(_bm(5.0, 25.0, 3.60), min_cell_v=math.nan), 1.0)
    d.step(replace(_bm(25.0, 25.0, 3.50), min_cell_v=math.nan), 1.0)
    assert math.isnan(d.ctl.battery(0).resistance_ohm)


def test_a_step_without_a_voltage_change_is_no_resistance() -> None:
    """A 20 A step at an unchanged check voltage gives R = 0, which no cell has: it is not
    learned, the resistance stays unknown and the row is the most conservative one, not the
    low-resistance row (generated mutant b4d54e0b86: ``r_new > 0`` -> ``>= 0`` learned 0 Ohm)."""
    d = Driver(R_TABLE)
    d.step(_bm(5.0, 25.0, 3.60), 1.0)
    d.step(_bm(25.0, 25.0, 3.60), 1.0)
    assert math.isnan(d.ctl.battery(0).resistance_ohm)
    assert _param(d) == "HIGH_R"


SOH_TABLE = ProtectionConfig.model_validate(
    {
        "parameters": [
            {"name": "NEW", "cutoff_v": 3.0, "t_max_s": 10},
            {"name": "AGED", "cutoff_v": 3.1, "t_max_s": 5},
        ],
        "table": [
            {"param": "NEW", "ranges": {"soh": "[0.8, inf)"}},
            {"param": "AGED", "ranges": {"soh": "(-inf, 0.8)"}},
        ],
    }
)


def test_soh_axis_is_full_over_nominal_capacity() -> None:
    """The SOH axis is the reported full capacity over the pack's nominal one (5 Ah): 5 Ah is
    SOH 1.0 (the NEW row, no axis fault), 3.5 Ah is 0.7 (AGED) (generated mutant 31a8b923ce:
    ``cap > 0`` -> ``cap < 0`` made every SOH unknown, the most conservative row)."""
    d = Driver(SOH_TABLE)
    d.step(_bm(5.0, 25.0, 3.6), 1.0)
    assert _param(d) == "NEW"
    assert not d.events("Fault")
    d.step(replace(_bm(5.0, 25.0, 3.6), full_capacity_ah=3.5), 1.0)
    assert _param(d) == "AGED"
