"""``run`` against ``hil`` in real time in one process: the twin stepping in a thread of its
own, the BMS runtime in the caller's, each on its own monotonic clock, on a python-can
``virtual`` channel (the charger on a second one). What the real-time tests and the runtime
benchmark measure; two *processes* share a bus through ``packpilot can-hub`` instead."""

from __future__ import annotations

import threading
from typing import Any

from packpilot.config import ScenarioConfig
from packpilot.io.can.bus import open_bus
from packpilot.runtime.bms import BmsRuntime, RuntimeOptions
from packpilot.runtime.hil import Hil, run_realtime


def run_against_twin(
    cfg: ScenarioConfig, period_s: float, seconds: float, channel: str
) -> tuple[BmsRuntime, Hil, dict[str, Any]]:
    """The twin of ``cfg`` (stepping every ``period_s``) and the BMS (every ``period_s``) for
    ``seconds`` of wall time on virtual channel ``channel``; returns both, closed, and the
    BMS's metrics."""
    charger_channel = f"{channel}-charger"
    bus = open_bus("virtual", channel)
    charger = open_bus("virtual", charger_channel)
    hil = Hil(cfg, bus, charger_bus=charger, bms_period_s=period_s)
    opts = RuntimeOptions(interface="virtual", channel=channel,
                          charger_channel=charger_channel, period_s=period_s)  # fmt: skip
    bms = BmsRuntime(cfg, opts)
    stop = threading.Event()
    twin = threading.Thread(target=run_realtime, args=(hil, period_s, None, 1.0, stop))
    twin.start()
    try:
        metrics = bms.run(seconds)
    finally:
        stop.set()
        twin.join()
        bms.close()
        bus.shutdown()
        charger.shutdown()
    return bms, hil, metrics


__all__ = ["run_against_twin"]
