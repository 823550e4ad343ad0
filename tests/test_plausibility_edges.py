"""Plausibility at its exact edges (#18 §1: rules only mutation testing showed unguarded).

The plausible ranges are closed (a reading exactly at an edge is plausible), a sample exactly
``max_sample_age_s`` old is fresh (stale means *older*), and every pack or battery reading the
docs list under ``nonfinite`` is checked, the load current and the battery current included.
"""

from __future__ import annotations

import math
from typing import Any

import pytest

from packpilot.contract.charger import CHARGER_OFF
from packpilot.control.plausibility import PlausibilityConfig
from tests.test_limits_helpers import CAP
from tests.test_plausibility_monitor import _FIELDS, AgedMeasurement, PDriver, faults, live

CFG = PlausibilityConfig()


@pytest.mark.parametrize(
    "edge",
    [
        {"max_cell_v": CFG.cell_v_range[1]},
        {"min_cell_v": CFG.cell_v_range[0]},
        {"temp_c": CFG.temp_range_c[1]},
        {"min_temp_c": CFG.temp_range_c[0]},
        {"soc": CFG.soc_range[1]},
        {"soc": CFG.soc_range[0]},
        {"current_a": CFG.current_range_c[1] * CAP},
        {"current_a": CFG.current_range_c[0] * CAP},
    ],
    ids=lambda e: "-".join(f"{k}={v}" for k, v in e.items()),
)
def test_a_reading_exactly_at_a_range_edge_is_plausible(edge: dict[str, Any]) -> None:
    """Held 5 s (ten times the range delay): no fault."""
    d = PDriver()
    outs = d.run(lambda k: (live(k, **edge), live(k)), 50)
    assert not faults(outs), [e.data for e in faults(outs)]


def test_a_reading_just_outside_a_range_edge_is_not() -> None:
    """The companion of the edge test: one ulp-ish step past the edge is a fault."""
    d = PDriver()
    outs = d.run(lambda k: (live(k, max_cell_v=CFG.cell_v_range[1] + 1e-6), live(k)), 50)
    assert [e.data["kind"] for e in faults(outs)] == ["out_of_range"]


def test_a_sample_exactly_max_sample_age_old_is_fresh() -> None:
    def aged(k: int, age: float) -> AgedMeasurement:
        return AgedMeasurement(**{f: getattr(live(k), f) for f in _FIELDS}, sample_age_s=age)

    d = PDriver()
    assert not faults(d.run(lambda k: (aged(k, CFG.max_sample_age_s), live(k)), 20))


def test_a_nan_load_current_is_a_pack_fault_that_stops_the_charger() -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k), live(k)), 10, load_current_a=math.nan)
    (ev,) = faults(outs)
    assert ev.battery is None and ev.data["field"] == "load_current_a"
    assert outs[-1].commands.charger == CHARGER_OFF
    assert d.mon.pack_fault


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_a_nonfinite_battery_current_is_a_fault(bad: float) -> None:
    d = PDriver()
    outs = d.run(lambda k: (live(k, current_a=bad), live(k)), 10)
    (ev,) = faults(outs)
    assert ev.battery == 0 and ev.data["kind"] == "nonfinite"
    assert ev.data["field"] == "current_a"
