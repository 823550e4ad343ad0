"""Closed-loop acceptance of parallel-discharge sequencing on the project plant (uav_5ah cells).

Scenarios ``examples/sequencing_*.toml`` against the baseline of direct parallel (no controller,
every FET on). Runs use dt = 0.5 s to stay fast; the benchmark runs them at the files' 0.1 s.
"""

from __future__ import annotations

import json
import subprocess
import sys
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import Result
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _cfg(name: str, strategy: str, **sim: float) -> ScenarioConfig:
    cfg = load_config(EXAMPLES / f"sequencing_{name}.toml")
    return cfg.model_copy(
        update={
            "controller": [] if strategy == "direct" else ["sequencing"],
            "sim": cfg.sim.model_copy(update={"progress": False, **sim}),
        }
    )


@cache
def _run(name: str, strategy: str, dt_s: float = 0.5) -> Result:
    return Runner(_cfg(name, strategy, dt_s=dt_s)).run()


def _first_brownout(res: Result) -> float:
    tr = res.trace
    uns = (tr.load_demand_a > 1e-9) & (tr.load_a < tr.load_demand_a - 1e-6)
    return float(tr.t_s[int(np.argmax(uns))]) if uns.any() else float("inf")


def _energy_to_brownout_wh(res: Result, dt_s: float = 0.5) -> float:
    tr = res.trace
    k = int(np.searchsorted(tr.t_s, _first_brownout(res)))
    return float(np.sum(tr.bus_v[:k] * tr.load_a[:k]) * dt_s / 3600.0)


def _energy_with_budget_wh(res: Result, budget_s: float, dt_s: float = 0.5) -> float:
    """Energy delivered until the load has been unsupplied for ``budget_s`` in total (the
    scenario's brown-out budget counted the same way for a pulsing and a latched-off load)."""
    tr = res.trace
    uns = (tr.load_demand_a > 1e-9) & (tr.load_a < tr.load_demand_a - 1e-6)
    over = np.nonzero(np.cumsum(uns) * dt_s >= budget_s - 1e-9)[0]
    k = int(over[0]) + 1 if over.size else len(uns)
    return float(np.sum(tr.bus_v[:k] * tr.load_a[:k]) * dt_s / 3600.0)


def _into(res: Result) -> np.ndarray:
    return np.maximum(-res.trace.channel("current_a"), 0.0)


def test_direct_parallel_pushes_about_50a_into_the_low_battery_on_connection() -> None:
    res = Runner(_cfg("dual_hover", "direct", dt_s=0.1, duration_s=1.0)).run()
    peak_into_b = float(_into(res)[:, 1].max())
    # 2 V / (2 x 20 mOhm + 4 x 0.1 mOhm FETs) = 49.5 A: the spec's "about 50 A".
    assert 47.0 <= peak_into_b <= 52.0


@pytest.mark.parametrize("name", ["dual_hover", "hot_insert", "four_spread"])
def test_sequencing_never_supplies_less_and_keeps_the_energy(name: str) -> None:
    base, seq = _run(name, "direct"), _run(name, "sequencing")
    assert seq.metrics["events"].get("Fault", 0) == 0
    # The load browns out no earlier than with every FET on (i.e. only when the batteries
    # together are at the load's cut-off), and delivers >= 99 % of the energy up to then.
    assert _first_brownout(seq) >= _first_brownout(base)
    assert _energy_to_brownout_wh(seq) >= 0.99 * _energy_to_brownout_wh(base)
    # Body diodes carry current only for the R3 episodes (a few joules, not a lossy path).
    diode_j = sum(seq.metrics["chg_diode_energy_j"]) + sum(seq.metrics["dsg_diode_energy_j"])
    assert diode_j < 0.001 * seq.metrics["energy_out_wh"] * 3600.0
    # STANDBY never has its charge FET on (effective gate, from the plant).
    chg = seq.trace.channel("chg_on")
    for row, states in zip(chg, seq.trace.status["seq_state"], strict=True):
        assert all(not c for c, s in zip(row, states, strict=True) if s == "STANDBY")


@pytest.mark.parametrize("name", ["dual_hover", "hot_insert", "four_spread"])
def test_energy_at_least_99_percent_under_the_same_brownout_budget(name: str) -> None:
    # Both strategies stop counting once the load has been unsupplied for the scenario's
    # stop_when_unsupplied_s in total (direct parallel pulses the load after its first
    # brown-out, which resets the runner's continuous-brown-out counter).
    budget_s = _cfg(name, "direct").sim.stop_when_unsupplied_s
    assert budget_s is not None
    base, seq = _run(name, "direct"), _run(name, "sequencing")
    assert _energy_with_budget_wh(seq, budget_s) >= 0.99 * _energy_with_budget_wh(base, budget_s)


@pytest.mark.parametrize("name", ["dual_hover", "hot_insert"])
def test_no_current_into_any_battery_while_the_pack_discharges(name: str) -> None:
    base, seq = _run(name, "direct"), _run(name, "sequencing")
    assert base.metrics["peak_cross_current_a"] > 30.0
    assert seq.metrics["peak_cross_current_a"] <= 1.0


def test_dual_hover_low_battery_waits_then_joins() -> None:
    seq = _run("dual_hover", "sequencing")
    joins = [e for e in seq.events if e.kind == "BatteryJoined"]
    # Battery B joins first when its rest voltage meets A's fast voltage V + I*R (load merge),
    # before its terminal voltage is v_co above A's loaded one (R2).
    assert (joins[0].battery, joins[0].data["reason"]) == (1, "load merge")
    k = int(np.searchsorted(seq.trace.t_s, joins[0].t_s))
    assert not seq.trace.channel("chg_on")[:k, 1].any()
    assert np.all(seq.trace.channel("current_a")[:k, 1] == 0.0)
    # Afterwards the guard time-shares while their fast voltages drift apart under load (a
    # battery it opens comes back by load merge or R2 within seconds): both carry the load
    # most of the time, and every guard opening is followed by a rejoin or the end of the run.
    cur = seq.trace.channel("current_a")[k:]
    both = np.mean(np.all(cur > 1.0, axis=1))
    assert both > 0.8
    guard = [e for e in seq.events if e.kind == "CrossCurrentGuard"]
    for g in guard:
        assert any(j.battery == g.battery and j.t_s > g.t_s for j in joins)


def test_hot_inserted_fresh_battery_takes_over() -> None:
    seq = _run("hot_insert", "sequencing")
    at_300 = [e for e in seq.events if e.t_s == 300.0 and e.kind == "StateChanged"]
    assert {(e.battery, e.data["to"]) for e in at_300} >= {(0, "STANDBY"), (1, "DISCHARGING")}
    rejoin = [e for e in seq.events if e.kind == "BatteryJoined"]
    assert rejoin[0].battery == 0 and rejoin[0].t_s > 300.0


def test_four_spread_never_pushes_more_than_1a_into_a_battery() -> None:
    base, seq = _run("four_spread", "direct"), _run("four_spread", "sequencing")
    assert seq.metrics["load_unsupplied_s"] == 0.0
    assert seq.metrics["peak_cross_current_a"] <= 1.0
    assert float(_into(seq).max()) <= 1.0
    # The guard acted (the landing step alone pushed 2.5 A without it).
    assert seq.metrics["events"].get("CrossCurrentGuard", 0) >= 1

    def cross(r: Result) -> float:
        return float(_into(r)[r.trace.load_a > 1e-3].sum())

    assert cross(seq) < 0.002 * cross(base)


@pytest.mark.xfail(
    strict=True,
    reason="at the first brown-out the load cut pushes 0.96 A (> i_rev) from B into A, which is "
    "demoted; at rest their terminal voltages stay 40-48 mV apart, i.e. 1.0-1.2 A over the "
    "40.4 mOhm loop, outside the rest-merge window (i_merge <= i_rev = 0.5 A -> 20.2 mV), and B "
    "alone sags below the load's 19.8 V lock-out before A's 0.6 V diode conducts, so neither the "
    "rest merge nor R2/R3 brings A back; direct parallel keeps pulsing the load and delivers "
    "~4 % more (docs/parallel_discharge.md)",
)
def test_dual_hover_total_energy_including_post_brownout_pulsing() -> None:
    base, seq = _run("dual_hover", "direct"), _run("dual_hover", "sequencing")
    assert seq.metrics["energy_out_wh"] >= 0.99 * base.metrics["energy_out_wh"]


def test_cli_simulate_reports_peak_cross_current() -> None:
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "packpilot.cli",
            "simulate",
            str(EXAMPLES / "sequencing_dual_hover.toml"),
            "--json",
            "--no-progress",
            "--duration",
            "300",
        ],
        capture_output=True,
        text=True,
        check=True,
    )
    metrics = json.loads(out.stdout.strip().splitlines()[-1])
    assert metrics["peak_cross_current_a"] <= 1.0
    assert metrics["events"]["BatteryJoined"] >= 1
