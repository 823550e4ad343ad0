"""Compile every kernel the test suite runs, once, into numba's cache, before pytest (#25).

Why: ``make test COLD_KERNELS=1`` (CI) starts from an empty ``NUMBA_CACHE_DIR`` so that CI
proves the kernels compile from source. Left to the tests, the two xdist workers compiled the
same kernels at the same time (each its own ~4 CPU-minutes of the uav_mission core, the first
writer's cache entry wasted on the other), and so did a CLI test's subprocess that started
compiled, or a first run's background compile (``packpilot.warmup``) racing them. Here each
kernel is compiled by **one** process, the work split over ``--jobs`` processes (2 on this
machine), and the tests then load what they call from the cache (about a second per process).
Nothing is skipped: a kernel the suite calls that this step did not compile is compiled by the
test that calls it, as before; every kernel still compiles from source in every CI run.

Two phases (``packpilot.warmup``'s stages, spread over the processes):

1. each method's rules (``step_packs``, through a fused step of that method alone on a copy of
   a core's arenas: the argument types of every fused step that holds the method), the largest
   first, and the plant of a scenario with no method (``smart_battery``);
2. when all of those are in the cache: every shipped example's own fused step (its
   combination of methods and the supervisor, which loads the rules) and its plant, a few steps
   of it. Each leaves the marker a first run's background compile leaves
   (``packpilot.coldstart.marker``), so a CLI test of a shipped example starts compiled, as a
   user's second run does.

Run: ``python -m tests.precompile [--jobs N]`` (``make test`` does, before pytest). With every
example's marker present (a warm cache whose kernels' source did not change) it does nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
PLANT_ONLY = "smart_battery"
"""A shipped example with no method: its run compiles the plant and nothing of the core."""
RULES_CPU_S = {
    "soc": 131.0, "charging": 59.0, "sequencing": 59.0, "plausibility": 30.0,
    "protection": 16.0, "limits": 15.0, "equalization": 11.0, "plant": 42.0,
}  # fmt: skip
"""Cold compile of each method's rules job and of the plant (``smart_battery``), CPU s
(measured by this step, 2026-11-28 h25ci; soc's observer made it the dearest: coldstart's
1.9 s predates it). The order of phase 1, so that the last job to end is a short one (phase 2
waits for all of them)."""
BEAT_S = 15.0
"""Seconds between two progress lines while a compile goes on."""


def _rules(example: str, method: str) -> tuple[str, float]:
    """Compile ``method``'s rules through a fused step of that method alone (on ``example``'s
    core, which has it)."""
    c0 = time.process_time()
    from packpilot.config import load_config
    from packpilot.control.core_kernel import DIR_N_PARTS, DIR_PARTS, DIR_STRIDE, Fusion, fused
    from packpilot.sim.runner import Runner, as_core

    runner = Runner(load_config(EXAMPLES / f"{example}.toml"), progress=False)
    assert runner.controller is not None
    core = as_core(runner.controller, runner.info)
    assert core.fusion is not None
    kind_index = [_method(k.step_packs) for k in core.fusion.kinds].index(method)
    kind = core.fusion.kinds[kind_index]
    f, i, h, c, b, lay = (a.copy() for a in core.arenas)
    d = core.directory.copy()
    for j in range(int(d[DIR_N_PARTS])):  # this method's parts only: the others skip
        row = DIR_PARTS + DIR_STRIDE * j
        d[row] = 0 if d[row] == kind_index else -1
    fused(Fusion((kind,), False))(f, i, h, c, b, lay, d, runner.cfg.sim.dt_s)
    return f"rules:{_method(kind.step_packs)}", time.process_time() - c0


def _scenario(example: str) -> tuple[str, float]:
    """Compile what a run of ``example`` calls and leave its marker (``packpilot.warmup``)."""
    c0 = time.process_time()
    from packpilot.coldstart import marker
    from packpilot.config import load_config
    from packpilot.warmup import compile_scenario

    path = EXAMPLES / f"{example}.toml"
    scratch = Path(os.environ.get("TMPDIR", "/tmp")) / f"packpilot-precompile-{os.getpid()}"
    compile_scenario(path, scratch)
    scratch.unlink(missing_ok=True)
    mark = marker(load_config(path))
    mark.parent.mkdir(parents=True, exist_ok=True)
    mark.write_text(str(path) + "\n")
    return f"example:{example}", time.process_time() - c0


def _method(step_packs: str) -> str:
    return step_packs.split(":")[0].split(".")[-2]


def plan() -> tuple[list[tuple[str, str]], list[str]]:
    """Phase 1 (example, method) per distinct method, the dearest first (``RULES_CPU_S``);
    phase 2 the examples, the ones with the most methods first. Built from the examples'
    configs (no kernel is imported)."""
    from packpilot.coldstart import methods_of
    from packpilot.config import load_config

    names = sorted(p.stem for p in EXAMPLES.glob("*.toml"))
    cfgs = {n: load_config(EXAMPLES / f"{n}.toml") for n in names}
    first: dict[str, tuple[str, str]] = {}
    for n in names:
        for method in methods_of(cfgs[n]):
            if method != "supervisor":  # compiled with each supervised example's fused step
                first.setdefault(method, (n, method))
    first["plant"] = (PLANT_ONLY, "plant")
    rules = sorted(first, key=lambda m: -RULES_CPU_S.get(m, 30.0))
    examples = sorted(names, key=lambda n: -len(methods_of(cfgs[n])))
    return [first[m] for m in rules], examples


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rules, examples = plan()
    from packpilot.coldstart import marker
    from packpilot.config import load_config

    examples = [n for n in examples if not marker(load_config(EXAMPLES / f"{n}.toml")).exists()]
    if not examples:
        print("precompile: every example's kernels are compiled already", file=sys.stderr)
        return 0
    cpu = 0.0
    # spawn: a fresh interpreter per worker (no numba state inherited from this one)
    with ProcessPoolExecutor(args.jobs, mp_context=get_context("spawn")) as pool:
        for phase, jobs in (
            ("kernels", [pool.submit(_scenario, PLANT_ONLY) if m == "plant" else
                         pool.submit(_rules, ex, m) for ex, m in rules]),
            ("examples", [pool.submit(_scenario, ex) for ex in examples]),
        ):  # fmt: skip
            cpu += _wait(phase, jobs, t0)
    print(f"precompile: done in {time.perf_counter() - t0:.0f} s ({cpu:.0f} CPU s in "
          f"{args.jobs} processes)", file=sys.stderr, flush=True)  # fmt: skip
    return 0


def _wait(phase: str, jobs: list[Future[tuple[str, float]]], t0: float) -> float:
    """Wait for ``jobs``, saying each one as it ends and, in between, every ``BEAT_S`` that
    the compile goes on (never minutes of silence in ``make test``)."""
    cpu, done = 0.0, 0
    pending = set(jobs)
    while pending:
        finished, pending = wait(pending, timeout=BEAT_S, return_when=FIRST_COMPLETED)
        for job in finished:
            label, s = job.result()
            cpu += s
            done += 1
            print(f"precompile ({phase} {done}/{len(jobs)}): {label} {s:.0f} CPU s "
                  f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)  # fmt: skip
        if not finished:
            print(f"precompile ({phase} {done}/{len(jobs)}): compiling "
                  f"({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)  # fmt: skip
    return cpu


if __name__ == "__main__":
    sys.exit(main())
