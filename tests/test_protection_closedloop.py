"""Closed-loop acceptance claims of the discharge protection on the uav_5ah plant.

Scenarios are the shipped ``examples/protection_*.toml``; the baselines are the same controller
with a one-row table. Measured numbers and the analysis are in docs/discharge_protection.md.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import load_config
from packpilot.config.protection import ProtectionConfig
from packpilot.model.cell import load_parameter_set
from packpilot.model.cell.calibrate import calibrate_protection
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

BASELINES: dict[str, dict[str, Any] | None] = {
    "method": None,
    "conservative": {
        "parameters": [{"name": "F", "cutoff_v": 3.2, "t_max_s": 5}],
        "table": [{"param": "F"}],
    },
    "aggressive": {
        "parameters": [{"name": "F", "cutoff_v": 2.8, "t_max_s": 15}],
        "table": [{"param": "F"}],
    },
    # never trips above 2.0 V: the reference for the energy available above the SOC floor
    "no_trip": {
        "parameters": [{"name": "F", "cutoff_v": 2.0, "t_max_s": 86400}],
        "table": [{"param": "F"}],
    },
}
SOC_FLOOR = 0.02
BASELINES["calibrated"] = calibrate_protection(load_parameter_set("uav_5ah"), SOC_FLOOR)[
    0
].model_dump()


@cache
def _run(scenario: str, strategy: str, rest: bool) -> dict[str, Any]:
    cfg = load_config(EXAMPLES / f"protection_{scenario}.toml")
    update: dict[str, Any] = {"controller": ["protection"]}
    if BASELINES[strategy] is not None:
        update["protection"] = ProtectionConfig.model_validate(BASELINES[strategy])
    if not rest:
        update["sim"] = cfg.sim.model_copy(update={"stop_when_unsupplied_s": 1.0})
    runner = Runner(cfg.model_copy(update=update), progress=False)
    res = runner.run()
    trips = [e for e in res.events if e.kind == "ProtectionTripped"]
    trip = trips[0] if trips else None
    t = res.trace.t_s
    v = res.trace.channel("voltage_v")[:, 0]
    i = res.trace.channel("current_a")[:, 0]
    soc_tr = res.trace.channel("remaining_ah")[:, 0] / res.trace.channel("full_ah")[:, 0]
    floor = np.flatnonzero(soc_tr <= SOC_FLOOR)
    dt = float(t[1] - t[0])
    soc, _ = runner.pack.cell_states()
    current = res.trace.channel("current_a")[:, 0]
    dsg = res.trace.channel("dsg_on")[:, 0]
    return {
        "trip": trip,
        "energy_wh": float(res.metrics["energy_out_wh"]),
        "rest_ocv_v": float(runner.pack.cell_voltage_now()[0].mean()),
        "rest_s": runner.pack.t_s - (trip.t_s if trip else runner.pack.t_s),
        "after_trip_a": current[t > trip.t_s + 1.0] if trip else current[:0],
        "dsg_after": dsg[t > trip.t_s + 1.0] if trip else dsg[:0],
        "energy_to_floor_wh": (
            None
            if floor.size == 0
            else float(np.sum(np.maximum(v * i, 0.0)[: floor[0]]) * dt / 3600)
        ),
        "min_cell_soc": float(soc[0].min()),
        "tripped_status": res.trace.status["protection_tripped"],
    }


def test_warm_light_rest_ocv_not_below_conservative_minus_10_mv() -> None:
    method = _run("warm_light", "method", rest=True)
    cons = _run("warm_light", "conservative", rest=True)
    assert method["rest_s"] >= 1800.0 and cons["rest_s"] >= 1800.0
    assert method["rest_ocv_v"] >= cons["rest_ocv_v"] - 0.010


def test_cold_heavy_method_delivers_more_energy_than_conservative() -> None:
    method = _run("cold_heavy", "method", rest=False)
    cons = _run("cold_heavy", "conservative", rest=False)
    assert method["energy_wh"] > cons["energy_wh"]
    assert cons["trip"].data["param"] == "F"
    assert method["trip"].t_s > cons["trip"].t_s


def test_cold_heavy_selects_p1_and_matches_the_aggressive_baseline() -> None:
    """Above 25 A the spec's grid is P1 at every temperature, i.e. 2.8 V / 15 s."""
    method = _run("cold_heavy", "method", rest=False)
    aggr = _run("cold_heavy", "aggressive", rest=False)
    assert method["trip"].data["param"] == "P1"
    assert method["trip"].t_s == aggr["trip"].t_s
    assert method["energy_wh"] == pytest.approx(aggr["energy_wh"], rel=1e-12)


def test_trip_opens_the_discharge_path_and_latches() -> None:
    run = _run("warm_light", "method", rest=True)
    assert run["trip"].data["param"] == "P3"
    assert np.all(np.abs(run["after_trip_a"]) < 1e-6)
    assert run["dsg_after"].size > 0 and not np.any(run["dsg_after"])
    flags = [row[0] for row in run["tripped_status"]]
    first = flags.index(True)
    assert all(flags[first:]) and not any(flags[:first])


# The +15 % target of the earlier protection issue is withdrawn (#15 §4: on uav_5ah only
# +11.3 % exists above empty); its strict xfail is replaced by the calibrated table's goal.


@pytest.mark.parametrize("scenario", ["cold_heavy", "warm_light", "warming_flight"])
def test_calibrated_table_captures_95_percent_above_the_floor_and_never_below_empty(
    scenario: str,
) -> None:
    ref = _run(scenario, "no_trip", rest=False)["energy_to_floor_wh"]
    cal = _run(scenario, "calibrated", rest=True)
    assert ref is not None and cal["trip"] is not None
    assert cal["energy_wh"] >= 0.95 * ref
    assert cal["min_cell_soc"] >= 0.0
