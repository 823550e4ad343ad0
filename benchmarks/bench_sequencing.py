"""Parallel-discharge sequencing vs direct parallel, closed loop on the uav_5ah plant.

Scenarios (``examples/sequencing_*.toml``): two 6S 5 Ah 20 mOhm batteries 2 V apart on a hover;
four batteries with a spread in SOC and resistance on a 20-minute mission; a fresh battery
hot-inserted at t = 300 s. Strategies: ``direct`` (no controller, every FET on: the baseline)
and ``sequencing`` (the scenario's ``[sequencing]`` section).

Per run: peak current into any battery while the load is supplied (the simulator's
``peak_cross_current_a``), the same at any time (includes connection at rest), charge pushed
into batteries while the load is supplied, time the load was unsupplied and the first
brown-out, energy delivered, body-diode conduction energy, joins, reverse-current, guard and
risk events.

Energy is reported under three termination rules, each applied to both strategies alike:

* ``energy_wh`` - the scenario's own rule (stop after ``stop_when_unsupplied_s`` of
  *continuous* brown-out). Not apples to apples: direct parallel pulses the load on and off
  after its first brown-out (the load's lock-out retries every step and the two batteries
  together hold it for a step or two), which resets that counter, so it runs on for minutes
  while the sequencing run stops 5 s after its first brown-out.
* ``energy_to_brownout_wh`` - up to the first step the load was not supplied (a UAV's flight
  ends there).
* ``energy_budget_wh`` - up to the step at which the load has been unsupplied for
  ``stop_when_unsupplied_s`` in *total*: the scenario's budget of brown-out time, counted the
  same way for a pulsing and a latched-off load.

Run: ``python benchmarks/bench_sequencing.py``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import Result
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCENARIOS = {
    "dual_hover_2V": "sequencing_dual_hover.toml",
    "four_spread": "sequencing_four_spread.toml",
    "hot_insert": "sequencing_hot_insert.toml",
}
STRATEGIES = ("direct", "sequencing")


def scenario(name: str, strategy: str, **sim: Any) -> ScenarioConfig:
    """The scenario file with the strategy's controller list (and optional [sim] overrides)."""
    cfg = load_config(EXAMPLES / SCENARIOS[name])
    controller: list[str] = [] if strategy == "direct" else ["sequencing"]
    return cfg.model_copy(
        update={
            "controller": controller,
            "sim": cfg.sim.model_copy(update={"progress": False, **sim}),
        }
    )


def summarize(cfg: ScenarioConfig, res: Result) -> dict[str, Any]:
    """The benchmark's figures for one finished run."""
    tr = res.trace
    dt = cfg.sim.dt_s
    cur = tr.channel("current_a")
    into = np.maximum(-cur, 0.0)
    supplying = tr.load_a > 1e-3
    unsupplied = (tr.load_demand_a > 1e-9) & (tr.load_a < tr.load_demand_a - 1e-6)
    k_bo = int(np.argmax(unsupplied)) if unsupplied.any() else len(unsupplied)
    budget_s = cfg.sim.stop_when_unsupplied_s
    k_budget = len(unsupplied)
    if budget_s is not None:
        over = np.nonzero(np.cumsum(unsupplied) * dt >= budget_s - 1e-9)[0]
        if over.size:
            k_budget = int(over[0]) + 1
    power_w = tr.bus_v * tr.load_a
    m = res.metrics
    return {
        "peak_cross_a": float(m["peak_cross_current_a"]),
        "peak_into_any_time_a": float(into.max()),
        "cross_charge_mah": float(into[supplying].sum() * dt / 3.6),
        "unsupplied_s": float(m["load_unsupplied_s"]),
        "first_brownout_s": float(tr.t_s[k_bo]) if k_bo < len(unsupplied) else None,
        "energy_wh": float(m["energy_out_wh"]),
        "energy_to_brownout_wh": float(np.sum(power_w[:k_bo]) * dt / 3600.0),
        "energy_budget_wh": float(np.sum(power_w[:k_budget]) * dt / 3600.0),
        "budget_end_s": float(tr.t_s[k_budget - 1]) + dt,
        "diode_j": float(sum(m["chg_diode_energy_j"]) + sum(m["dsg_diode_energy_j"])),
        "joule_j": float(m["joule_heat_j"]),
        "joins": int(m["events"].get("BatteryJoined", 0)),
        "reverse_events": int(m["events"].get("ReverseCurrent", 0)),
        "guard_events": int(m["events"].get("CrossCurrentGuard", 0)),
        "risk_events": int(m["events"].get("CrossCurrentRisk", 0)),
        "iso_events": int(m["events"].get("SourceIsolated", 0)),
        "sim_s": float(m["sim_time_s"]),
    }


def run_case(name: str, strategy: str, **sim: Any) -> dict[str, Any]:
    cfg = scenario(name, strategy, **sim)
    t0 = time.perf_counter()
    res = Runner(cfg).run()
    row = {"scenario": name, "strategy": strategy, **summarize(cfg, res)}
    row["wall_s"] = time.perf_counter() - t0
    return row


def run() -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in SCENARIOS:
        base = run_case(name, "direct")
        rows.append(base)
        for strategy in STRATEGIES[1:]:
            rows.append(run_case(name, strategy))
        for row in rows[-len(STRATEGIES) :]:
            row["energy_ratio"] = row["energy_wh"] / base["energy_wh"]
            row["energy_to_brownout_ratio"] = (
                row["energy_to_brownout_wh"] / base["energy_to_brownout_wh"]
            )
            row["energy_budget_ratio"] = row["energy_budget_wh"] / base["energy_budget_wh"]
    return rows


COLUMNS = (
    ("scenario", "{}"),
    ("strategy", "{}"),
    ("peak_cross_a", "{:.2f}"),
    ("peak_into_any_time_a", "{:.2f}"),
    ("cross_charge_mah", "{:.1f}"),
    ("unsupplied_s", "{:.1f}"),
    ("first_brownout_s", "{:.1f}"),
    ("energy_wh", "{:.2f}"),
    ("energy_ratio", "{:.4f}"),
    ("energy_to_brownout_wh", "{:.2f}"),
    ("energy_to_brownout_ratio", "{:.4f}"),
    ("energy_budget_wh", "{:.2f}"),
    ("energy_budget_ratio", "{:.4f}"),
    ("budget_end_s", "{:.1f}"),
    ("sim_s", "{:.1f}"),
    ("diode_j", "{:.2f}"),
    ("joins", "{}"),
    ("reverse_events", "{}"),
    ("guard_events", "{}"),
    ("risk_events", "{}"),
    ("iso_events", "{}"),
    ("wall_s", "{:.1f}"),
)


def main() -> None:
    rows = run()
    header = [c for c, _ in COLUMNS]
    cells = [[fmt.format(r[c]) if r[c] is not None else "-" for c, fmt in COLUMNS] for r in rows]
    widths = [max(len(h), *(len(row[i]) for row in cells)) for i, h in enumerate(header)]
    print("  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
    for row in cells:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))


if __name__ == "__main__":
    main()
