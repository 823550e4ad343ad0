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

Per strategy: peak current into each battery (charging, A), total I²R heat of the traction
batteries (kJ, the plant's ohmic heat), maximum cell-temperature rise over ambient (K), and the
time to full (s): the moment every traction battery has been at V_sat − 0.5 V with its charge
current down to the termination current (2 A), the same criterion the method stops on.

Run: ``python benchmarks/bench_charging.py`` (``--direct`` skips CAN and writes setpoints
straight into the plant charger; the numbers agree to the heartbeat's one-period latency).
``--frontier`` instead sweeps the heat/time trade-off of the two current laws (I_full for
``sqrt``, the per-battery limit for ``constant``), direct, one row per setting.
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, load_config
from packpilot.io.can import CanChargerLink
from packpilot.sim.result import Result
from packpilot.sim.runner import Runner

SCENARIO = Path(__file__).resolve().parents[1] / "examples" / "evtol_charging.toml"
DT_S = 2.0
DURATION_S = 21_600.0
FULL_BAND_V = 0.5
"""'At V_sat' band and termination current: the charging controller's reach_tol_v and the
scenario's termination_current_a."""

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
}
CHARGING_KEYS = (
    "target_mode",
    "battery_current_limit_a",
    "current_law",
    "full_current_a",
    "vc3_margin_v",
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
}
"""``--frontier``: the heat/time trade-off of each current law around the 1.2 x time budget
(``vc3_margin_v = 3`` makes the S40 steps end in CC instead of a CV taper)."""


def scenario(strategy: str, dt_s: float = DT_S, duration_s: float = DURATION_S) -> ScenarioConfig:
    cfg = load_config(SCENARIO)
    spec = STRATEGIES[strategy] if strategy in STRATEGIES else FRONTIER[strategy]
    charging = dict(cfg.charging or {})
    for key in CHARGING_KEYS:
        if key in spec:
            charging[key] = spec[key]
    sim = cfg.sim.model_copy(update={"dt_s": dt_s, "duration_s": duration_s, "progress": False})
    return cfg.model_copy(
        update={"controller": spec["controller"], "charging": charging, "sim": sim}
    )


def time_to_full(res: Result, v_sat_v: float, term_a: float, traction: list[int]) -> float:
    """First time by which every traction battery has met the full criterion (NaN if never)."""
    v = res.trace.channel("voltage_v")[:, traction]
    i_chg = -res.trace.channel("current_a")[:, traction]
    full = (v >= v_sat_v - FULL_BAND_V) & (i_chg <= term_a)
    t_full = []
    for b in range(full.shape[1]):
        hits = np.flatnonzero(full[:, b])
        if hits.size == 0:
            return float("nan")
        t_full.append(float(res.trace.t_s[hits[0]] + res.trace.t_s[1] - res.trace.t_s[0]))
    return max(t_full)


def run_case(strategy: str, *, can: bool = True, dt_s: float = DT_S) -> dict[str, Any]:
    cfg = scenario(strategy, dt_s=dt_s)
    runner = Runner(cfg, progress=False)
    link = None
    if can and cfg.controller:
        link = CanChargerLink(runner.pack.charger.view(0))
        runner.charger_link = link
    try:
        res = runner.run()
    finally:
        if link is not None:
            link.close()
    chg = cfg.charging or {}
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
    return row


def _case(args: tuple[str, bool]) -> dict[str, Any]:
    return run_case(args[0], can=args[1])


def run(
    *, can: bool = True, workers: int | None = None, frontier: bool = False
) -> list[dict[str, Any]]:
    """One row per strategy (the baseline first); the runs are independent, so they go to a
    process pool. ``frontier``: the ``FRONTIER`` settings instead of ``STRATEGIES``."""
    names = ["baseline", *FRONTIER] if frontier else list(STRATEGIES)
    n = workers if workers is not None else min(len(names), os.cpu_count() or 1)
    jobs = [(s, can) for s in names]
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


def main(argv: list[str]) -> None:
    frontier = "--frontier" in argv
    rows = run(can="--direct" not in argv and not frontier, frontier=frontier)
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


if __name__ == "__main__":
    main(sys.argv[1:])
