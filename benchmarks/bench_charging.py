"""Staged charging vs the naive dock on the eVTOL charging bus (``examples/evtol_charging.toml``).

Six ~100 V (28S, 100 Ah) batteries at 2x96, 2x101, 2x106 V on one charging busbar behind
relays, V_sat = 117 V, a 100 A charger, and a 12 V auxiliary battery.

Strategies:

* ``baseline`` — no BMS staging: every relay closed, the dock at V_sat with the same 100 A
  current limit (the scenario's ``[charger]`` setpoint, ``controller = []``).
* ``staged_levels`` — the method, Vt from the next level / V2 + step_v (spec example 3),
  charger setpoints over a python-can virtual bus (client → emulator → plant charger).
* ``staged_saturation`` — the method with Vt = V_sat when no third level exists (example 4),
  also over CAN.
* ``staged_levels_0.2C`` — ``staged_levels`` plus ``battery_current_limit_a = 20`` (0.2C per
  connected battery): trades charge time for I²R heat (see docs/staged_charging.md).
* ``staged_levels_sqrt`` — ``staged_levels`` plus ``current_law = "sqrt"``: the charger current
  with n of the N batteries still to charge connected is min(100 A, I_full·sqrt(n/N)), I_full =
  the charger limit (the same total I²R heat rate in every stage, the least heat for a given
  charge time; docs/staged_charging.md).
* ``staged_levels_sqrt_budget`` — the sqrt law scaled to the 1.2 x time budget (I_full 94.5 A),
  S40 steps ending in CC (``vc3_margin_v = 3``) and a 0.7 V join gap (``d1_v``): the least-heat
  point of the ``--frontier`` sweep that still meets the time target.

Per strategy: peak current into each battery (charging, A), total I²R heat of the traction
batteries (kJ, the plant's ohmic heat), maximum cell-temperature rise over ambient (K), and the
time to full (s): the moment every traction battery has been at V_sat − 0.5 V with its charge
current down to the termination current (2 A), the same criterion the method stops on.

Run: ``python benchmarks/bench_charging.py`` (``--direct`` skips CAN and writes setpoints
straight into the plant charger; the numbers agree to the heartbeat's one-period latency).
``--frontier`` instead sweeps the heat/time trade-off of the two current laws (I_full for
``sqrt``, the per-battery limit for ``constant``, the join gap ``d1_v``), direct, one row per
setting. ``--breakdown`` adds, per staged strategy, where the heat and the time go (one line per
stage: duration, batteries connected, charge, mean charger current, I²R heat, effective
resistance) and the least heat any constant-current-per-stage schedule of the same stages can
reach in 1.2 x the baseline time (``cc_heat_bound_j``).
"""

from __future__ import annotations

import math
import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, load_config
from packpilot.config.charging import ChargingConfig
from packpilot.io.can import CanChargerLink
from packpilot.sim.quality import stage_breakdown, time_to_full
from packpilot.sim.runner import Runner

SCENARIO = Path(__file__).resolve().parents[1] / "examples" / "evtol_charging.toml"
DT_S = 2.0
DURATION_S = 21_600.0

STRATEGIES: dict[str, dict[str, Any]] = {
    "baseline": {"controller": []},
    "staged_levels": {"controller": ["charging"], "target_mode": "levels"},
    "staged_saturation": {"controller": ["charging"], "target_mode": "saturation"},
    "staged_levels_0.2C": {
        "controller": ["charging"],
        "target_mode": "levels",
        "battery_current_limit_a": 20.0,
    },
    "staged_levels_sqrt": {
        "controller": ["charging"],
        "target_mode": "levels",
        "current_law": "sqrt",
    },
    "staged_levels_sqrt_budget": {
        "controller": ["charging"],
        "target_mode": "levels",
        "current_law": "sqrt",
        "full_current_a": 94.5,
        "vc3_margin_v": 3.0,
        "d1_v": 0.7,
    },
}
CHARGING_KEYS = (
    "target_mode",
    "battery_current_limit_a",
    "current_law",
    "full_current_a",
    "vc3_margin_v",
    "d1_v",
)
"""Strategy keys that are ``[charging]`` settings (the rest, ``controller``, is top level)."""

FRONTIER: dict[str, dict[str, Any]] = {
    **{
        f"sqrt_I_full_{a:g}A": {
            "controller": ["charging"],
            "current_law": "sqrt",
            "full_current_a": a,
        }
        for a in (100.0, 97.5, 95.0, 92.5, 90.0)
    },
    **{
        f"constant_{a:g}A_per_battery": {
            "controller": ["charging"],
            "battery_current_limit_a": a,
        }
        for a in (25.0, 22.0, 20.0, 18.0)
    },
    **{
        f"sqrt_I_full_{a:g}A_vc3_3V": {
            "controller": ["charging"],
            "current_law": "sqrt",
            "full_current_a": a,
            "vc3_margin_v": 3.0,
        }
        for a in (95.0, 92.5)
    },
    **{
        f"sqrt_I_full_{a:g}A_vc3_3V_d1_{d:g}V": {
            "controller": ["charging"],
            "current_law": "sqrt",
            "full_current_a": a,
            "vc3_margin_v": 3.0,
            "d1_v": d,
        }
        for a in (96.0, 94.5, 93.0)
        for d in (0.4, 0.7, 1.5)
    },
}
"""``--frontier``: the heat/time trade-off of each current law around the 1.2 x time budget
(``vc3_margin_v = 3`` makes the S40 steps end in CC instead of a CV taper; ``d1_v`` moves the
S30 joins: a larger gap moves charge into the stages with more batteries but costs a larger
equalising transient, ``d1_v`` <= ``eps_eq_v`` removes the join step altogether)."""
TIME_BUDGET = 1.2
"""The acceptance's charge-time budget, x the baseline's time to full."""


def scenario(strategy: str, dt_s: float = DT_S, duration_s: float = DURATION_S) -> ScenarioConfig:
    cfg = load_config(SCENARIO)
    spec = STRATEGIES[strategy] if strategy in STRATEGIES else FRONTIER[strategy]
    charging = cfg.charging.model_dump(exclude_unset=True) if cfg.charging else {}
    for key in CHARGING_KEYS:
        if key in spec:
            charging[key] = spec[key]
    sim = cfg.sim.model_copy(update={"dt_s": dt_s, "duration_s": duration_s, "progress": False})
    return cfg.model_copy(
        update={
            "controller": spec["controller"],
            "charging": ChargingConfig.model_validate(charging),
            "sim": sim,
        }
    )


def cc_heat_bound_j(stages: list[tuple[float, float, int]], time_s: float) -> float:
    """Least I²R heat of delivering charge ``q`` (C) through ``n`` parallel batteries of
    effective resistance ``r`` (Ω) per stage ``(q, r, n)``, at a constant charger current per
    stage, all stages together in ``time_s``.

    Stage k at current I_k heats q_k·I_k·r_k/n_k and lasts q_k/I_k; minimising the sum for a
    fixed total time (Lagrange, or Cauchy-Schwarz) gives I_k ∝ sqrt(n_k/r_k) and the bound
    (Σ q_k·sqrt(r_k/n_k))² / time_s, reached exactly when every stage heats at the same rate.
    """
    if time_s <= 0.0:
        return float("inf")
    total = sum(q * math.sqrt(r / n) for q, r, n in stages if q > 0.0 and n > 0)
    return total * total / time_s


def run_case(
    strategy: str, *, can: bool = True, dt_s: float = DT_S, breakdown: bool = False
) -> dict[str, Any]:
    cfg = scenario(strategy, dt_s=dt_s)
    runner = Runner(cfg, progress=False)
    heat_snapshots: list[np.ndarray] = []
    pack_step = runner.pack.step

    def step_and_record(*args: Any, **kwargs: Any) -> Any:
        interval = pack_step(*args, **kwargs)
        heat_snapshots.append(runner.pack.joule_j[0].copy())
        return interval

    runner.pack.step = step_and_record  # type: ignore[method-assign]
    link = None
    if can and cfg.controller:
        link = CanChargerLink(runner.pack.charger.view(0))
        runner.charger_link = link
    try:
        res = runner.run()
    finally:
        if link is not None:
            link.close()
    chg = cfg.charging.model_dump(exclude_unset=True) if cfg.charging else {}
    v_sat = float(chg.get("v_sat_v", 117.0))
    term = float(chg.get("termination_current_a", 2.0))
    traction = list(runner.traction)
    cur = res.trace.channel("current_a")[:, traction]
    temp = res.trace.channel("temp_c")[:, traction]
    heat = runner.pack.joule_j[0][traction]
    names = [res.battery_names[i] for i in traction]
    peak_in = np.maximum(-cur, 0.0).max(axis=0)
    row: dict[str, Any] = {
        "strategy": strategy,
        "link": "can" if link is not None else "direct",
        "peak_charge_a": {n: round(float(x), 1) for n, x in zip(names, peak_in, strict=True)},
        "peak_charge_max_a": round(float(peak_in.max()), 1),
        "peak_discharge_a": round(float(np.maximum(cur, 0.0).max()), 1),
        "i2r_heat_kj": round(float(heat.sum()) / 1e3, 1),
        "max_temp_rise_k": round(float(np.nanmax(temp)) - cfg.pack.ambient_c, 2),
        "time_to_full_s": round(time_to_full(res, v_sat, term, traction), 0),
        "final_soc_min": round(float(res.trace.channel("soc")[-1, traction].min()), 4),
        "events": res.metrics["events"],
        "wall_s": round(res.metrics["wall_time_s"], 1),
    }
    if link is not None:
        c = link.client.counters
        row["can_frames"] = {"sent": c.sent, "received": c.received, "bad": c.malformed}
    if breakdown:
        cum = np.array(heat_snapshots)[:, traction].sum(axis=1)
        row["stages"] = stage_breakdown(res, traction, np.diff(cum, prepend=0.0))
    return row


def _case(args: tuple[str, bool, bool]) -> dict[str, Any]:
    return run_case(args[0], can=args[1], breakdown=args[2])


def run(
    *,
    can: bool = True,
    workers: int | None = None,
    frontier: bool = False,
    breakdown: bool = False,
) -> list[dict[str, Any]]:
    """One row per strategy (the baseline first); the runs are independent, so they go to a
    process pool. ``frontier``: the ``FRONTIER`` settings instead of ``STRATEGIES``;
    ``breakdown``: each row also gets ``stages`` (``stage_breakdown``)."""
    names = ["baseline", *FRONTIER] if frontier else list(STRATEGIES)
    n = workers if workers is not None else min(len(names), os.cpu_count() or 1)
    jobs = [(s, can, breakdown) for s in names]
    if n <= 1:
        rows = [_case(j) for j in jobs]
    else:
        with ProcessPoolExecutor(max_workers=n) as pool:
            rows = list(pool.map(_case, jobs))
    base = rows[0]
    for row in rows:
        row["peak_vs_baseline"] = round(row["peak_charge_max_a"] / base["peak_charge_max_a"], 3)
        row["heat_vs_baseline"] = round(row["i2r_heat_kj"] / base["i2r_heat_kj"], 3)
        row["time_vs_baseline"] = round(row["time_to_full_s"] / base["time_to_full_s"], 3)
    return rows


def print_breakdown(rows: list[dict[str, Any]]) -> None:
    """Per strategy: the stages, then the constant-current bound at the time budget (the
    top-off CV tail, whose current the charger does not set, is kept as measured)."""
    budget_s = TIME_BUDGET * rows[0]["time_to_full_s"]
    for r in rows:
        print(f"\n{r['strategy']}:")
        print("  stage | t0_s | duration_s | n | charge_ah | mean_a | heat_kj | r_eff_mohm")
        for g in r["stages"]:
            print(
                f"  {g['stage']} | {g['t0_s']:.0f} | {g['duration_s']:.0f} | {g['n']} | "
                f"{g['charge_ah']:.1f} | {g['mean_a']:.1f} | {g['heat_kj']:.1f} | "
                f"{g['r_eff_mohm']:.2f}"
            )
        if r["strategy"] == "baseline":
            continue
        cc = [g for g in r["stages"] if g["stage"] in ("S20", "S30", "S40")]
        tail = [g for g in r["stages"] if g["stage"] == "top_off"]
        tail_s = sum(g["duration_s"] for g in tail)
        tail_kj = sum(g["heat_kj"] for g in tail)
        bound_kj = tail_kj + 1e-3 * cc_heat_bound_j(
            [(g["charge_ah"] * 3600.0, g["r_eff_mohm"] * 1e-3, g["n"]) for g in cc],
            budget_s - tail_s,
        )
        print(
            f"  least heat of these stages at constant current per stage in "
            f"{TIME_BUDGET:g} x the baseline time ({budget_s:.0f} s, top-off tail "
            f"{tail_s:.0f} s / {tail_kj:.1f} kJ as measured): {bound_kj:.1f} kJ = "
            f"{bound_kj / rows[0]['i2r_heat_kj']:.3f} x baseline"
        )


def main(argv: list[str]) -> None:
    frontier = "--frontier" in argv
    breakdown = "--breakdown" in argv
    rows = run(can="--direct" not in argv and not frontier, frontier=frontier, breakdown=breakdown)
    cols = (
        "strategy",
        "link",
        "peak_charge_max_a",
        "peak_vs_baseline",
        "i2r_heat_kj",
        "heat_vs_baseline",
        "max_temp_rise_k",
        "time_to_full_s",
        "time_vs_baseline",
        "final_soc_min",
        "wall_s",
    )
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r[c]) for c in cols))
    print()
    for r in rows:
        print(f"{r['strategy']}: peak charge current per battery {r['peak_charge_a']}")
    print("targets: peak and heat <= 0.5 x baseline, time <= 1.2 x baseline")
    if breakdown:
        print_breakdown(rows)


if __name__ == "__main__":
    main(sys.argv[1:])
