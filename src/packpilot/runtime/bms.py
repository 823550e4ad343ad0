"""``packpilot run``: the BMS as a long-running process on a CAN bus.

The same loop as the simulator's (:func:`packpilot.sim.loop.control`: links → sensors → the
supervised core → actuators → links), with :class:`~packpilot.io.can.plant.CanPlant` standing
where :class:`~packpilot.sim.plant_io.SimulatedPlant` stands and a
:class:`~packpilot.io.can.link.CanChargerLink` client (no emulator) as the charger link.
Each period on a monotonic clock: read the latest telemetry, run the core, send the switch
commands, command the charger, publish the pack as one battery (every second), record.

Time: ``t`` is seconds since the start on the monotonic clock, and ``dt`` the time actually
elapsed since the previous period (a late period integrates what really passed). A lock-step
driver (:func:`packpilot.runtime.lockstep.run_lockstep`) calls :meth:`BmsRuntime.step` with
simulated time instead, which is how the tests compare it with ``simulate``.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig
from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Recorder, StepSample
from packpilot.contract.topology import PackInfo
from packpilot.errors import ConfigError
from packpilot.io.can.bus import FrameLog, open_bus
from packpilot.io.can.codec import STATUS_ID
from packpilot.io.can.dbcgen import MAX_BATTERIES, MAX_GROUPS
from packpilot.io.can.link import CanChargerLink
from packpilot.io.can.plant import CanPlant, battery_map
from packpilot.io.can.shared import SharedBus
from packpilot.runtime.publish import Publisher
from packpilot.runtime.timing import LoopTiming
from packpilot.sim.links import ChargerLinks
from packpilot.sim.loop import build_core, control
from packpilot.sim.plant_io import SimulatedPlant, topology

STANDARD_ONLY = [{"can_id": 0, "can_mask": 0, "extended": False}]
"""python-can filter: every 11-bit frame (the PackPilot and Pylontech frames), no 29-bit."""
CHARGER_ONLY = [{"can_id": STATUS_ID, "can_mask": 0x1FFFFFFF, "extended": True}]


SOFTWARE_FILTERED = frozenset({"virtual", "socketcand"})
"""Interfaces whose receive filters python-can applies in software, after ``recv``."""


def filters(interface: str, which: list[dict[str, Any]]) -> dict[str, Any]:
    """Receive filters where the interface applies them before ``recv`` (socketcan: in the
    kernel). python-can's software filtering (``virtual``, ``socketcand``) gives up a
    ``recv(timeout=0)`` at the first frame it filters out, which would leave the rest of the
    queue unread for a period, so there the receivers classify and count every frame
    themselves."""
    return {} if interface in SOFTWARE_FILTERED else {"can_filters": which}


@dataclass(frozen=True)
class RuntimeOptions:
    """How ``run`` talks to the pack (CLI options; the scenario says what the pack is)."""

    interface: str = "virtual"
    channel: str = "packpilot"
    charger_channel: str | None = None
    """The charger's bus, if not the batteries' (TC/Elcon chargers run at 250 kbit/s)."""
    period_s: float = 0.1
    log_path: Path | None = None
    node_id: int = 100
    """DroneCAN node id of the BMS."""
    publish: bool = True
    platform_timeout_s: float = 1.0
    babble_factor: int = 4
    dronecan_ids: tuple[int, ...] | None = None
    """DroneCAN ``battery_id`` of each battery of ``[[pack.batteries]]`` in order that reports
    by BatteryInfo + BatteryInfoAux (-1: by the PackPilot frames); None: all PackPilot."""
    startup_timeout_s: float = 2.0
    """How long ``run`` waits for every battery's first telemetry before its first period."""
    allow_unmonitored: bool = False
    """Run without ``[plausibility]`` (then stale telemetry is NOT detected): bench use."""
    bus_kwargs: tuple[tuple[str, Any], ...] = ()
    """python-can interface options (``--can-arg``) for every bus ``run`` opens."""


def configured_infos(cfg: ScenarioConfig) -> list[PackInfo]:
    """What the BMS is configured with: the scenario's batteries and cell sets (capacities, the
    OCV table), as the simulator derives them — the facts, not the physics."""
    return SimulatedPlant(cfg, 1).infos


def check_runtime(cfg: ScenarioConfig, opts: RuntimeOptions) -> None:
    """Refuse what the runtime cannot serve safely, with a one-line error."""
    bats = cfg.pack.batteries
    if len(bats) > MAX_BATTERIES:
        raise ConfigError(f"pack.batteries: {len(bats)} batteries, the CAN map has {MAX_BATTERIES}")
    for k, b in enumerate(bats):
        if b.series_groups > MAX_GROUPS:
            raise ConfigError(
                f"pack.batteries.{k}.series_groups: {b.series_groups}, frames carry {MAX_GROUPS}"
            )
    if cfg.plausibility is None and not opts.allow_unmonitored:
        raise ConfigError(
            "plausibility: `run` needs a [plausibility] section, which turns stale or lost "
            "telemetry into a fault and a safe state (or pass --allow-unmonitored)"
        )
    ids = opts.dronecan_ids
    if ids is not None:
        used = [b for b in ids if b >= 0]
        if len(ids) != len(bats) or len(set(used)) != len(used) or any(b > 255 for b in ids):
            raise ConfigError(
                f"--dronecan-ids {','.join(map(str, ids))}: one battery_id 0..255 (or -1) per "
                f"battery of [[pack.batteries]] ({len(bats)}), no id twice"
            )
    if not (math.isfinite(opts.period_s) and 0.001 <= opts.period_s <= 10.0):
        raise ConfigError(f"--period: {opts.period_s} s, need 0.001 .. 10 s")


class BmsRuntime:
    """The BMS of one pack over CAN: one period per :meth:`step`."""

    def __init__(
        self, cfg: ScenarioConfig, opts: RuntimeOptions, recorder: Recorder | None = None
    ) -> None:
        check_runtime(cfg, opts)
        self.cfg, self.opts, self.recorder = cfg, opts, recorder
        self.topology = topology(cfg)
        infos = configured_infos(cfg)
        self.core = build_core(cfg, infos)
        self.log = FrameLog(opts.log_path) if opts.log_path is not None else None
        kw = dict(opts.bus_kwargs)
        own = cfg.charger.present and opts.charger_channel not in (None, opts.channel)
        """The charger on its own bus (else it shares the batteries' bus through a port)."""
        wanted = STANDARD_ONLY if own or not cfg.charger.present else STANDARD_ONLY + CHARGER_ONLY
        raw = open_bus(opts.interface, opts.channel, **filters(opts.interface, wanted), **kw)
        self.shared = SharedBus(raw, self.log)
        charger_port = None
        if cfg.charger.present and not own:
            charger_port = self.shared.port(_is_charger_status)
        port = self.shared.port()  # everything else: the batteries, the platform, intruders
        bats = cfg.pack.batteries
        bmap = battery_map(self.topology.names, self.topology.roles,
                           [b.series_groups for b in bats])  # fmt: skip
        self.plant = CanPlant(
            port, bmap, balancers=cfg.balancer.present,
            babble_factor=opts.babble_factor, platform_timeout_s=opts.platform_timeout_s,
            period_s=opts.period_s,
            stale_s=cfg.plausibility.max_sample_age_s if cfg.plausibility else math.inf,
            dronecan_ids={bid: i for i, bid in enumerate(opts.dronecan_ids or ()) if bid >= 0},
            capacity_ah=float(np.nansum(infos[0].capacity_ah)), charger=cfg.charger.present,
        )  # fmt: skip
        self.charger: CanChargerLink | None = None
        links: list[Any] = []
        if cfg.charger.present:
            self.charger = CanChargerLink(
                None, interface=opts.interface, channel=opts.charger_channel or opts.channel,
                heartbeat_timeout_s=cfg.charger.heartbeat_timeout_s,
                rating=(cfg.charger.rated_v, cfg.charger.rated_a),
                bus_kwargs={**filters(opts.interface, CHARGER_ONLY), **kw}, bus=charger_port,
            )  # fmt: skip
            if own:
                self.charger.client.log = self.log
            links.append(self.charger)
        self.links = ChargerLinks(cfg, links)
        self.publisher = Publisher(cfg, self.core, infos[0], port, opts.node_id)
        self.timing = LoopTiming(opts.period_s)
        self.events: list[Event] = []
        self.k = 0
        self.run_id: int | None = None
        if recorder is not None:
            self.run_id = recorder.start(cfg.model_dump(mode="json"), list(self.topology.names))

    # ------------------------------------------------------------------ one period
    def step(self, t: float, dt_s: float) -> list[Event]:
        """One period at time ``t``: the loop's BMS half, the publications, the record."""
        self.plant.t_s = self.shared.t_s = t
        self.shared.pump()
        control(self.core, self.plant, self.links, t, dt_s)
        if self.opts.publish:
            self.publisher.maybe_publish(t)
        events = self.core.events()[0] if self.core.ev.n[0] else []
        if self.plant.detections:
            events = [*self._detected(), *events]
        if events:
            self.events.extend(events)
        if self.recorder is not None:
            self.recorder.record(self.sample(t))
            if events:
                self.recorder.record_events(events)
        self.k += 1
        return events

    def _detected(self) -> list[Event]:
        """What the CAN port detected this period (telemetry sequence, presence, dock), as
        events of the runtime (``battery``: the traction index, None for the pack)."""
        traction = self.plant.map.traction
        out = []
        for d in self.plant.detections:
            k = traction.index(d.battery) if d.battery in traction else None
            out.append(Event(d.t_s, d.kind, k, d.message, {"node": -1 if d.battery is None
                                                          else d.battery}))  # fmt: skip
        self.plant.detections.clear()
        return out

    def sample(self, t: float) -> StepSample:
        """What the BMS measured this period, as the recorders' unit of telemetry (the
        simulator records plant truth; a real pack has only its telemetry)."""
        m, topo = self.core.m, self.topology
        n = len(topo.names)
        rows = np.full((n, len(BATTERY_CHANNELS)), np.nan)
        g = m.bat.group_v.shape[2]
        groups = np.full((n, g), np.nan)
        for k, s in enumerate(topo.traction):
            rows[s] = _row(m.bat, k)
            groups[s] = m.bat.group_v[0, k]
        if topo.aux is not None:
            rows[topo.aux] = _row(m.aux, 0)
            groups[topo.aux, : m.aux.group_v.shape[2]] = m.aux.group_v[0, 0, :g]
        status = {k: topo.spread(v) for k, v in self.core.status_of(0).items()}
        ch = m.charger
        return StepSample(
            step=self.k, t_s=t, bus_v=float(m.bus_v[0]), load_demand_a=math.nan,
            load_a=float(m.load_current_a[0]), charger_v=float(ch.output_v[0]),
            charger_a=float(ch.output_a[0]), battery=rows, group_v=groups,
            status=status,  # type: ignore[arg-type]
        )  # fmt: skip

    # ------------------------------------------------------------------ real time
    def run(
        self,
        duration_s: float | None = None,
        stop: threading.Event | None = None,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> dict[str, Any]:
        """Run on the monotonic clock until ``duration_s`` or ``stop``; returns the metrics."""
        period = self.opts.period_s
        self.warm_up()
        self.wait_for_telemetry(self.opts.startup_timeout_s, clock, sleep)
        self.plant.wall = time.time  # from now on a frame's age counts from its timestamp
        t0 = clock()
        due = t0
        prev: float | None = None
        status = "ok"
        try:
            while (stop is None or not stop.is_set()) and (
                duration_s is None or due - t0 < duration_s - 1e-9
            ):
                now = clock()
                if now < due:
                    sleep(due - now)
                start = clock()
                t = start - t0
                self.step(t, period if prev is None else t - prev)
                prev = t
                end = clock()
                due = self.timing.add(due, start, end)
        except KeyboardInterrupt:
            status = "interrupted"
            raise
        except BaseException:
            status = "error"
            raise
        finally:
            metrics = self.metrics()
            if self.recorder is not None:
                self.recorder.finish(metrics, status=status)
        return metrics

    def warm_up(self) -> None:
        """Pay the one-time costs before the clock starts: loading the compiled core (one step
        on a *copy* of its arenas: the real state is untouched), the state-of-power kernels,
        DSDL parsing, codec caches (frames built, not sent)."""
        core = self.core
        if core.fused:
            f, i, h, c, b, lay = (a.copy() for a in core.arenas)
            core.step_kernel(f, i, h, c, b, lay, core.directory.copy(), self.opts.period_s)
        self.publisher.warm_up()
        self.publisher.frames(0.0)
        self.publisher.transfer_id = 0

    def wait_for_telemetry(
        self,
        timeout_s: float,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> bool:
        """Read the bus until every battery has reported once or ``timeout_s`` passed, so the
        first period does not judge batteries that have not had time to speak. Frames read
        here count as received at t = 0; a battery still silent then starts as never heard
        (NaN, infinitely old: a fault at once)."""
        end = clock() + timeout_s
        self.plant.t_s = self.shared.t_s = 0.0
        while True:
            self.shared.pump()
            self.plant.poll()
            if self.plant.complete():
                return True
            if clock() >= end:
                return False
            sleep(min(0.005, self.opts.period_s))

    def metrics(self) -> dict[str, Any]:
        c = self.plant.counters
        out: dict[str, Any] = {"steps": self.k, **self.timing.summary()}
        out.update({f"can_{k}": getattr(c, k) for k in ("sent", "received", "malformed",
                                                        "unexpected", "send_errors")})  # fmt: skip
        out["can_babbling_periods"] = self.plant.babbled
        fr = self.plant.freshness
        names = ("duplicates", "out_of_order", "resyncs", "suspect", "late", "present_glitches",
                 "dock_rejected")  # fmt: skip
        out.update({f"can_{k}": getattr(fr, k) for k in names})
        out.update(self.plant.ages.summary())
        out["published_frames"] = self.publisher.sent
        if self.charger is not None:
            cc = self.charger.client.counters
            out["charger_frames_sent"] = cc.sent
            out["charger_frames_received"] = cc.received
        out["events"] = len(self.events)
        return out

    def close(self) -> None:
        if self.charger is not None:
            self.charger.close()
        if self.publisher.worker is not None:
            self.publisher.worker.close()
        self.shared.shutdown()
        if self.log is not None:
            self.log.close()
            self.log = None


def _is_charger_status(msg: Any) -> bool:
    return bool(msg.is_extended_id and msg.arbitration_id == STATUS_ID)


def _row(bat: Any, k: int) -> np.ndarray:
    return np.array([
        bat.voltage_v[0, k], bat.current_a[0, k], bat.soc[0, k], bat.temp_c[0, k],
        bat.min_cell_v[0, k], bat.max_cell_v[0, k], bat.remaining_capacity_ah[0, k],
        bat.full_capacity_ah[0, k], float(bat.sw_chg[0, k]), float(bat.sw_dsg[0, k]),
        math.nan, math.nan, math.nan,
    ])  # fmt: skip


__all__ = ["BmsRuntime", "RuntimeOptions", "check_runtime", "configured_infos"]
