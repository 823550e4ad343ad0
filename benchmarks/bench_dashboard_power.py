"""What the dashboard's new panels cost (issue #28 §3-4, helper h28view): the state-of-power
panel and join view per prediction (``web/power.py:PowerPanel.compute``, the thread the page
never waits for), and ``LiveRun.status`` (what every poll and WebSocket push calls) with the
panel cached. Standalone (not in ``make bench``):

    PYTHONPATH=src python benchmarks/bench_dashboard_power.py

On ``sequencing_dual_hover`` with ``[soc]`` and ``[limits]``, 75 s: B waits in STANDBY (one
join plan per prediction). Kernels warm (one prediction first)."""

from __future__ import annotations

import statistics
import time
from typing import Any

from packpilot.config import load_config, parse_config
from packpilot.contract.record import StepSample
from packpilot.sim.runner import Runner
from packpilot.web.live import DashboardRecorder, LiveRun

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]


class Keep(DashboardRecorder):
    def __init__(self, live: LiveRun) -> None:
        super().__init__(live)
        self.samples: list[StepSample] = []

    def record(self, sample: StepSample) -> None:
        super().record(sample)
        if sample.step % 50 == 0:
            self.samples.append(sample)


def _timed(fn: Any, n: int) -> tuple[float, float]:
    """(median wall ms, median CPU ms) of ``n`` calls."""
    wall, cpu = [], []
    for _ in range(n):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(1e3 * (time.perf_counter() - w0))
        cpu.append(1e3 * (time.process_time() - c0))
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    cfg = load_config(ROOT / "examples" / "sequencing_dual_hover.toml")
    data = cfg.model_dump(mode="json")
    data["sim"].update(duration_s=75.0, progress=False)
    data.update(soc={}, limits={})
    live = LiveRun(scenario="bench", battery_names=["A", "B"])
    rec = Keep(live)
    Runner(parse_config(data), recorder=rec, progress=False).run()
    t0 = time.perf_counter()
    live.power.compute(rec.samples[0])
    first = time.perf_counter() - t0
    samples = rec.samples
    k = iter(range(10**9))
    wall, cpu = _timed(lambda: live.power.compute(samples[next(k) % len(samples)]), 60)
    live.power.latest(live._latest, final=True)
    live.power.wait(60.0)
    s_wall, s_cpu = _timed(live.status, 200)
    print(f"first prediction (kernels from the cache or compiled): {first:.2f} s")
    print(f"PowerPanel.compute, {len(samples)} steps cycled, 60 calls: median {wall:.1f} ms "
          f"wall, {cpu:.1f} ms CPU")
    print(f"LiveRun.status with the panel cached, 200 calls: median {s_wall:.2f} ms wall, "
          f"{s_cpu:.2f} ms CPU")


if __name__ == "__main__":
    main()
