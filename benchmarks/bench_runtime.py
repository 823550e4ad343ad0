"""Loop timing of ``packpilot run`` against ``packpilot hil`` in real time.

Two threads of one process on a python-can ``virtual`` channel (this kernel has no vcan):
the twin (uav_mission in flight, stepping every BMS period) and the BMS runtime on its
monotonic clock, for ``--seconds`` of wall time = simulated time, at each ``--period``.
Reported per period: BMS steps, overruns and missed periods, start jitter p50/p99/max, step
time p50/p99/max (the whole BMS period: read the bus, the core, commands, publications),
telemetry faults and switch-node timeouts (both should be 0). Wall-clock figures on a 2-core
machine shared with other sessions: the neighbours show up in the tails.

Run: ``python benchmarks/bench_runtime.py [--seconds 600] [--period 0.1 0.01]``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from packpilot.config import load_config
from packpilot.runtime.realtime import run_against_twin

ROOT = Path(__file__).resolve().parents[1]


def measure(period_s: float, seconds: float) -> dict[str, Any]:
    cfg = load_config(ROOT / "examples" / "uav_mission.toml")
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"dt_s": period_s})})
    bms, hil, m = run_against_twin(cfg, period_s, seconds, f"bench-{period_s:g}")
    m["telemetry_faults"] = sum(1 for e in bms.events if e.kind == "Fault")
    m["switch_timeouts"] = sum(n.timeouts for n in hil.switch)
    m["unsupplied_periods"] = 0 if hil.last_iv is None else int(not hil.last_iv.supplied[0])
    return m


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--period", type=float, nargs="+", default=[0.1, 0.01])
    args = ap.parse_args()
    for p in args.period:
        m = measure(p, args.seconds)
        keys = (
            "steps", "overruns", "missed_periods", "jitter_p50_ms", "jitter_p99_ms",
            "jitter_max_ms", "step_p50_ms", "step_p99_ms", "step_max_ms", "telemetry_faults",
            "switch_timeouts", "can_malformed", "can_babbling_periods",
        )  # fmt: skip
        print(json.dumps({"period_s": p, **{k: m[k] for k in keys}}), flush=True)


if __name__ == "__main__":
    main()
