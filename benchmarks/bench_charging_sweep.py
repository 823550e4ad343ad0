"""Staged charging never lets a battery discharge into its siblings while the dock charges
(issue #24 item 3): a sweep of packs and docks, each charged to full in the closed loop.

Packs of 3-6 batteries (28S ecm_example cells, the eVTOL scenario's) whose rest voltages
spread over 1-10 V, on docks of 20-200 A. Per case: the longest time any traction battery
discharged more than 2 A while the dock delivered (s, the acceptance allows 10 s), the
largest such current (A), the peak battery-to-battery current the metrics report
(``peak_cross_current_a``), whether every battery ended full (``BatteryFull`` for each and
``ChargeComplete``), and the time to complete.

The spread is laid out unevenly (a low pair and irregular gaps above it), since equal gaps
hide the case of issue #24 (seed 001: 95/97/100/104 V on a 100 A dock).

    python benchmarks/bench_charging_sweep.py            # full sweep: 4 x 4 x 4 = 64 cases
    python benchmarks/bench_charging_sweep.py --small    # the CI subset the tests run
    (``--serial``: one process)
"""

from __future__ import annotations

import os
import sys
import tomllib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import parse_config
from packpilot.sim.runner import Runner

SCENARIO = Path(__file__).resolve().parents[1] / "examples" / "evtol_charging.toml"
CAPACITY_AH = 100.0
"""The eVTOL scenario's battery (the acceptance's docks are for it: 20-200 A = 0.2-2C)."""
DISCHARGE_A = 2.0
DISCHARGE_S = 10.0
"""Acceptance: no battery discharging more than 2 A for more than 10 s while the dock charges."""
V_LOW = 96.0
"""The lowest battery's rest voltage (V)."""

COUNTS = (3, 4, 5, 6)
SPREADS_V = (1.0, 3.0, 6.0, 10.0)
DOCKS_A = (20.0, 50.0, 100.0, 200.0)
SMALL = ((3, 1.0, 20.0), (4, 9.0, 100.0), (5, 3.0, 200.0), (6, 10.0, 50.0))
"""The CI subset: every count, spread and dock range once (seed 001's shape in the second)."""


def voltages(n: int, spread_v: float) -> list[float]:
    """Rest voltages of ``n`` batteries spread over ``spread_v``: a low battery, irregular
    gaps (weights 2, 3, 4, 1, 5 ...), the top one at ``V_LOW + spread_v``."""
    weights = [2.0, 3.0, 4.0, 1.0, 5.0][: n - 1]
    total = sum(weights)
    out, v = [V_LOW], V_LOW
    for w in weights:
        v += spread_v * w / total
        out.append(round(v, 3))
    return out


def scenario(n: int, spread_v: float, dock_a: float) -> dict[str, Any]:
    """evtol_charging with ``n`` batteries at :func:`voltages` and a ``dock_a`` dock, long
    enough to charge them all at the dock's current plus a CV tail."""
    data = tomllib.loads(SCENARIO.read_text())
    aux = [b for b in data["pack"]["batteries"] if b.get("role") == "aux"]
    data["pack"]["batteries"] = [
        {"name": f"B{k + 1}", "series_groups": 28, "ocv0_v": v}
        for k, v in enumerate(voltages(n, spread_v))
    ] + aux
    data["charger"].update({"current_a": dock_a, "rated_a": max(dock_a, 100.0)})
    data["charging"].update(
        {"charger_current_limit_a": dock_a, "termination_current_a": min(2.0, 0.05 * dock_a)}
    )
    need_s = n * 1.0 * CAPACITY_AH * 3600.0 / dock_a + 3 * 3600.0  # from empty, + CV tail
    data["sim"].update({"dt_s": 2.0, "duration_s": need_s, "progress": False})
    return data


def measure(n: int, spread_v: float, dock_a: float) -> dict[str, Any]:
    """One case in the closed loop: the figures of the acceptance."""
    runner = Runner(parse_config(scenario(n, spread_v, dock_a)), progress=False)
    res = runner.run()
    tr = list(runner.traction)
    cur = res.trace.channel("current_a")[:, tr]
    t = res.trace.t_s
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    charging = res.trace.charger_a > 0.01
    bad = (cur > DISCHARGE_A) & charging[:, None]
    longest = 0.0
    for k in range(len(tr)):
        run_s = 0.0
        for x in bad[:, k]:
            run_s = run_s + dt if x else 0.0
            longest = max(longest, run_s)
    worst = float(np.where(charging[:, None], cur, 0.0).max())
    full = {e.battery for e in res.events if e.kind == "BatteryFull"}
    done = [e.t_s for e in res.events if e.kind == "ChargeComplete"]
    return {
        "n": n,
        "spread_v": spread_v,
        "dock_a": dock_a,
        "volts": voltages(n, spread_v),
        "longest_discharge_s": longest,
        "max_discharge_a": round(worst, 2),
        "peak_cross_a": round(float(res.metrics["peak_cross_current_a"]), 2),
        "all_full": len(full) == n and bool(done),
        "final_soc_min": round(float(res.trace.channel("soc")[-1, tr].min()), 4),
        "complete_s": done[0] if done else None,
        "ok": longest <= DISCHARGE_S and len(full) == n and bool(done),
    }


def _case(args: tuple[int, float, float]) -> dict[str, Any]:
    return measure(*args)


def run(small: bool = False, workers: int | None = None) -> list[dict[str, Any]]:
    cases = SMALL if small else [(n, s, d) for n in COUNTS for s in SPREADS_V for d in DOCKS_A]
    w = workers if workers is not None else min(len(cases), os.cpu_count() or 1)
    if w <= 1:
        rows = []
        for c in cases:
            rows.append(_case(c))
            print("  ", {k: rows[-1][k] for k in ("n", "spread_v", "dock_a",
                  "longest_discharge_s", "max_discharge_a", "all_full")}, flush=True)  # fmt: skip
        return rows
    with ProcessPoolExecutor(max_workers=w) as pool:
        return list(pool.map(_case, cases))


def main(argv: list[str]) -> None:
    rows = run(small="--small" in argv, workers=1 if "--serial" in argv else None)
    cols = ("n", "spread_v", "dock_a", "longest_discharge_s", "max_discharge_a",
            "peak_cross_a", "all_full", "final_soc_min", "complete_s", "ok")  # fmt: skip
    print(" | ".join(cols))
    for r in rows:
        print(" | ".join(str(r[c]) for c in cols))
    bad = [r for r in rows if not r["ok"]]
    print(
        f"{len(rows) - len(bad)}/{len(rows)} cases meet the acceptance (no battery discharging "
        f"> {DISCHARGE_A:g} A for > {DISCHARGE_S:g} s while the dock charges, all full); "
        f"longest discharge {max(r['longest_discharge_s'] for r in rows):.0f} s, "
        f"largest {max(r['max_discharge_a'] for r in rows):.1f} A"
    )


if __name__ == "__main__":
    main(sys.argv[1:])
