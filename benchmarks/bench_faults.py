"""A sensor fault must not drop the bus (issue #15 §5): the fault matrix of
``docs/fault_injection.md`` on ``examples/uav_mission.toml``.

Each row is the whole mission (flight, dock, charging) with one fault injected at ``AT_S`` (in
the hover) or, for the dock's faults, while charging. Figures per row:

* ``unsupplied_s``: time the load got less than it asked for;
* ``unsupplied_with_energy_s``: the part of it while some battery still had energy above
  ``FLOOR_SOC`` (plant truth) - the goal is 0 s: losing power in flight while a battery could
  still supply it is the failure the degraded mode exists to prevent;
* ``flight_energy_wh`` and ``energy_vs_fault_free``: energy delivered to the load during the
  flight against the fault-free run of the same scenario;
* ``max_into_a``: the largest current into any battery while undocked (A, positive = into it);
* the degraded-mode events (``Fault``, ``ReserveEngaged``, ``ProtectionTripped``).

    python benchmarks/bench_faults.py
"""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import parse_config
from packpilot.sim.runner import Runner

SCENARIO = Path(__file__).resolve().parent.parent / "examples" / "uav_mission.toml"
AT_S = 300.0
FLIGHT_END_S = 1250.0
FLOOR_SOC = 0.02
GOAL_UNSUPPLIED_S = 0.0

SENSOR = ("voltage_v", "current_a", "temp_c", "min_cell_v", "max_cell_v", "soc")
MATRIX: tuple[tuple[str, dict[str, Any]], ...] = (
    ("fault-free", {}),
    *(
        (f"sensor_nan {q} B", {"kind": "sensor_nan", "quantity": q, "battery": "B"})
        for q in SENSOR
    ),
    ("sensor_nan temp_c A", {"kind": "sensor_nan", "quantity": "temp_c", "battery": "A"}),
    ("sensor_stuck voltage_v B", {"kind": "sensor_stuck", "quantity": "voltage_v", "battery": "B"}),
    ("sensor_stuck temp_c A", {"kind": "sensor_stuck", "quantity": "temp_c", "battery": "A"}),
    ("sensor_dropout B", {"kind": "sensor_dropout", "battery": "B"}),
    ("sensor_dropout A", {"kind": "sensor_dropout", "battery": "A"}),
    ("shorted_fet chg B", {"kind": "shorted_fet", "fet": "chg", "battery": "B"}),
    ("shorted_fet dsg B", {"kind": "shorted_fet", "fet": "dsg", "battery": "B"}),
    ("cooling_failure B", {"kind": "cooling_failure", "cooling_factor": 0.05, "battery": "B"}),
    ("charger_fault (docked)",
     {"kind": "charger_fault", "at_s": 1500.0, "flag": "hardware_failure"}),
    ("can_silence (docked)", {"kind": "can_silence", "at_s": 1500.0, "until_s": 1600.0}),
)


def _scenario(fault: dict[str, Any]) -> dict[str, Any]:
    d = tomllib.loads(SCENARIO.read_text())
    if fault:
        d["faults"] = [{"at_s": AT_S, **copy.deepcopy(fault)}]
    return d


def _row(name: str, fault: dict[str, Any]) -> dict[str, Any]:
    result = Runner(parse_config(_scenario(fault)), progress=False).run()
    tr = result.trace
    dt = np.diff(tr.t_s, prepend=tr.t_s[0] - (tr.t_s[1] - tr.t_s[0]))
    short = tr.load_a < tr.load_demand_a - np.maximum(1e-6, 0.01 * tr.load_demand_a)
    short &= tr.load_demand_a > 1e-9
    soc = tr.channel("soc")
    has_energy = (soc > FLOOR_SOC).any(axis=1)
    flight = tr.t_s <= FLIGHT_END_S
    current = tr.channel("current_a")
    undocked = tr.charger_v <= 0.0
    into = -current[undocked].min() if undocked.any() else 0.0
    kinds = [e.kind for e in result.events]
    return {
        "fault": name,
        "unsupplied_s": float(dt[short].sum()),
        "unsupplied_with_energy_s": float(dt[short & has_energy].sum()),
        "flight_energy_wh": float((tr.bus_v * tr.load_a * dt)[flight].sum() / 3600.0),
        "max_into_a": float(max(into, 0.0)),
        "faults": kinds.count("Fault"),
        "reserve_engaged": kinds.count("ReserveEngaged"),
        "trips": kinds.count("ProtectionTripped") + kinds.count("LimitTripped"),
    }


def run() -> list[dict[str, Any]]:
    rows = [_row(name, fault) for name, fault in MATRIX]
    ref = rows[0]["flight_energy_wh"]
    for r in rows:
        r["energy_vs_fault_free"] = r["flight_energy_wh"] / ref if ref > 0 else float("nan")
        r["goal_met"] = r["unsupplied_with_energy_s"] <= GOAL_UNSUPPLIED_S
    return rows


def main() -> None:
    rows = run()
    keys = list(rows[0])
    print("| " + " | ".join(keys) + " |")
    print("|" + "---|" * len(keys))
    for r in rows:
        cells = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in r.values()]
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
