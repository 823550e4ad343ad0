"""What the kernels cost to compile (issue #25 §1): per kernel, per signature, per scenario.

A fresh process with an empty ``NUMBA_CACHE_DIR`` runs one scenario for a few steps (what
``packpilot simulate EXAMPLE --duration 1`` does) while a numba event listener
(``numba:compile``, fired only for a real compile, never for a cache load) records, for every
compile of every dispatcher, its signature and the CPU time (``time.process_time``) between
the start and the end of the compile. Compiles nest (a kernel compiles the kernels it calls
while it is typed), so each row has an *inclusive* time (its callees' compiles included) and an
*exclusive* one (its own typing, lowering and LLVM optimisation only). At the end the child
lists every packpilot dispatcher and its number of signatures.

Run: ``python benchmarks/bench_compile.py [EXAMPLE ...] [--json OUT]``; ``run()`` for
``make bench`` (uav_mission only: one cold compile is minutes of CPU).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]

_CHILD = r"""
import json, sys, time
from numba.core import event as ev

rows, stack = [], []
t_start = time.process_time()

class Rec(ev.Listener):
    def on_start(self, e):
        d = e.data["dispatcher"]
        name = f"{d.py_func.__module__}.{d.py_func.__qualname__}"
        stack.append((name, str(tuple(e.data["args"])), time.process_time(),
                      time.perf_counter(), len(stack)))
    def on_end(self, e):
        name, sig, c0, w0, depth = stack.pop()
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        rows.append({"kernel": name, "sig": sig, "cpu_s": cpu, "wall_s": wall,
                     "depth": depth, "parent": stack[-1][0] if stack else None})

ev.register("numba:compile", Rec())
t0 = time.perf_counter()
from packpilot.config import load_config
from packpilot.sim.runner import Runner
cfg = load_config(sys.argv[1])
cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": float(sys.argv[2]),
                                                                "progress": False})})
res = Runner(cfg).run()
wall = time.perf_counter() - t0
cpu = time.process_time()

import numba
from numba.core.registry import CPUDispatcher
sigs = {}
for mname, mod in list(sys.modules.items()):
    if not mname.startswith("packpilot"):
        continue
    for obj in list(vars(mod).values()):
        if isinstance(obj, CPUDispatcher):
            name = f"{obj.py_func.__module__}.{obj.py_func.__qualname__}"
            sigs[name] = [str(s) for s in obj.signatures]
print("@@" + json.dumps({"rows": rows, "wall_s": wall, "cpu_s": cpu,
                          "steps": res.metrics["steps"], "signatures": sigs}))
"""


def cold(example: str, duration_s: float = 1.0) -> dict[str, Any]:
    """One cold run of ``example`` in a fresh process on a fresh, empty numba cache."""
    cache = tempfile.mkdtemp(prefix="packpilot-cold-")
    try:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYBAMM_DISABLE_TELEMETRY="true")
        env["PYTHONPATH"] = os.pathsep.join(
            [str(ROOT / "src"), *[p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p]]
        )
        path = str(ROOT / "examples" / f"{example}.toml")
        t0 = time.perf_counter()
        out = subprocess.run(
            [sys.executable, "-c", _CHILD, path, str(duration_s)],
            env=env, capture_output=True, text=True, check=False,
        )  # fmt: skip
        wall = time.perf_counter() - t0
        if out.returncode != 0:
            raise RuntimeError(out.stderr[-3000:])
        line = next(x for x in out.stdout.splitlines() if x.startswith("@@"))
        data: dict[str, Any] = json.loads(line[2:])
        data["process_wall_s"] = wall
        data["example"] = example
        return data
    finally:
        shutil.rmtree(cache, ignore_errors=True)


def per_kernel(data: dict[str, Any]) -> list[dict[str, Any]]:
    """Per kernel: signatures compiled, inclusive / exclusive CPU, compiled by whom."""
    rows = data["rows"]
    # exclusive = inclusive - the inclusive time of direct children (rows end in post-order)
    out: dict[str, dict[str, Any]] = {}
    pending: list[tuple[int, float]] = []  # (depth, inclusive) of finished rows not yet claimed
    for r in rows:
        d = r["depth"]
        kids = sum(c for dd, c in pending if dd == d + 1)
        pending = [(dd, c) for dd, c in pending if dd <= d]
        pending.append((d, r["cpu_s"]))
        excl = r["cpu_s"] - kids
        k = out.setdefault(
            r["kernel"],
            {"kernel": r["kernel"], "compiles": 0, "incl_cpu_s": 0.0, "excl_cpu_s": 0.0,
             "top_level": 0},
        )  # fmt: skip
        k["compiles"] += 1
        k["excl_cpu_s"] += excl
        k["incl_cpu_s"] += r["cpu_s"]
        k["top_level"] += d == 0
    return sorted(out.values(), key=lambda x: -x["excl_cpu_s"])


def summary(data: dict[str, Any]) -> dict[str, Any]:
    rows = data["rows"]
    top = [r for r in rows if r["depth"] == 0]
    sigs = data["signatures"]
    return {
        "example": data["example"],
        "process_cpu_s": data["cpu_s"],
        "process_wall_s": data["process_wall_s"],
        "compile_cpu_s": sum(r["cpu_s"] for r in top),
        "compiles": len(rows),
        "top_level": [(r["kernel"], round(r["cpu_s"], 2)) for r in top],
        "kernels_compiled": len({r["kernel"] for r in rows}),
        "most_signatures": sorted(((len(v), k) for k, v in sigs.items()), reverse=True)[:12],
    }


def run() -> list[dict[str, Any]]:
    """``make bench``: one cold ``uav_mission`` (every method) and one ``smart_battery`` (no
    method): compile CPU, kernels and signatures, the ten costliest kernels."""
    rows: list[dict[str, Any]] = []
    for ex in ("uav_mission", "smart_battery"):
        data = cold(ex)
        s = summary(data)
        rows.append(
            {
                "case": f"cold {ex} --duration 1: CPU of the process (empty NUMBA_CACHE_DIR)",
                "figure": s["process_cpu_s"],
                "unit": "s CPU",
                "goal": "reported",
                "verdict": "reported",
                "reference": f"{s['compile_cpu_s']:.1f} s CPU inside numba's compiles",
                "note": f"{s['compiles']} compiles of {s['kernels_compiled']} kernels; "
                f"wall {s['process_wall_s']:.0f} s",
            }
        )
        for k in per_kernel(data)[:10]:
            rows.append(
                {
                    "case": f"  {ex}: {k['kernel'].removeprefix('packpilot.')}",
                    "figure": k["excl_cpu_s"],
                    "unit": "s CPU excl.",
                    "note": f"{k['compiles']} signature(s); {k['incl_cpu_s']:.1f} s incl. callees",
                }
            )
    return rows


def main(argv: list[str]) -> int:
    out_path = None
    if "--json" in argv:
        i = argv.index("--json")
        out_path = argv[i + 1]
        argv = argv[:i] + argv[i + 2 :]
    examples = argv or ["uav_mission"]
    result = {}
    for ex in examples:
        data = cold(ex)
        result[ex] = data
        s = summary(data)
        print(json.dumps(s, indent=1), flush=True)
        for k in per_kernel(data)[:40]:
            print(
                f"  {k['excl_cpu_s']:7.2f} s excl {k['incl_cpu_s']:7.2f} s incl "
                f"{k['compiles']:3d} sig  {k['kernel']}",
                flush=True,
            )
    if out_path:
        Path(out_path).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
