"""The background compile of a first run (started by :mod:`packpilot.coldstart`).

``python -m packpilot.warmup SCENARIO STATUS MARKER LOCK`` compiles into numba's on-disk cache
every kernel a run of ``SCENARIO`` calls, in stages so that the waiting command can show
``k/n``: each method's rules (``step_packs``, compiled through a fused step of that method
alone, on a copy of the core's arenas: the same argument types as the full step, so the full
step then loads them from the cache), the fused step of the whole core, then the plant (a few
simulated steps). It writes ``k n label pid`` to ``STATUS`` after each stage, ``MARKER`` when
all is done, and holds an exclusive lock on ``LOCK`` while it runs (one at a time per cache).
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path


def _write(status: Path, k: int, n: int, label: str) -> None:
    tmp = status.with_suffix(".tmp")
    tmp.write_text(f"{k} {n} {label} {os.getpid()}\n")
    tmp.replace(status)


def compile_scenario(scenario: Path, status: Path) -> None:
    """Compile what a run of ``scenario`` calls, stage by stage (see the module docstring)."""
    from packpilot.config import load_config
    from packpilot.control.core_kernel import DIR_N_PARTS, DIR_PARTS, DIR_STRIDE, Fusion, fused
    from packpilot.sim.runner import Runner, as_core

    cfg = load_config(scenario)
    steps = 3
    sim = cfg.sim.model_copy(
        update={"duration_s": min(cfg.sim.duration_s, steps * cfg.sim.dt_s), "progress": False}
    )
    cfg = cfg.model_copy(update={"sim": sim})
    runner = Runner(cfg)
    assert runner.controller is not None
    core = as_core(runner.controller, runner.info)
    kinds = core.fusion.kinds if core.fusion is not None else ()
    n = len(kinds) + 2
    for k, kind in enumerate(kinds):
        _write(status, k, n, "rules:" + kind.step_packs.split(":")[0].split(".")[-2])
        f, i, h, c, b, lay = (a.copy() for a in core.arenas)
        d = core.directory.copy()
        for j in range(int(d[DIR_N_PARTS])):  # this method's parts only: the others skip
            row = DIR_PARTS + DIR_STRIDE * j
            d[row] = 0 if d[row] == k else -1
        fused(Fusion((kind,), False))(f, i, h, c, b, lay, d, cfg.sim.dt_s)
    if core.fused:
        _write(status, len(kinds), n, "fused-step")
        f, i, h, c, b, lay = (a.copy() for a in core.arenas)
        core.step_kernel(f, i, h, c, b, lay, core.directory.copy(), cfg.sim.dt_s)
    _write(status, n - 1, n, "plant")
    runner.run()
    _write(status, n, n, "done")


def main(argv: list[str]) -> int:
    scenario, status, marker, lock = (Path(a) for a in argv)
    import fcntl

    with open(lock, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            return 0  # another background compile runs
        with contextlib.suppress(OSError):
            os.nice(0)
        compile_scenario(scenario, Path(status))
        marker.parent.mkdir(parents=True, exist_ok=True)
        marker.write_text(str(scenario) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
