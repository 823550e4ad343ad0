"""Parallel-discharge sequencing vs direct parallel, closed loop on the uav_5ah plant (issue #15).

Scenarios (``examples/sequencing_*.toml``): two 6S 5 Ah 20 mOhm batteries 2 V apart on a 20 A
hover (``dual_hover_2V``) and on a 30 A hover (``hover_30A``); four batteries with a spread in
SOC and resistance on a 20-minute mission (``four_spread``); a fresh battery hot-inserted at
t = 300 s (``hot_insert``). Strategies: ``direct`` (no controller, every FET on: the
baseline), ``sequencing`` (the scenario's ``[sequencing]`` section, no comparator) and
``sequencing+comp`` (the same with the plant's reverse-current comparator fitted,
``[pack.switch] reverse_comparator = true``, trip 1 A).

Figures per run (issue #15 section 1; goals in :data:`GOALS`):

* ``meet_s`` - first time the batteries' open-circuit voltages (the plant's OCV at their SOC
  and temperature) are all within ``v_co`` of each other: "the voltages meet". With unequal
  resistances (four_spread) co-discharging batteries settle at an OCV spread of about
  I_load / N x (R_max - R_min), which is added to ``v_co`` there.
* ``co_share`` - share of the loaded time (load > 1 A) after ``meet_s`` in which every
  present battery discharges with both FETs on (goal >= 0.90).
* ``sw_per_min`` - FET gate changes (charge and discharge, all batteries) per minute of
  loaded time from 10 s after the load starts to the first brown-out: the whole hover, gusts
  included (four_spread: the whole mission, bursts and landing) (goal <= 1).
* ``peak_share`` - largest per-battery discharge current over the load current after
  ``meet_s`` (goal <= 0.6 for two batteries); ``peak_share_join`` the same from the first
  period in which every battery discharged (``join_s``); ``peak_share_all`` over the whole
  run (1.0 while R1 has one battery carry the load alone, by design). All three only where the
  load draws more than ``SHARE_MIN_LOAD_A`` (5 A).
* ``rev_peak_a`` / ``rev_1a_s`` - largest current into any battery while no charger is on, and
  the longest uninterrupted time with more than 1 A into one battery (goal: at most one
  control period plus the FET delay, 0.1 s here; the plant applies commands at the next step).
* ``cross_mah_h`` - charge pushed into batteries (no charger) per hour of run (goal <= 1 mAh).
* ``heat_j`` / ``heat_ratio``, ``energy_wh`` / ``energy_ratio`` - ohmic (R0) heat of the cells
  and energy delivered, against direct parallel in the same scenario (goal: energy >= 99 %,
  less heat). Energy under the equal cumulative brown-out budget (``energy_budget_ratio``) is
  the like-for-like figure (see docs/parallel_discharge.md).

Run: ``python benchmarks/bench_sequencing.py``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import Result
from packpilot.model.cell.model import ocv_v
from packpilot.model.cell.params import load_parameter_set
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCENARIOS = {
    "dual_hover_2V": "sequencing_dual_hover.toml",
    "hover_30A": "sequencing_hover_30a.toml",
    "four_spread": "sequencing_four_spread.toml",
    "hot_insert": "sequencing_hot_insert.toml",
}
STRATEGIES = ("direct", "sequencing", "sequencing+comp")
SHARE_MIN_LOAD_A = 5.0
"""Load sharing is judged where the load draws at least 1C of a 5 Ah battery: at a landing's
1.5 A a circulating current of a few hundred mA would make any ratio meaningless."""
GOALS = {
    "co_share": ">= 0.90",
    "sw_per_min": "<= 1",
    "peak_share": "<= 0.6",
    "rev_1a_s": "<= 0.1 s",
    "cross_mah_h": "<= 1",
    "energy_budget_ratio": ">= 0.99",
    "heat_ratio": "< 1",
}


def scenario(name: str, strategy: str, **sim: Any) -> ScenarioConfig:
    """The scenario file with the strategy's controller list and switch (and [sim] overrides)."""
    cfg = load_config(EXAMPLES / SCENARIOS[name])
    controller: list[str] = [] if strategy == "direct" else ["sequencing"]
    switch = cfg.pack.switch.model_copy(
        update={"reverse_comparator": strategy == "sequencing+comp"}
    )
    return cfg.model_copy(
        update={
            "controller": controller,
            "pack": cfg.pack.model_copy(update={"switch": switch}),
            "sim": cfg.sim.model_copy(update={"progress": False, **sim}),
        }
    )


def _ocv(cfg: ScenarioConfig, res: Result) -> np.ndarray:
    """(steps, batteries) open-circuit voltage of each battery from its SOC and temperature."""
    tr = res.trace
    soc = tr.channel("soc")
    temp = tr.channel("temp_c")
    out = np.empty_like(soc)
    for k, b in enumerate(cfg.pack.batteries[: soc.shape[1]]):
        params = load_parameter_set(b.cell or cfg.pack.cell)
        out[:, k] = ocv_v(params, soc[:, k], temp[:, k]) * b.series_groups * b.cells_per_group
    return out


def _longest(mask: np.ndarray, dt: float) -> float:
    """Longest run of True (s), per column, the largest over columns."""
    best = 0
    for col in mask.T:
        run = 0
        for x in col:
            run = run + 1 if x else 0
            best = max(best, run)
    return best * dt


def _meet(cfg: ScenarioConfig, res: Result, present: np.ndarray) -> int | None:
    """First step at which the present batteries' OCVs are within v_co (plus the spread their
    resistance differences sustain at the present load), or None."""
    tr = res.trace
    ocv = _ocv(cfg, res)
    r = [b.resistance_ohm for b in cfg.pack.batteries[: ocv.shape[1]]]
    dr = max(r) - min(r) if all(x is not None for x in r) else 0.0  # type: ignore[operator]
    n_pres = present.sum(axis=1)
    hi = np.where(present, ocv, -np.inf).max(axis=1)
    lo = np.where(present, ocv, np.inf).min(axis=1)
    allow = cfg.sequencing.v_co + np.maximum(tr.load_a, 0.0) / np.maximum(n_pres, 1) * dr
    met = (hi - lo < allow) & (n_pres >= 2)
    return int(np.argmax(met)) if met.any() else None


def _switching(
    tr: Any, chg: np.ndarray, dsg: np.ndarray, loaded: np.ndarray, k_bo: int, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """FET gate changes per step, and the steps of steady hover."""
    # Steady hover: the loaded time from 10 s after the load starts to the first brown-out
    # (the hover profiles' gusts included; four_spread's whole mission, bursts and landing).
    dem = tr.load_demand_a
    steady = (dem > 1.0) & loaded
    k0 = int(np.argmax(dem > 1.0)) + max(1, round(10.0 / dt)) if (dem > 1.0).any() else 0
    steady[:k0] = False
    steady[k_bo:] = False
    flips = np.zeros(len(dem))
    flips[1:] = (chg[1:] != chg[:-1]).sum(axis=1) + (dsg[1:] != dsg[:-1]).sum(axis=1)
    return flips, steady


def summarize(cfg: ScenarioConfig, res: Result) -> dict[str, Any]:
    """The benchmark's figures for one finished run."""
    tr = res.trace
    dt = cfg.sim.dt_s
    cur = tr.channel("current_a")
    volt = tr.channel("voltage_v")
    chg = tr.channel("chg_on") > 0.5
    dsg = tr.channel("dsg_on") > 0.5
    present = np.isfinite(volt) & (volt > 1.0)
    n_pres = present.sum(axis=1)
    no_charger = ~(tr.charger_a > 1e-6) if tr.charger_a is not None else np.ones(len(cur), bool)
    into = np.where(present, np.maximum(-cur, 0.0), 0.0)
    into[~no_charger] = 0.0
    loaded = tr.load_a > 1.0
    unsupplied = (tr.load_demand_a > 1e-9) & (tr.load_a < tr.load_demand_a - 1e-6)
    k_bo = int(np.argmax(unsupplied)) if unsupplied.any() else len(unsupplied)
    budget_s = cfg.sim.stop_when_unsupplied_s
    k_budget = len(unsupplied)
    over = np.nonzero(np.cumsum(unsupplied) * dt >= (budget_s or np.inf) - 1e-9)[0]
    k_budget = int(over[0]) + 1 if over.size else k_budget
    power_w = tr.bus_v * tr.load_a
    energy_budget_wh = float(np.sum(power_w[:k_budget]) * dt / 3600.0)
    k_meet = _meet(cfg, res, present)
    both = np.all(~present | (chg & dsg & (cur > 0.0)), axis=1) & (n_pres >= 2)
    after = np.zeros(len(cur), bool)
    if k_meet is not None:
        after[k_meet:k_bo] = True
    sel = after & loaded
    co_share = float(both[sel].mean()) if sel.any() else None
    flying = tr.load_a > SHARE_MIN_LOAD_A
    share = np.where(flying[:, None], cur / np.maximum(tr.load_a[:, None], 1e-9), 0.0)
    share_max = np.where(present, share, 0.0).max(axis=1)
    sel_f = sel & flying
    peak_share = float(share_max[sel_f].max()) if sel_f.any() else None
    k_join = int(np.argmax(both)) if both.any() else None
    since_join = np.zeros(len(cur), bool)
    if k_join is not None:
        since_join[k_join:k_bo] = True
    sel_j = since_join & flying
    peak_share_join = float(share_max[sel_j].max()) if sel_j.any() else None
    both_present = flying & (n_pres >= 2)
    peak_share_all = float(share_max[both_present].max()) if both_present.any() else None
    flips, steady = _switching(tr, chg, dsg, loaded, k_bo, dt)
    steady_min = steady.sum() * dt / 60.0
    run_h = len(cur) * dt / 3600.0
    m = res.metrics
    return {
        "meet_s": float(tr.t_s[k_meet]) if k_meet is not None else None,
        "co_share": co_share,
        "sw_per_min": float(flips[steady].sum() / steady_min) if steady_min > 0 else None,
        "steady_min": steady_min,
        "peak_share": peak_share,
        "peak_share_join": peak_share_join,
        "join_s": float(tr.t_s[k_join]) if k_join is not None else None,
        "peak_share_all": peak_share_all,
        "rev_peak_a": float(into.max()),
        "rev_1a_s": _longest(into > 1.0, dt),
        "rev_0.5a_s": _longest(into > 0.5, dt),
        "cross_mah_h": float(into.sum() * dt / 3.6 / run_h),
        "unsupplied_s": float(m["load_unsupplied_s"]),
        "first_brownout_s": float(tr.t_s[k_bo]) if k_bo < len(unsupplied) else None,
        "energy_wh": float(m["energy_out_wh"]),
        "energy_to_brownout_wh": float(np.sum(power_w[:k_bo]) * dt / 3600.0),
        "energy_budget_wh": energy_budget_wh,
        "heat_j": float(m["joule_heat_j"]),
        "diode_j": float(sum(m["chg_diode_energy_j"]) + sum(m["dsg_diode_energy_j"])),
        "joins": int(m["events"].get("BatteryJoined", 0)),
        "reverse_events": int(m["events"].get("ReverseCurrent", 0)),
        "risk_events": int(m["events"].get("CrossCurrentRisk", 0)),
        "sim_s": float(m["sim_time_s"]),
    }


def run_case(name: str, strategy: str, **sim: Any) -> dict[str, Any]:
    cfg = scenario(name, strategy, **sim)
    t0 = time.perf_counter()
    res = Runner(cfg).run()
    row = {"scenario": name, "strategy": strategy, **summarize(cfg, res)}
    row["wall_s"] = time.perf_counter() - t0
    return row


def run(scenarios: tuple[str, ...] = tuple(SCENARIOS)) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in scenarios:
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
            row["heat_ratio"] = row["heat_j"] / base["heat_j"]
    return rows


GOALS: dict[str, Callable[[float], bool]] = {
    "co_share": lambda x: x >= 0.90,
    "sw_per_min": lambda x: x <= 1.0,
    "peak_share": lambda x: x <= 0.6,
    "rev_1a_s": lambda x: x <= 0.1 + 1e-9,
    "cross_mah_h": lambda x: x <= 1.0,
    "energy_budget_ratio": lambda x: x >= 0.99,
    "heat_ratio": lambda x: x < 1.0,
}
"""Issue #15 §1's goals, per figure (run_all's headlines use the same table)."""


def verdicts(row: dict[str, Any]) -> dict[str, str]:
    """Goal -> 'met' / 'MISSED' / '-' for one sequencing row."""
    out: dict[str, str] = {}
    for key, ok in GOALS.items():
        x = row.get(key)
        out[key] = "-" if x is None else ("met" if ok(x) else "MISSED")
    return out


COLUMNS = (
    ("scenario", "{}"),
    ("strategy", "{}"),
    ("meet_s", "{:.1f}"),
    ("co_share", "{:.3f}"),
    ("sw_per_min", "{:.2f}"),
    ("steady_min", "{:.1f}"),
    ("peak_share", "{:.3f}"),
    ("join_s", "{:.1f}"),
    ("peak_share_join", "{:.3f}"),
    ("peak_share_all", "{:.3f}"),
    ("rev_peak_a", "{:.2f}"),
    ("rev_1a_s", "{:.2f}"),
    ("rev_0.5a_s", "{:.2f}"),
    ("cross_mah_h", "{:.2f}"),
    ("energy_wh", "{:.2f}"),
    ("energy_ratio", "{:.4f}"),
    ("energy_budget_ratio", "{:.4f}"),
    ("energy_to_brownout_ratio", "{:.4f}"),
    ("heat_j", "{:.0f}"),
    ("heat_ratio", "{:.3f}"),
    ("unsupplied_s", "{:.1f}"),
    ("first_brownout_s", "{:.1f}"),
    ("diode_j", "{:.2f}"),
    ("joins", "{}"),
    ("reverse_events", "{}"),
    ("risk_events", "{}"),
    ("wall_s", "{:.1f}"),
)


def main() -> None:
    rows = run()
    header = [c for c, _ in COLUMNS]
    cells = [
        [fmt.format(r[c]) if r.get(c) is not None else "-" for c, fmt in COLUMNS] for r in rows
    ]
    widths = [max(len(h), *(len(row[i]) for row in cells)) for i, h in enumerate(header)]
    print("  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
    for row in cells:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
    print()
    for r in rows:
        if r["strategy"] != "direct":
            v = verdicts(r)
            print(r["scenario"], r["strategy"], {k: f"{v[k]} ({GOALS[k]})" for k in v})


if __name__ == "__main__":
    main()
