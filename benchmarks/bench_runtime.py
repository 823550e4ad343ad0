"""Loop timing of ``packpilot run`` against ``packpilot hil`` in real time.

Two threads of one process on a python-can ``virtual`` channel (this kernel has no vcan):
the twin (uav_mission in flight, stepping every BMS period) and the BMS runtime on its
monotonic clock, for ``--seconds`` of wall time = simulated time, at each ``--period``.
Reported per period: BMS steps, overruns and missed periods, start jitter p50/p99/max, step
time p50/p99/max (the whole BMS period: read the bus, the core, commands, publications),
telemetry faults and switch-node timeouts (both should be 0). Wall-clock figures on a 2-core
machine shared with other sessions: the neighbours show up in the tails.

``--two-processes``: ``packpilot hil`` and ``packpilot run`` as two processes through the
loopback CAN hub (``io/can/hub.py``, python-can's ``socketcand`` client; the charger on a second
channel of the hub, as above), the run's own ``--json`` timing, plus the frames per second the
hub carried over the run. The twin starts first, so its switch nodes open once each before the
BMS speaks (``switch_timeouts`` counts those too: 2 for uav_mission); ``run`` steps until its
record holds ``--seconds`` of periods, then both are stopped (SIGTERM), the twin first.

Run: ``python benchmarks/bench_runtime.py [--seconds 600] [--period 0.1 0.01]
[--two-processes]``.
"""

from __future__ import annotations

import argparse
import json
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import tomli_w

from packpilot.config import load_config
from packpilot.io.can.hub import CanHub
from packpilot.io.telemetry import samples_committed
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


def measure_two_processes(period_s: float, seconds: float) -> dict[str, Any]:
    """``hil`` and ``run`` as processes through the hub, each stepping every ``period_s``;
    the twin is stopped first, the run right after (well within the 2 s a battery may be
    silent), so neither outlives the other by a switch timeout."""
    import tomllib

    cli = [sys.executable, "-m", "packpilot.cli"]
    with tempfile.TemporaryDirectory() as tmp, CanHub("127.0.0.1", 0) as hub:
        scenario, db = Path(tmp) / "uav.toml", Path(tmp) / "run.sqlite"
        raw = tomllib.loads((ROOT / "examples" / "uav_mission.toml").read_text())
        raw["sim"]["dt_s"] = period_s
        scenario.write_text(tomli_w.dumps(raw))
        bus = ["--can-interface", "socketcand", "--can-channel", "pack",
               "--charger-channel", "charger", "--can-arg", "host=127.0.0.1",
               "--can-arg", f"port={hub.port}"]  # fmt: skip
        twin = subprocess.Popen([*cli, "hil", str(scenario), *bus, "--bms-period",
                                 str(period_s)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
        assert twin.stderr is not None
        twin.stderr.readline()  # its banner: the nodes are on the bus
        run = subprocess.Popen([*cli, "run", str(scenario), *bus, "--period", str(period_s),
                                "--db", str(db), "--json"], stdout=subprocess.PIPE,
                               text=True)  # fmt: skip
        n0, t0 = _when(lambda: samples_committed(db) > 0, hub)  # the first 50 periods are committed
        n1, t1 = _when(lambda: samples_committed(db) >= seconds / period_s, hub)
        twin.send_signal(signal.SIGTERM)
        twin_out, _ = twin.communicate()
        run.send_signal(signal.SIGTERM)
        out, _ = run.communicate()
        m = json.loads(out)
        with sqlite3.connect(db) as c:
            kinds = [r[0] for r in c.execute("select kind from events")]
    m["telemetry_faults"] = kinds.count("Fault")
    m["switch_timeouts"] = json.loads(twin_out)["switch_timeouts"]
    m["hub_frames_per_s"] = round((n1 - n0) / (t1 - t0), 1)
    m["hub_malformed"], m["hub_dropped"] = hub.stats.malformed, hub.stats.dropped
    return m


def _when(done: Any, hub: CanHub) -> tuple[int, float]:
    """(frames through the hub, monotonic time) once ``done()``."""
    while not done():
        time.sleep(0.02)
    return hub.stats.frames_in, time.monotonic()


KEYS = (
    "steps", "overruns", "missed_periods", "jitter_p50_ms", "jitter_p99_ms", "jitter_max_ms",
    "step_p50_ms", "step_p99_ms", "step_max_ms", "telemetry_faults", "switch_timeouts",
    "can_malformed", "can_babbling_periods",
)  # fmt: skip
HUB_KEYS = ("can_received", "hub_frames_per_s", "hub_malformed", "hub_dropped")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=600.0)
    ap.add_argument("--period", type=float, nargs="+", default=[0.1, 0.01])
    ap.add_argument("--two-processes", action="store_true", help="through the CAN hub")
    args = ap.parse_args()
    for p in args.period:
        if args.two_processes:
            m = measure_two_processes(p, args.seconds)
            keys = KEYS + HUB_KEYS
        else:
            m, keys = measure(p, args.seconds), KEYS
        print(json.dumps({"period_s": p, **{k: m[k] for k in keys}}), flush=True)


if __name__ == "__main__":
    main()
