"""The one BMS core: step cost of the whole supervised BMS + plant (issue #14's figures).

Four figures, each beside a reference measured in the same run (this 2-core VM is shared, its
speed drifts by tens of % within minutes: only same-run ratios travel):

1. **P = 1**: CPU per step of ``examples/uav_mission.toml``'s flight (t = 0..1200 s, the
   ``uav_flight`` profile from spool-up to motors off; 6,000 steps of 0.2 s) through the closed
   loop (``ClosedLoop.step``: links, sensors, the fused core with its seven methods and the
   supervisor, actuation, plant, events, metrics), median of repeats after a warm-up; beside
   PyBaMM's ``Simulation.step`` (Thevenin, ECM_Example, dt 0.1 s, as ``bench_loop``), the two
   measured in alternation. Also ``Runner.run()`` over the same window (adds the trace
   recording a single run keeps). Goal: <= 60 us (was 644 us; PyBaMM's step 1,322 us).
2. **P = 256, lockstep**: CPU per pack-step of the same flight for a batch of 256 packs with the
   campaign's spreads, whole BMS; beside the plant alone (``SimulatedPlant.step``: no sensors,
   no core, no metrics) and the core-less loop (the same loop with an empty core), the three
   stepped in alternating chunks of 100 steps so they share the machine's conditions. Goal:
   <= 8 us (plant alone was 2.1 us).
3. **Compile / start**: a fresh process with an empty ``NUMBA_CACHE_DIR`` (first use: every
   kernel compiled), then a second fresh process on that cache (import packpilot, build the
   uav_mission Runner, run 5 steps): wall clock from spawn to exit. Goal: cached <= 3 s.
4. **Where the time goes**: the loop's phases (sense, core_step, actuate, plant step, metrics,
   links, events, demand...) timed inside one instrumented copy of ``ClosedLoop.step`` (its
   results checked bit-equal to the real step), and the core step per method (the fused
   kernel run with one branch enabled at a time on a snapshot of the arena).

Run: ``python benchmarks/bench_core.py [--quick] [--no-compile]``; ``run()`` for ``make bench``.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT / "src") not in sys.path:
    sys.path.insert(0, str(ROOT / "src"))
os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")

MISSION = ROOT / "examples" / "uav_mission.toml"
FLIGHT_S = (0.0, 1200.0)
"""The flight of uav_mission: the ``uav_flight`` profile runs 0..1200 s (take-off at 5 s,
landing flare to 1190 s, motors off at 1200 s); the charger docks at 1300 s."""
SPREAD = "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35"
GOAL_P1_US = 60.0
GOAL_P256_US = 8.0
GOAL_START_S = 3.0
WAS_P1_US = 644.0
WAS_PYBAMM_US = 1322.0
WAS_PLANT_US = 2.1


def _cfg(duration_s: float | None = None) -> Any:
    from packpilot.config import load_config

    cfg = load_config(MISSION)
    sim = {"progress": False}
    if duration_s is not None:
        sim["duration_s"] = duration_s
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update=sim)})


def _flight_steps(cfg: Any) -> tuple[int, int]:
    dt = cfg.sim.dt_s
    return round(FLIGHT_S[0] / dt), round(FLIGHT_S[1] / dt)


def _cpu(fn: Callable[[], Any]) -> float:
    t0 = time.process_time()
    fn()
    return time.process_time() - t0


def _others_busy_cores(window_s: float = 1.0) -> float:
    """Cores kept busy by other processes right now (/proc/stat while this one sleeps)."""
    stat = Path("/proc/stat")
    if not stat.exists():
        return float("nan")

    def sample() -> tuple[int, int]:
        f = [int(x) for x in stat.read_text().splitlines()[0].split()[1:]]
        idle = f[3] + f[4]
        return sum(f) - idle, sum(f)

    b0, t0 = sample()
    time.sleep(window_s)
    b1, t1 = sample()
    return (b1 - b0) / max(1, t1 - t0) * (os.cpu_count() or 1)


# ---------------------------------------------------------------------------------- PyBaMM
def _pybamm_sim() -> Any:
    import pybamm

    sim = pybamm.Simulation(
        pybamm.equivalent_circuit.Thevenin(),
        parameter_values=pybamm.ParameterValues("ECM_Example"),
    )
    sim.step(dt=0.1)  # build + first solve outside the timing
    return sim


def _pybamm_cpu_us(n: int = 100) -> float:
    """CPU per ``Simulation.step(dt=0.1)`` of a fresh simulation (as ``bench_loop``)."""
    sim = _pybamm_sim()
    return _cpu(lambda: [sim.step(dt=0.1) for _ in range(n)]) / n * 1e6


# ---------------------------------------------------------------------------------- P = 1
def _loop(cfg: Any, n_packs: int = 1, overrides: Any = None, core: Any = None) -> Any:
    from packpilot.sim.loop import ClosedLoop
    from packpilot.sim.plant_io import SimulatedPlant

    if core == "empty":
        from packpilot.control.core import Core

        plant = SimulatedPlant(cfg, n_packs, overrides)
        return ClosedLoop.of(cfg, n_packs, core=Core(plant.infos, [], None), plant=plant)
    return ClosedLoop.of(cfg, n_packs, overrides=overrides)


def _flight_cpu_us(cfg: Any) -> float:
    """CPU per step of one pack through the flight (a fresh loop from t = 0)."""
    k0, k1 = _flight_steps(cfg)
    loop = _loop(cfg)
    dt = cfg.sim.dt_s
    step = loop.step
    for k in range(k0):
        step(k, dt)

    def fly() -> None:
        for k in range(k0, k1):
            step(k, dt)

    us = _cpu(fly) / (k1 - k0) * 1e6
    loop.close()
    return us


def _runner_cpu_us(cfg: Any) -> float:
    """CPU per step of ``Runner(cfg).run()`` over the flight (build included, trace kept)."""
    from packpilot.sim.runner import Runner

    _, k1 = _flight_steps(cfg)
    flight = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": FLIGHT_S[1]})})
    return _cpu(lambda: Runner(flight).run()) / k1 * 1e6


def p1(repeat: int) -> dict[str, Any]:
    cfg = _cfg()
    _flight_cpu_us(cfg)  # warm-up: numba cache load, first-call paths
    _runner_cpu_us(cfg)
    _pybamm_cpu_us(20)
    ours, runner, pyb = [], [], []
    for _ in range(repeat):  # alternate, so both see the same machine
        pyb.append(_pybamm_cpu_us())
        ours.append(_flight_cpu_us(cfg))
        runner.append(_runner_cpu_us(cfg))
    return {
        "loop_us": statistics.median(ours),
        "loop_all_us": ours,
        "runner_us": statistics.median(runner),
        "pybamm_us": statistics.median(pyb),
        "pybamm_all_us": pyb,
    }


# ---------------------------------------------------------------------------------- P = 256
def _overrides(n: int, cfg: Any) -> dict[str, Any]:
    from packpilot.campaign import make_draws, parse_spreads, stack_overrides

    return stack_overrides(make_draws(parse_spreads(SPREAD), 0, range(n), cfg.pack.ambient_c))


def _run_loop(loop: Any, a: int, b: int, dt: float) -> None:
    for k in range(a, b):
        loop.step(k, dt)


def _run_plant(plant: Any, loop: Any, demand: Any, a: int, b: int, dt: float) -> None:
    """The plant alone under the loop's load profile (gates as built: all on)."""
    kind = loop.profile.kind
    for _ in range(a, b):
        demand.fill(loop.demand(plant.t_s))
        plant.step(dt, demand, kind)


def lockstep(n_packs: int, passes: int, chunk: int = 100) -> dict[str, Any]:
    """CPU per pack-step over the flight: whole BMS, core-less loop, plant alone, in
    alternating chunks of ``chunk`` steps (each pass rebuilds the three from t = 0)."""
    from packpilot.sim.plant_io import SimulatedPlant

    cfg = _cfg()
    dt = cfg.sim.dt_s
    k0, k1 = _flight_steps(cfg)
    over = _overrides(n_packs, cfg)
    warm = _loop(cfg, 2, _overrides(2, cfg))
    for k in range(20):
        warm.step(k, dt)
    cpu = {"bms": 0.0, "coreless": 0.0, "plant": 0.0}
    per_pass: dict[str, list[float]] = {k: [] for k in cpu}
    steps = 0
    for _ in range(passes):
        full = _loop(cfg, n_packs, over)
        bare = _loop(cfg, n_packs, over, core="empty")
        plant = SimulatedPlant(cfg, n_packs, over)
        demand = np.empty(n_packs)
        this = dict.fromkeys(cpu, 0.0)
        _run_loop(full, 0, k0, dt)
        _run_loop(bare, 0, k0, dt)
        _run_plant(plant, full, demand, 0, k0, dt)
        for a in range(k0, k1, chunk):
            b = min(a + chunk, k1)
            this["bms"] += _cpu(lambda a=a, b=b, x=full: _run_loop(x, a, b, dt))
            this["coreless"] += _cpu(lambda a=a, b=b, x=bare: _run_loop(x, a, b, dt))
            this["plant"] += _cpu(
                lambda a=a, b=b, x=plant, f=full, d=demand: _run_plant(x, f, d, a, b, dt)
            )
        n = (k1 - k0) * n_packs
        for key, v in this.items():
            cpu[key] += v
            per_pass[key].append(v / n * 1e6)
        steps += n
        full.close()
        bare.close()
    out: dict[str, Any] = {k: v / steps * 1e6 for k, v in cpu.items()}
    out["per_pass"] = per_pass
    return out


# ---------------------------------------------------------------------------------- start-up
_CHILD = r"""
import json, time
t0 = time.perf_counter()
from packpilot.config import load_config
from packpilot.sim.runner import Runner
t1 = time.perf_counter()
cfg = load_config(%(mission)r)
cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": 1.0,
                                                                "progress": False})})
r = Runner(cfg)
t2 = time.perf_counter()
res = r.run()
t3 = time.perf_counter()
assert res.metrics["steps"] == 5, res.metrics
print(json.dumps({"import_s": t1 - t0, "build_s": t2 - t1, "steps_s": t3 - t2,
                  "cpu_s": time.process_time()}))
"""


def _child(cache_dir: str) -> dict[str, float]:
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir, PYBAMM_DISABLE_TELEMETRY="true")
    extra = [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT / "src"), str(ROOT), *extra])
    code = _CHILD % {"mission": str(MISSION)}
    t0 = time.perf_counter()
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False
    )
    wall = time.perf_counter() - t0
    if out.returncode != 0:
        raise RuntimeError(f"child failed:\n{out.stderr[-3000:]}")
    row: dict[str, float] = json.loads(out.stdout.strip().splitlines()[-1])
    row["wall_s"] = wall
    return row


def startup(warm_repeat: int = 3) -> dict[str, Any]:
    """First use with an empty numba cache, then second processes on that cache."""
    with tempfile.TemporaryDirectory(prefix="packpilot-numba-") as cache:
        busy = _others_busy_cores()
        cold = _child(cache)
        files = sum(1 for _ in Path(cache).rglob("*.nbc"))
        warm = [_child(cache) for _ in range(warm_repeat)]
    best = min(warm, key=lambda r: r["wall_s"])
    return {
        "cold": cold,
        "warm": warm,
        "warm_median_s": statistics.median(r["wall_s"] for r in warm),
        "warm_best": best,
        "cache_files": files,
        "others_busy_cores": busy,
    }


# ---------------------------------------------------------------------------------- profile
PHASES = (
    "hooks+faults", "links.poll", "sense", "core_step", "actuate", "links.send",
    "demand", "plant.step", "events", "supply", "metrics", "stop",
)  # fmt: skip


def _timed_tail(loop: Any, t: float, iv: Any, dt_s: float, acc: dict[str, int]) -> Any:
    """The part of ``ClosedLoop.step`` after the plant: event kinds, supply, metrics, stop."""
    from packpilot.sim.loop import with_supply

    pc = time.perf_counter_ns
    core, plant = loop.core, loop.plant
    a = pc()
    kinds = core.event_kinds() if core.ev.n[0] else None
    b = pc()
    acc["events"] += b - a
    supply = loop._supply_events(t, iv, dt_s)
    kinds = with_supply(kinds, supply, plant.n_packs)
    a = pc()
    acc["supply"] += a - b
    loop.metrics.add(plant.pack, iv, loop._traction, kinds)
    b = pc()
    acc["metrics"] += b - a
    stop = loop.cfg.sim.stop_when_unsupplied_s
    if stop is not None:
        loop.metrics.stop(loop.unsupplied_s >= stop, plant.pack)
    acc["stop"] += pc() - b
    return supply


def _timed_step(loop: Any, k: int, dt_s: float, acc: dict[str, int]) -> Any:
    """``ClosedLoop.step`` with a clock between its phases (same calls, same order)."""
    from packpilot.control.core_kernel import DIR_CMD, DIR_M
    from packpilot.sim.loop import StepRecord

    pc = time.perf_counter_ns
    plant, m, core = loop.plant, loop.m, loop.core
    a = pc()
    t = plant.t_s
    for hook in loop.hooks:
        hook(t)
    if loop.faults is not None:
        loop.faults.before_step(t)
    b = pc()
    acc["hooks+faults"] += b - a
    if loop.links:
        loop.links.poll(t, m)
    a = pc()
    acc["links.poll"] += a - b
    plant.measure(core.arenas, int(core.directory[DIR_M]))
    if loop.faults is not None:
        loop.faults.filter(m)
    b = pc()
    acc["sense"] += b - a
    core.step_batch(m, dt_s)
    a = pc()
    acc["core_step"] += a - b
    plant.apply(core.arenas, int(core.directory[DIR_CMD]))
    b = pc()
    acc["actuate"] += b - a
    if loop.links:
        loop.links.send(t, core.cmd)
    a = pc()
    acc["links.send"] += a - b
    demand = np.full(plant.n_packs, loop.demand(t))
    b = pc()
    acc["demand"] += b - a
    iv = plant.step(dt_s, demand, loop.profile.kind)
    a = pc()
    acc["plant.step"] += a - b
    loop.n_stepped += 1
    supply = _timed_tail(loop, t, iv, dt_s, acc)
    return StepRecord(k, iv, loop, supply)


def _same(a: Any, b: Any) -> bool:
    """Two loops in the same state (plant, core arena, metrics), bit for bit."""
    ma, mb = a.metrics, b.metrics
    arrays = [
        (a.plant.pack.bus_v, b.plant.pack.bus_v),
        (a.plant.pack.cell_voltage_now(), b.plant.pack.cell_voltage_now()),
        (ma.energy_out, mb.energy_out),
        (ma.min_cell_v, mb.min_cell_v),
        (ma.peak_val, mb.peak_val),
        *zip(a.core.arenas, b.core.arenas, strict=True),
    ]
    same = all(np.array_equal(x, y, equal_nan=x.dtype.kind == "f") for x, y in arrays)
    return same and ma.events == mb.events


def phase_profile(n_packs: int, steps: int, start: int = 250) -> dict[str, Any]:
    """Per-phase wall time of the loop (us per pack-step) at ``n_packs``, from flight step
    ``start`` on; the instrumented step is checked bit-equal to ``ClosedLoop.step``."""
    cfg = _cfg()
    dt = cfg.sim.dt_s
    over = _overrides(n_packs, cfg) if n_packs > 1 else None
    loop = _loop(cfg, n_packs, over)
    twin = _loop(cfg, n_packs, over)
    for k in range(start):
        loop.step(k, dt)
        twin.step(k, dt)
    acc = dict.fromkeys(PHASES, 0)
    w0 = time.perf_counter()
    c0 = time.process_time()
    for k in range(start, start + steps):
        _timed_step(loop, k, dt, acc)
    cpu = time.process_time() - c0
    wall = time.perf_counter() - w0
    for k in range(start, start + steps):
        twin.step(k, dt)
    checked = _same(loop, twin)
    loop.close()
    twin.close()
    n = steps * n_packs
    out: dict[str, Any] = {name: acc[name] / n / 1e3 for name in PHASES}
    out["sum_of_phases"] = sum(acc.values()) / n / 1e3
    out["wall"] = wall / n * 1e6
    out["cpu"] = cpu / n * 1e6
    out["bit_equal_to_loop_step"] = checked
    return out


def core_profile(n_packs: int, steps: int = 300, start: int = 250) -> dict[str, float]:
    """The fused core step per method (us per pack-step, wall, best of 5): the kernel with
    only that branch enabled, on a snapshot of the arena taken during the flight, minus the
    kernel with none enabled (clear + unpack + call); ``full`` is all of them."""
    from packpilot.control.core_kernel import DIR_N_PARTS, DIR_PARTS, DIR_STRIDE, DIR_SUP_PRM

    cfg = _cfg()
    dt = cfg.sim.dt_s
    loop = _loop(cfg, n_packs, _overrides(n_packs, cfg) if n_packs > 1 else None)
    for k in range(start):
        loop.step(k, dt)
    core = loop.core
    d0 = core.directory
    n_parts = int(d0[DIR_N_PARTS])
    core_step = core.step_kernel
    saved = [a.copy() for a in core.arenas]

    def variant(keep: set[int], sup: bool) -> Any:
        d = d0.copy()
        for j in range(n_parts):
            if j not in keep:
                d[DIR_PARTS + DIR_STRIDE * j] = -1
        if not sup:
            d[DIR_SUP_PRM] = -1
        return d

    def best(d: Any) -> float:
        b = float("inf")
        for _ in range(5):
            for a, s in zip(core.arenas, saved, strict=True):
                np.copyto(a, s)
            t0 = time.perf_counter()
            for _ in range(steps):
                core_step(*core.arenas, d, dt)
            b = min(b, (time.perf_counter() - t0) / steps)
        return b * 1e6 / n_packs

    none = best(variant(set(), False))
    out = {"clear+unpack+call": none}
    for j in range(n_parts):
        out[core.parts[j].method.name] = best(variant({j}, False)) - none
    out["supervisor"] = best(variant(set(), True)) - none
    out["full"] = best(d0)
    for a, s in zip(core.arenas, saved, strict=True):
        np.copyto(a, s)
    loop.close()
    return out


# ---------------------------------------------------------------------------------- run
def _verdict(value: float, goal: float) -> str:
    return "met" if value <= goal else "MISSED"


def run(quick: bool = False, compile_time: bool = True) -> list[dict[str, Any]]:
    """The rows for ``make bench``; rows with a ``goal`` are the issue's figures and carry
    the reference measured in the same run and a verdict."""
    rows: list[dict[str, Any]] = []

    def row(
        case: str, figure: float, unit: str, goal: str = "", note: str = "", ref: str = "",
        verdict: str = "",
    ) -> None:  # fmt: skip
        rows.append(
            {"case": case, "figure": figure, "unit": unit, "goal": goal, "verdict": verdict,
             "reference": ref, "note": note}
        )  # fmt: skip

    busy0 = _others_busy_cores()
    one = p1(repeat=3 if quick else 7)
    ratio = one["pybamm_us"] / one["loop_us"]
    row(
        "P=1 uav_mission flight, ClosedLoop.step, CPU per step",
        one["loop_us"],
        "us",
        f"<= {GOAL_P1_US:g} us",
        f"median of {len(one['loop_all_us'])} flights of 6,000 steps "
        f"(range {min(one['loop_all_us']):.1f}-{max(one['loop_all_us']):.1f}); "
        f"{WAS_P1_US / one['loop_us']:.1f}x less than the {WAS_P1_US:g} us before",
        f"PyBaMM Simulation.step {one['pybamm_us']:.0f} us CPU: {ratio:.1f}x faster",
        _verdict(one["loop_us"], GOAL_P1_US),
    )
    row(
        "PyBaMM Thevenin Simulation.step (1 cell, dt 0.1 s), CPU, same run",
        one["pybamm_us"],
        "us",
        "",
        f"median of {len(one['pybamm_all_us'])} x 100 steps, alternating with the row above "
        f"(was {WAS_PYBAMM_US:g} us wall in RESULTS.md, on another host)",
    )
    row("P=1 whole BMS + plant step vs one PyBaMM cell step", ratio, "x faster")
    row(
        "P=1 uav_mission flight, Runner.run() incl. trace recording, CPU per step",
        one["runner_us"],
        "us",
        "",
        f"{one['pybamm_us'] / one['runner_us']:.1f}x faster than the PyBaMM step",
    )

    lock = lockstep(256, passes=1 if quick else 2)
    row(
        "P=256 lockstep uav_mission flight, whole BMS, CPU per pack-step",
        lock["bms"],
        "us",
        f"<= {GOAL_P256_US:g} us",
        "passes: " + ", ".join(f"{x:.2f}" for x in lock["per_pass"]["bms"])
        + f"; core-less loop {lock['coreless']:.2f} us, so the core's own share is "
        f"{lock['bms'] - lock['coreless']:.2f} us",
        f"plant alone {lock['plant']:.2f} us: whole BMS = {lock['bms'] / lock['plant']:.2f}x",
        _verdict(lock["bms"], GOAL_P256_US),
    )  # fmt: skip
    row(
        "P=256 plant alone (SimulatedPlant.step), CPU per pack-step, same run",
        lock["plant"],
        "us",
        "",
        f"was {WAS_PLANT_US:g} us (another plant and host)",
    )
    row(
        "P=256 core-less loop (sensors, links, plant, metrics; empty core), CPU per pack-step",
        lock["coreless"],
        "us",
        "",
        f"the BMS core's own share: {lock['bms'] - lock['coreless']:.2f} us",
    )

    prof1 = phase_profile(1, 1000 if quick else 3000)
    prof256 = phase_profile(256, 60 if quick else 200)
    core1 = core_profile(1, 1000)
    core256 = core_profile(256, 30 if quick else 100)
    for label, prof in (("P=1", prof1), ("P=256", prof256)):
        note = (
            f"wall {prof['wall']:.2f} us, CPU {prof['cpu']:.2f} us per pack-step while timed; "
            f"instrumented step bit-equal to ClosedLoop.step: {prof['bit_equal_to_loop_step']}"
        )
        row(f"{label} profile: sum of loop phases (wall)", prof["sum_of_phases"], "us", "", note)
        for name in PHASES:
            row(f"{label} profile: {name}", prof[name], "us")
    for label, prof in (("P=1", core1), ("P=256", core256)):
        for name, v in prof.items():
            row(f"{label} core_step by method: {name}", v, "us", "", "wall, best of 5")

    if compile_time:
        st = startup()
        cold, best = st["cold"], st["warm_best"]
        row(
            "first use: fresh process, empty NUMBA_CACHE_DIR, import, uav_mission Runner, 5 steps",
            cold["wall_s"],
            "s wall",
            "reported",
            f"import {cold['import_s']:.1f} s, build {cold['build_s']:.1f} s, first steps "
            f"{cold['steps_s']:.1f} s (compiling); CPU {cold['cpu_s']:.0f} s; "
            f"{st['cache_files']} cached kernels; "
            f"others used {st['others_busy_cores']:.2f} cores",
            f"cached start {st['warm_median_s']:.2f} s: "
            f"{cold['wall_s'] / st['warm_median_s']:.0f}x",
            "reported",
        )
        row(
            "cached start: second fresh process, same cache, same work",
            st["warm_median_s"],
            "s wall",
            f"<= {GOAL_START_S:g} s",
            f"median of {len(st['warm'])}; best {best['wall_s']:.2f} s = import "
            f"{best['import_s']:.2f} + build {best['build_s']:.2f} + steps "
            f"{best['steps_s']:.2f} s + interpreter",
            f"first use {cold['wall_s']:.0f} s",
            _verdict(st["warm_median_s"], GOAL_START_S),
        )
    row(
        "other processes' load at start",
        busy0,
        "cores",
        "",
        f"{_others_busy_cores():.2f} at the end; 2 cores",
    )
    return rows


def main() -> None:
    args = sys.argv[1:]
    rows = run(quick="--quick" in args, compile_time="--no-compile" not in args)
    for r in rows:
        print(
            f"{r['case']:<92} {r['figure']:10.4g} {r['unit']:<9} {r['goal']:<11} "
            f"{r['verdict']:<9} {r['reference']}  {r['note']}"
        )


if __name__ == "__main__":
    main()
