"""Lock-step ``run`` against ``hil`` in one process: deterministic, as fast as the CPU goes.

Per period ``t``: the twin's nodes publish the telemetry of ``t``; the BMS runs its period at
``t`` (reads it, decides, sends commands and the charger heartbeat); the twin's switch nodes
and charger obey and the plant steps to ``t + dt``. That is the simulator's sampling and
actuation timing (a command decided at ``t`` acts over ``[t, t + dt]``), with every value
passing through the frames' quantisation on a real python-can bus (``virtual``).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from packpilot.config import ScenarioConfig
from packpilot.contract.record import Recorder
from packpilot.io.can.bus import open_bus
from packpilot.io.can.codec import REQUEST_ID
from packpilot.runtime.bms import BmsRuntime, RuntimeOptions
from packpilot.runtime.hil import Hil

_channels = itertools.count()
REQUEST_ONLY = [{"can_id": REQUEST_ID, "can_mask": 0x1FFFFFFF, "extended": True}]
"""The charger node's receive filter (where the interface filters before ``recv``)."""


@dataclass
class Lockstep:
    """The twin, the BMS, and what the plant's switches did each period."""

    hil: Hil
    bms: BmsRuntime
    chg: list[np.ndarray] = field(default_factory=list)
    dsg: list[np.ndarray] = field(default_factory=list)
    supplied: list[bool] = field(default_factory=list)
    load_j: float = 0.0
    """Energy the twin's load took from the bus (its plant's own bus voltage and load current)."""
    dock_j: float = 0.0
    """Energy the twin's charger put on the bus."""

    def step(self, dt_s: float) -> None:
        t = self.hil.t_s
        self.hil.publish()
        self.bms.step(t, dt_s)
        iv = self.hil.advance(dt_s)
        c, d = self.hil.gates()
        self.chg.append(c)
        self.dsg.append(d)
        self.supplied.append(bool(iv.supplied[0]))
        self.load_j += float(iv.bus_v[0] * iv.load_a[0]) * dt_s
        self.dock_j += float(iv.charger_v[0] * iv.charger_a[0]) * dt_s

    def close(self) -> None:
        self.bms.close()
        self.hil.bus.shutdown()
        if self.hil.charger is not None:
            self.hil.charger.bus.shutdown()


def lockstep(
    cfg: ScenarioConfig,
    opts: RuntimeOptions | None = None,
    recorder: Recorder | None = None,
    timeout_periods: int = 5,
) -> Lockstep:
    """A twin and a BMS on a fresh virtual channel, the charger on its own (as a TC/Elcon
    charger at 250 kbit/s would be); the BMS period is ``cfg.sim.dt_s``. The batteries
    ``opts.dronecan_ids`` names publish DroneCAN (as ``hil --dronecan-ids`` with the same
    list)."""
    channel = f"packpilot-hil-{next(_channels)}"
    opts = replace(opts or RuntimeOptions(), interface="virtual", channel=channel,
                   charger_channel=f"{channel}-charger", period_s=cfg.sim.dt_s,
                   bus_kwargs=())  # fmt: skip
    bus = open_bus("virtual", channel)
    charger_bus = open_bus("virtual", f"{channel}-charger")
    ids = {i: b for i, b in enumerate(opts.dronecan_ids or ()) if b >= 0}
    hil = Hil(cfg, bus, charger_bus=charger_bus, timeout_periods=timeout_periods,
              dronecan_ids=ids)  # fmt: skip
    try:
        bms = BmsRuntime(cfg, opts, recorder)
    except BaseException:
        bus.shutdown()
        charger_bus.shutdown()
        raise
    return Lockstep(hil, bms)


def run_lockstep(
    cfg: ScenarioConfig,
    steps: int,
    opts: RuntimeOptions | None = None,
    hook: Callable[[Lockstep, int], None] | None = None,
    recorder: Recorder | None = None,
) -> Lockstep:
    """``steps`` periods of ``run`` against ``hil``; the buses are shut down at the end."""
    ls = lockstep(cfg, opts, recorder)
    try:
        for k in range(steps):
            if hook is not None:
                hook(ls, k)
            ls.step(cfg.sim.dt_s)
    finally:
        ls.close()
    return ls


Transition = tuple[int, int, bool]
"""(period, battery, new state) of one switch."""


def transitions(x: np.ndarray) -> list[Transition]:
    """Every switch transition of ``x`` (periods × batteries of booleans)."""
    d = np.nonzero(x[1:] != x[:-1])
    return [(int(k) + 1, int(i), bool(x[k + 1, i])) for k, i in zip(*d, strict=True)]


def match_transitions(
    ref: np.ndarray, got: np.ndarray, periods: int
) -> tuple[list[Transition], list[Transition]]:
    """(missing, extra): the transitions of ``ref`` that ``got`` lacks and those ``got`` has
    beyond them, matched in order (same switch, same new state, at most ``periods`` apart):
    how a CAN run's switch decisions compare with the simulator's."""
    theirs = transitions(got)
    missing: list[Transition] = []
    extra: list[Transition] = []
    j = 0
    for x in transitions(ref):
        near = (k for k in range(j, len(theirs)) if theirs[k][1:] == x[1:]
                and abs(theirs[k][0] - x[0]) <= periods)  # fmt: skip
        k = next(near, None)
        if k is None:
            missing.append(x)
            continue
        extra += theirs[j:k]
        j = k + 1
    return missing, extra + theirs[j:]


__all__ = ["Lockstep", "Transition", "lockstep", "match_transitions", "run_lockstep", "transitions"]
