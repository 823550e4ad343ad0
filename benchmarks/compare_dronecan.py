"""A run on DroneCAN batteries against ``simulate`` of the same scenario, measured.

``run`` against ``hil`` in lock-step (``runtime/lockstep.py``) with every battery on DroneCAN
BatteryInfo + BatteryInfoAux (``--dbc``: on the PackPilot frames instead), and ``Runner(cfg)``
of the same scenario: how far the values the BMS read sit from the twin's sensing (the wire's
resolution), the events per kind (same sequence? how far apart?), the switch transitions
(missing / extra at one period, offsets when the sequences agree; the aux relay's too), the
energy to the load and from the dock, protection's allowance used at the end, the load
supplied, the group SOC spread at the end (what equalization achieved). The numbers of
docs/runtime.md, "Batteries on DroneCAN"; the tests pin what holds
(``tests/test_runtime_hil.py``).

Run: ``python benchmarks/compare_dronecan.py uav_mission 1250`` (about 20 s) or
``python benchmarks/compare_dronecan.py evtol_charging 18000`` (about 3-4 minutes); JSON out.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.bms import Event
from packpilot.model.pack import Pack
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.lockstep import lockstep, match_transitions, transitions
from packpilot.sim.loop import n_steps
from packpilot.sim.runner import Runner

QUANTITIES = ("voltage_v", "current_a", "temp_c", "min_cell_v", "max_cell_v", "soc", "group_v")


def scenario(name: str, duration_s: float) -> ScenarioConfig:
    cfg = load_config(scenario_path(Path(name)))
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": duration_s})})


def group_soc_spread(pack: Pack) -> list[float]:
    soc = pack.cell_states()[0][0]
    return [float(np.ptp(soc[pack.cell_string == s])) for s in range(pack.n_strings)]


def run_can(cfg: ScenarioConfig, dronecan: bool) -> dict[str, Any]:
    n_bat = len(cfg.pack.batteries)
    ids = tuple(21 + i for i in range(n_bat)) if dronecan else None
    opts = RuntimeOptions(dronecan_ids=ids, allow_unmonitored=cfg.plausibility is None)
    ls = lockstep(cfg, opts)
    err: dict[str, list[float]] = {q: [] for q in QUANTITIES}
    aux = ls.hil.plant.topology.aux
    aux_relay: list[bool] = []
    t0 = time.perf_counter()
    try:
        for _ in range(n_steps(cfg)):
            ls.step(cfg.sim.dt_s)
            if aux is not None:
                aux_relay.append(bool(ls.hil.plant.pack.effective_gates()[0][0, aux]))
            for q in QUANTITIES:
                d = np.abs(getattr(ls.bms.core.m.bat, q)[0] - getattr(ls.hil.m.bat, q)[0])
                d = d[np.isfinite(d)]
                err[q].append(float(d.max()) if d.size else 0.0)
    finally:
        ls.close()
    n, b = len(ls.chg), ls.hil.plant.infos[0].n_batteries
    c = ls.bms.plant.counters
    return {
        "wall_s": time.perf_counter() - t0,
        "events": ls.bms.events,
        "chg": np.array(ls.chg).reshape(n, b),
        "dsg": np.array(ls.dsg).reshape(n, b),
        "aux_relay": np.array(aux_relay).reshape(-1, 1),
        "load_wh": ls.load_j / 3600.0,
        "dock_wh": ls.dock_j / 3600.0,
        "allowance": ls.bms.core.status_of(0).get("protection_fraction"),
        "unsupplied_periods": int(np.sum(~np.array(ls.supplied))),
        "group_soc_spread": group_soc_spread(ls.hil.plant.pack),
        "error_max": {q: max(v) for q, v in err.items()},
        "error_p50": {q: float(np.median(v)) for q, v in err.items()},
        "frames": {"received": c.received, "malformed": c.malformed, "unexpected": c.unexpected,
                   "dronecan_errors": ls.bms.plant.assembler.errors,
                   "switch_timeouts": sum(node.timeouts for node in ls.hil.switch)},
    }  # fmt: skip


def compare_events(sim: list[Event], can: list[Event]) -> dict[str, Any]:
    """Per kind: the counts, and the largest offset when the (kind, battery) sequences agree."""
    out: dict[str, Any] = {}
    for kind in sorted({e.kind for e in sim} | {e.kind for e in can}):
        a = [e for e in sim if e.kind == kind]
        b = [e for e in can if e.kind == kind]
        same = [e.battery for e in a] == [e.battery for e in b]
        worst = max((abs(x.t_s - y.t_s) for x, y in zip(a, b, strict=False)), default=0.0)
        out[kind] = {"simulate": len(a), "can": len(b), "max_offset_s": worst if same else None}
    return out


def compare_switches(sim: np.ndarray, can: np.ndarray) -> dict[str, Any]:
    a, b = transitions(sim), transitions(can)
    missing, extra = match_transitions(sim, can, 1)
    offsets = [abs(x[0] - y[0]) for x, y in zip(a, b, strict=False)]
    same = [x[1:] for x in a] == [x[1:] for x in b]
    return {
        "simulate": len(a),
        "can": len(b),
        "max_offset_periods": max(offsets, default=0) if same else None,
        "missing_at_1_period": missing,
        "extra_at_1_period": extra,
        "agreement": float(np.mean(sim == can)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("scenario")
    ap.add_argument("duration_s", type=float)
    ap.add_argument("--dbc", action="store_true", help="the batteries on PackPilot frames")
    args = ap.parse_args()
    cfg = scenario(args.scenario, args.duration_s)
    runner = Runner(cfg, progress=False)
    sim = runner.run()
    can = run_can(cfg, not args.dbc)
    tr = list(runner.plant.topology.traction)
    aux = runner.plant.topology.aux
    dt = cfg.sim.dt_s
    allowance = sim.trace.status.get("protection_fraction")
    report = {
        "scenario": args.scenario,
        "duration_s": args.duration_s,
        "batteries_on": "PackPilot frames" if args.dbc else "DroneCAN",
        "can_wall_s": round(can["wall_s"], 1),
        "value_error_max": can["error_max"],
        "value_error_p50": can["error_p50"],
        "frames": can["frames"],
        "events": compare_events(sim.events, can["events"]),
        "chg_switches": compare_switches(sim.trace.channel("chg_on")[:, tr] > 0, can["chg"]),
        "dsg_switches": compare_switches(sim.trace.channel("dsg_on")[:, tr] > 0, can["dsg"]),
        "aux_relay": None if aux is None else compare_switches(
            sim.trace.channel("chg_on")[:, [aux]] > 0, can["aux_relay"]),
        "load_wh": {"simulate": float(np.sum(sim.trace.bus_v * sim.trace.load_a)) * dt / 3600,
                    "can": can["load_wh"]},
        "dock_wh": {"simulate": float(np.sum(sim.trace.charger_v * sim.trace.charger_a)) * dt
                    / 3600, "can": can["dock_wh"]},
        "allowance_used_end": {"simulate": allowance[-1] if allowance else None,
                               "can": can["allowance"]},
        "unsupplied_periods": can["unsupplied_periods"],
        "group_soc_spread_end": {"simulate": group_soc_spread(runner.pack),
                                 "can": can["group_soc_spread"]},
    }  # fmt: skip
    print(json.dumps(report, indent=1, default=str))


if __name__ == "__main__":
    main()
