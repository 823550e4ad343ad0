"""Cost of the charger link per pack and step: the compiled TC/Elcon model vs python-can.

Both links run on the eVTOL charging bus put on a virtual CAN bus (the dock charging, the
scenario's default setpoint, heartbeat and status frames every second), inside a closed loop
of P packs (P = 1 and P = 256; the python-can path builds one client, one emulator and two
virtual buses per pack). Measured: ``links.poll(t, m)`` + ``links.send(t, cmd)`` of one step,
per pack, best of a few repeats, after warm-up; and a whole loop step per pack for context.
Times are this process's CPU time (``time.process_time``): on a shared machine wall time
mostly measures the neighbours. ``--dt 2.0`` (the example's period) sends a request and a status
frame every step; ``--dt 0.2`` (the UAV mission's) one of each every fifth step.

Run: ``python benchmarks/bench_elcon.py [--packs 1 256] [--steps 400] [--dt 0.2]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from packpilot.config import ScenarioConfig, load_config
from packpilot.sim.elcon import ElconLinks
from packpilot.sim.links import can_link
from packpilot.sim.loop import ClosedLoop
from packpilot.sim.plant_io import SimulatedPlant

ROOT = Path(__file__).resolve().parents[1]


def config(dt_s: float | None) -> ScenarioConfig:
    doc = load_config(ROOT / "examples" / "evtol_charging.toml").model_dump()
    if dt_s is not None:
        doc["sim"]["dt_s"] = dt_s
    doc["controller"] = []  # every method compiled: a batch of 256 packs can run
    doc["soc"] = {}
    doc["can"] = {"interface": "virtual"}
    doc["sim"]["progress"] = False
    return ScenarioConfig.model_validate(doc)


def build(cfg: ScenarioConfig, n: int, model: bool) -> ClosedLoop:
    if model:
        loop = ClosedLoop.of(cfg, n)
        assert isinstance(loop.links, ElconLinks)
        return loop
    plant = SimulatedPlant(cfg, n)
    return ClosedLoop.of(cfg, links=[can_link(cfg, plant.pack, p) for p in range(n)], plant=plant)


def link_cost(loop: ClosedLoop, steps: int, repeats: int = 5) -> float:
    """µs per pack per step of poll + send (the plant does not step: the link alone)."""
    dt = loop.cfg.sim.dt_s
    n = loop.plant.n_packs
    t = loop.plant.t_s
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(steps):
            loop.links.poll(t, loop.m)
            loop.links.send(t, loop.core.cmd)
            t += dt
        best = min(best, (time.process_time() - t0) / steps / n)
    return best * 1e6


def step_cost(loop: ClosedLoop, steps: int) -> float:
    """µs per pack per whole loop step (plant, core, links)."""
    dt = loop.cfg.sim.dt_s
    t0 = time.process_time()
    for k in range(steps):
        loop.step(k, dt)
    return (time.process_time() - t0) / steps / loop.plant.n_packs * 1e6


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--packs", type=int, nargs="*", default=[1, 256])
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--dt", type=float, default=None, help="period (default: the example's)")
    args = ap.parse_args(argv)
    cfg = config(args.dt)
    print(f"dt = {cfg.sim.dt_s} s")
    rows: list[dict[str, Any]] = []
    for n in args.packs:
        for model in (True, False):
            loop = build(cfg, n, model)
            try:
                for k in range(20):  # warm-up: compile, dock charging, frames flowing
                    loop.step(k, cfg.sim.dt_s)
                steps = max(20, args.steps // max(1, n // 16)) if not model else args.steps
                whole = step_cost(loop, max(10, steps // 4))
                link = link_cost(loop, steps)
            finally:
                loop.close()
            name = "model" if model else "python-can"
            rows.append({"P": n, "link": name, "link_us": link, "step_us": whole})
            print(
                f"P={n:4d} {rows[-1]['link']:>10s}: link {link:8.3f} µs/pack-step, "
                f"whole loop step {whole:8.2f} µs/pack-step",
                flush=True,
            )
    for n in args.packs:
        m = next(r for r in rows if r["P"] == n and r["link"] == "model")
        p = next(r for r in rows if r["P"] == n and r["link"] == "python-can")
        print(f"P={n:4d}: the model is {p['link_us'] / m['link_us']:.0f}x cheaper per pack-step")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
