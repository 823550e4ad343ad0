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
}


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
    (trip,) = [e for e in res.events if e.kind == "ProtectionTripped"]
    t = res.trace.t_s
    current = res.trace.channel("current_a")[:, 0]
    dsg = res.trace.channel("dsg_on")[:, 0]
    return {
        "trip": trip,
        "energy_wh": float(res.metrics["energy_out_wh"]),
        "rest_ocv_v": float(runner.pack.cell_voltage_now()[0].mean()),
        "rest_s": runner.pack.t_s - trip.t_s,
        "after_trip_a": current[t > trip.t_s + 1.0],
        "dsg_after": dsg[t > trip.t_s + 1.0],
        "tripped_status": res.trace.status["protection_tripped"],
    }


def test_warm_light_rest_ocv_not_below_conservative_minus_10_mv() -> None:
    method = _run("warm_light", "method", rest=True)
    cons = _run("warm_light", "conservative", rest=True)
    assert method["rest_s"] >= 1800.0 and cons["rest_s"] >= 1800.0
    assert method["rest_ocv_v"] >= cons["rest_ocv_v"] - 0.010


@pytest.mark.xfail(
    strict=True,
    reason="measured +13.7 % on uav_5ah: the conservative baseline leaves only ~12 % SOC "
    "(low cell DCIR, self-heating from -10 degC); delivering until the weakest cell is empty "
    "would give only +11.3 %, so +15 % needs over-discharge. The cell's Arrhenius law (20 "
    "kJ/mol) was checked against PyBaMM's physics sets and kept; see "
    "docs/discharge_protection.md",
)
def test_cold_heavy_method_delivers_15_percent_more_energy_than_conservative() -> None:
    method = _run("cold_heavy", "method", rest=False)
    cons = _run("cold_heavy", "conservative", rest=False)
    assert method["energy_wh"] >= 1.15 * cons["energy_wh"]


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
