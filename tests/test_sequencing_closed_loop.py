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


@pytest.mark.parametrize("name", ["dual_hover", "hot_insert", "four_spread", "hover_30a"])
def test_energy_to_the_first_brownout_at_least_99_percent_of_direct(name: str) -> None:
    # The goal (issue #15's decision, recorded in issue #24): co-discharge energy is judged
    # against direct parallel up to the first load brown-out. After the load's lock-out the
    # flight is over; direct parallel keeps pulsing the locked-out load (each retry resets the
    # runner's brown-out counter) and that is not energy delivered. hover_30a, the case the
    # equal-budget comparison had as an xfail (98.80 %), is judged the same way, without the
    # reverse-current comparator (optional, off by default).
    base, seq = _run(name, "direct"), _run(name, "sequencing")
    assert not _cfg(name, "sequencing").pack.switch.reverse_comparator
    assert _first_brownout(seq) >= _first_brownout(base)
    assert _energy_to_brownout_wh(seq) >= 0.99 * _energy_to_brownout_wh(base)


@pytest.mark.parametrize("name", ["dual_hover", "hot_insert"])
def test_no_current_into_any_battery_while_the_pack_discharges(name: str) -> None:
    base, seq = _run(name, "direct"), _run(name, "sequencing")
    assert base.metrics["peak_cross_current_a"] > 30.0
    assert seq.metrics["peak_cross_current_a"] <= 1.0


def test_dual_hover_low_battery_waits_then_both_discharge_to_the_end() -> None:
    seq = _run("dual_hover", "sequencing")
    joins = [e for e in seq.events if e.kind == "BatteryJoined"]
    # B joins once, by R2, when its rest voltage has met A's fast voltage V + I*R.
    assert [(e.battery, e.data["reason"]) for e in joins] == [(1, "R2")]
    k = int(np.searchsorted(seq.trace.t_s, joins[0].t_s))
    assert not seq.trace.channel("chg_on")[:k, 1].any()
    assert np.all(seq.trace.channel("current_a")[:k, 1] == 0.0)
    # From the join to the first brown-out both FET pairs are on and both discharge: no
    # guard, no chatter (issue #15).
    k_bo = int(np.searchsorted(seq.trace.t_s, _first_brownout(seq)))
    assert seq.trace.channel("chg_on")[k:k_bo].all() and seq.trace.channel("dsg_on")[k:k_bo].all()
    assert np.all(seq.trace.channel("current_a")[k + 1 : k_bo] > 0.0)
    assert "CrossCurrentGuard" not in seq.metrics["events"]


def test_hot_inserted_fresh_battery_takes_over() -> None:
    seq = _run("hot_insert", "sequencing")
    at_300 = [e for e in seq.events if e.t_s == 300.0 and e.kind == "StateChanged"]
    assert {(e.battery, e.data["to"]) for e in at_300} >= {(0, "STANDBY"), (1, "DISCHARGING")}
    rejoin = [e for e in seq.events if e.kind == "BatteryJoined"]
    assert rejoin[0].battery == 0 and rejoin[0].t_s > 300.0


def test_four_spread_stays_within_the_charge_limit_and_cuts_in_one_period() -> None:
    base, seq = _run("four_spread", "direct"), _run("four_spread", "sequencing")
    assert seq.metrics["load_unsupplied_s"] == 0.0
    into = _into(seq)
    assert float(into.max()) <= 2.5  # 0.5C of 5 Ah
    # More than 1 A into a battery for at most one control period at a time.
    assert not np.any((into[1:] > 1.0) & (into[:-1] > 1.0))
    assert "CrossCurrentGuard" not in seq.metrics["events"]

    def cross(r: Result) -> float:
        return float(_into(r)[r.trace.load_a > 1e-3].sum())

    assert cross(seq) < 0.005 * cross(base)


@pytest.mark.parametrize("comparator", [False, True])
def test_hover_30a_reverse_current_with_and_without_the_comparator(comparator: bool) -> None:
    cfg = _cfg("hover_30a", "sequencing", dt_s=0.1)
    switch = cfg.pack.switch.model_copy(update={"reverse_comparator": comparator})
    pack = cfg.pack.model_copy(update={"switch": switch})
    res = Runner(cfg.model_copy(update={"pack": pack})).run()
    into = _into(res)
    if comparator:
        # The comparator opens the charge FET within the plant step: nothing above its trip.
        assert float(into.max()) <= 1.0
    else:
        # The load's lock-out at the first brown-out lets A take ~1.7 A from B for one period;
        # the reverse cut opens A's charge FET at the next sample.
        assert 1.0 < float(into.max()) <= 2.5
        assert not np.any((into[1:] > 1.0) & (into[:-1] > 1.0))
        assert res.metrics["events"].get("ReverseCurrent", 0) >= 1
    joins = [e for e in res.events if e.kind == "BatteryJoined"]
    assert [(e.battery, e.data["reason"]) for e in joins] == [(1, "R2")]


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
