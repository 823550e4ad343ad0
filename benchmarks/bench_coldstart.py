"""Issue #25's start-up figures, with no cache of any kind (an empty ``NUMBA_CACHE_DIR`` and an
empty ``PYTHONPYCACHEPREFIX`` per command):

* ``simulate``: seconds from the command's start to its first simulated step, every example;
* ``run`` against ``hil`` through the CAN hub: seconds from ``run``'s start to its first
  switch command (``SwitchCmd``, 0x200 + i) on the bus;
* ``demo``: what ``make demo`` runs after its install step (the whole uav_mission with
  ``--db --report --plot --can-log``), wall seconds and the longest silence on stderr.

Each command starts its background compile (``packpilot.coldstart``); this script stops it
(by its pid) once the figure is taken, so the commands do not compete with each other's.

    PYTHONPATH=src python benchmarks/bench_coldstart.py [--examples a,b] [--no-demo] [--no-run]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import os
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
WRAP = """
import sys
from packpilot.coldstart import prepare
argv = sys.argv[1:]
prepare(argv)
import time
def patch(cls):
    step = cls.step
    def first(self, *a, **k):
        out = step(self, *a, **k)
        if not getattr(cls, "_bench_first", False):
            cls._bench_first = True
            print(f"BENCH-FIRST-STEP cpu {time.process_time():.2f}", file=sys.stderr, flush=True)
        return out
    cls.step = first
from packpilot.sim import loop
patch(loop.ClosedLoop)
if argv[0] == "run":
    from packpilot.runtime import bms
    patch(bms.BmsRuntime)
sys.argv = ["packpilot", *argv]
from packpilot.cli import main
main()
"""


def _env(tmp: Path) -> dict[str, str]:
    (tmp / "numba").mkdir(exist_ok=True)
    (tmp / "pyc").mkdir(exist_ok=True)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp / "numba"),
           "PYTHONPYCACHEPREFIX": str(tmp / "pyc"), "PYTHONPATH": str(ROOT / "src")}  # fmt: skip
    env.pop("NUMBA_DISABLE_JIT", None)
    env.pop("PACKPILOT_START", None)
    return env


def _stop_child(tmp: Path) -> None:
    status = tmp / "numba" / "packpilot-compiled" / "status"
    with contextlib.suppress(OSError, ValueError, IndexError):
        os.kill(int(status.read_text().split()[3]), signal.SIGTERM)


class _Lines:
    """A process's stderr lines with the time each arrived (s since ``t0``)."""

    def __init__(self, proc: subprocess.Popen[str], t0: float) -> None:
        self.lines: list[tuple[float, str]] = []
        self.t0 = t0
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            self.lines.append((time.perf_counter() - self.t0, line.rstrip()))

    def first(self, text: str) -> float | None:
        return next((t for t, line in self.lines if text in line), None)

    def join(self) -> None:
        self._thread.join(timeout=10)

    def max_gap(self, until: float) -> float:
        times = [0.0] + [t for t, _ in self.lines] + [until]
        return max(b - a for a, b in itertools.pairwise(times))


def _cpu(lines: _Lines) -> float | None:
    """The command's own CPU seconds at its first step (what a free core would take)."""
    return next((float(text.split()[-1]) for _, text in lines.lines
                 if text.startswith("BENCH-FIRST-STEP")), None)  # fmt: skip


def first_step(name: str) -> dict[str, object]:
    """``simulate NAME`` for 10 steps, cold: seconds to the first step, the mode it chose."""
    sys.path.insert(0, str(ROOT / "src"))
    from packpilot.config import load_config

    cfg = load_config(ROOT / "examples" / f"{name}.toml")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cmd = [sys.executable, "-c", WRAP, "simulate", str(ROOT / "examples" / f"{name}.toml"),
               "--duration", f"{10 * cfg.sim.dt_s:g}", "--json"]  # fmt: skip
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True, env=_env(tmp), cwd=ROOT)  # fmt: skip
        lines = _Lines(proc, t0)
        try:
            proc.wait(timeout=900)
        finally:
            _stop_child(tmp)
            proc.kill()
        lines.join()
        mode = "interpreted" if lines.first("running interpreted") is not None else "compiled"
        return {"example": name, "first_step_s": lines.first("BENCH-FIRST-STEP"), "mode": mode,
                "first_step_cpu_s": _cpu(lines), "exit": proc.returncode}  # fmt: skip


def run_first_switch(example: str = "uav_mission") -> dict[str, object]:
    """``hil`` then ``run`` through the loopback CAN hub, each with its own empty caches:
    seconds from ``run``'s start to the first switch command it sends."""
    sys.path.insert(0, str(ROOT / "src"))
    from packpilot.io.can.bus import open_bus
    from packpilot.io.can.hub import CanHub

    out: dict[str, object] = {"example": example}
    with CanHub("127.0.0.1", 0) as hub, tempfile.TemporaryDirectory() as d1, \
            tempfile.TemporaryDirectory() as d2:  # fmt: skip
        bus_args = ["--can-interface", "socketcand", "--can-channel", "pack",
                    "--can-arg", "host=127.0.0.1", "--can-arg", f"port={hub.port}"]  # fmt: skip
        t0 = time.perf_counter()
        twin = subprocess.Popen(
            [sys.executable, "-m", "packpilot.cli", "hil", example, *bus_args],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env=_env(Path(d1)),
            cwd=ROOT,
        )
        twin_lines = _Lines(twin, t0)
        run = None
        listener = open_bus("socketcand", "pack", host="127.0.0.1", port=hub.port)
        try:
            while twin_lines.first("packpilot hil:") is None and twin.poll() is None:
                time.sleep(0.05)
            out["hil_ready_s"] = twin_lines.first("packpilot hil:")
            while listener.recv(0.0) is not None:
                pass
            t1 = time.perf_counter()
            run = subprocess.Popen([sys.executable, "-c", WRAP, "run", example, *bus_args,
                                    "--json"],
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                   env=_env(Path(d2)), cwd=ROOT)  # fmt: skip
            run_lines = _Lines(run, t1)
            deadline = t1 + 300
            while time.perf_counter() < deadline and run.poll() is None:
                msg = listener.recv(0.5)
                if msg is not None and 0x200 <= msg.arbitration_id < 0x210:
                    out["run_first_switch_s"] = time.perf_counter() - t1
                    break
            time.sleep(10.0)  # 100 periods, then stop
            out["run_mode"] = (
                "interpreted" if run_lines.first("running interpreted") is not None else "compiled"
            )
            out["run_first_step_cpu_s"] = _cpu(run_lines)
        finally:
            listener.shutdown()
            for proc, tmp in ((run, Path(d2)), (twin, Path(d1))):
                _stop_child(tmp)
                if proc is not None:
                    proc.send_signal(signal.SIGTERM)
                    with contextlib.suppress(subprocess.TimeoutExpired):
                        text = proc.communicate(timeout=30)[0] if proc is run else ""
                        with contextlib.suppress(ValueError, IndexError):
                            m = json.loads(text[text.index("{") :])
                            keys = ("periods", "step_p50_ms", "step_p99_ms", "overruns")
                            out["run_timing"] = {k: m.get(k) for k in keys}
                    proc.kill()
    return out


def demo() -> dict[str, object]:
    """What ``make demo`` runs after installing, cold: wall s, first step, longest silence."""
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cmd = [sys.executable, "-c", WRAP, "simulate", str(ROOT / "examples/uav_mission.toml"),
               "--progress", "--db", str(tmp / "demo.sqlite"), "--report", str(tmp / "r.html"),
               "--plot", str(tmp / "demo.png"), "--can-log", str(tmp / "demo_can.blf"),
               "--json"]  # fmt: skip
        cpu0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                env=_env(tmp), cwd=ROOT)  # fmt: skip
        lines = _Lines(proc, t0)
        try:
            proc.wait(timeout=3600)  # stderr is read by ``lines``; stdout is one JSON line
            assert proc.stdout is not None
            stdout = proc.stdout.read()
        finally:
            _stop_child(tmp)
        wall = time.perf_counter() - t0
        cpu1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime
        lines.join()
        summary = json.loads(stdout) if proc.returncode == 0 else {}
        return {"wall_s": round(wall, 1), "first_step_s": lines.first("BENCH-FIRST-STEP"),
                "first_step_cpu_s": _cpu(lines), "cpu_s": round(cpu, 1),
                "max_silence_s": round(lines.max_gap(wall), 2), "exit": proc.returncode,
                "wall_time_s": summary.get("wall_time_s"),
                "build_time_s": summary.get("build_time_s")}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--examples", help="comma-separated (default: every example)")
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--no-run", action="store_true")
    ap.add_argument("--no-simulate", action="store_true")
    args = ap.parse_args()
    names = args.examples.split(",") if args.examples else sorted(
        p.stem for p in (ROOT / "examples").glob("*.toml"))  # fmt: skip
    results: dict[str, object] = {"simulate": []}
    for name in [] if args.no_simulate else names:
        r = first_step(name)
        print(f"simulate {name:28s} first step {r['first_step_s']:.1f} s wall,"
              f" {r['first_step_cpu_s']} s CPU ({r['mode']})", flush=True)  # fmt: skip
        results["simulate"].append(r)  # type: ignore[attr-defined]
    if not args.no_run:
        r2 = run_first_switch()
        print(f"run (hil, CAN hub): {r2}", flush=True)
        results["run"] = r2
    if not args.no_demo:
        r3 = demo()
        print(f"demo (uav_mission, make demo's command): {r3}", flush=True)
        results["demo"] = r3
    print(json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
