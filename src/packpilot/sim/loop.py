"""The closed loop: measure → core → commands → one period of physics, for P packs.

One loop serves a single run (P = 1, :class:`~packpilot.sim.runner.Runner`) and a campaign
batch (P = N): the plant stands behind a narrow port (:class:`~.plant_io.SimulatedPlant`:
``measure``, ``apply``, ``step``), so a CAN bus or a replayed log can stand where the
simulator stands: :func:`control` is everything up to the physics, and ``packpilot run``
(:mod:`packpilot.runtime.bms`) runs it against a CAN bus. Per period, for every pack at once::

    faults (plant side) → charger status over the links → sensors → faults (sensor side)
    → core.step_batch (every rule, merged, supervised) → plant gates / balancers / aux
    → charger setpoints over the links → plant.step → plant events → record

Timing: the core sees the state at ``t`` under the previous period's current (a sampling BMS)
and its commands apply to ``[t, t + dt]``: one period of actuation delay, as in hardware.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from packpilot.arena import Arenas
from packpilot.config import ScenarioConfig
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.arrays import MeasArrays
from packpilot.contract.bms import Controller, Event
from packpilot.contract.charger import ChargerLink
from packpilot.contract.record import StepSample
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core, Part
from packpilot.control.core_kernel import DIR_CMD, DIR_M
from packpilot.control.registry import REGISTRY, SAFETY
from packpilot.model import loads
from packpilot.model.pack import Interval
from packpilot.sim.cell_window import check_cell_window
from packpilot.sim.faults import FaultInjector, Silenceable, SilenceableLink
from packpilot.sim.links import ChargerLinks, PackLinks, default_links, pack_links
from packpilot.sim.metrics import Metrics
from packpilot.sim.plant_io import SimulatedPlant
from packpilot.sim.sensors import start_soc_wrong

Array = NDArray[np.float64]


LOOP_EVENT_KINDS: tuple[str, ...] = (
    "LoadUnsupplied",
    "LoadResupplied",
    "BmuBrownOut",
    "BmuRestarted",
)
"""The events the loop itself emits (the plant's load supply and the BMU's own supply from the
aux battery, ``Pack._bmu_supply``), beside the core's reason tables:
every kind needs a row in :data:`packpilot.contract.severity.EVENT_SEVERITY`."""


def build_core(cfg: ScenarioConfig, infos: Sequence[PackInfo]) -> Core:
    """The BMS a scenario enables: its methods in the listed order, then the safety layers,
    under the supervisor when any of ``[supervisor]``, ``[limits]``, ``[plausibility]``,
    ``[soc]`` is present."""
    check_cell_window(cfg, infos)
    parts: list[Part | Controller] = [
        REGISTRY[name].part(cfg.section(name), infos) for name in cfg.controller
    ]
    supervisor: SupervisorConfig | None = None
    if cfg.supervised:
        present = [name for name in SAFETY if getattr(cfg, name) is not None]
        parts += [REGISTRY[name].part(cfg.section(name), infos) for name in present]
        supervisor = cfg.supervisor or SupervisorConfig()
    return Core(infos, parts, supervisor)


def load_profile(cfg: ScenarioConfig) -> loads.LoadProfile:
    lc = cfg.load
    if lc.kind == "none":
        return loads.constant("none", 0.0)
    if lc.profile is None:
        return loads.constant(lc.kind, lc.value)
    if lc.profile.endswith(".csv"):
        return loads.from_csv(Path(lc.profile), repeat=lc.repeat)
    if lc.profile.lower().endswith((".ulg", ".bin", ".log", ".tlog")):
        from packpilot.sim.flight_load import flight_load

        return flight_load(Path(lc.profile), lc.kind, lc.repeat)
    prof = loads.builtin(lc.profile, lc.value, lc.kind)
    return loads.LoadProfile(kind=prof.kind, t_s=prof.t_s, value=prof.value, repeat=lc.repeat)


def _hold_interval(
    profile: loads.LoadProfile, x: float, value: float
) -> tuple[loads.LoadProfile, float, float, float] | None:
    """The interval around ``x`` over which ``profile.at`` holds ``value`` (``at(x)``): the
    zero-order hold row that ``at`` picks, ``[t_i, t_i+1)``; before the first row the first
    value, from the last row on 0 (a one-row profile: its value everywhere). ``None`` where
    ``at`` does more than a lookup (a repeating profile, ``none``, no rows) or ``x`` is NaN."""
    ts = profile.t_s
    n = ts.size
    if profile.repeat or profile.kind == "none" or n == 0 or x != x:
        return None
    if n == 1:
        return (profile, -math.inf, math.inf, value)
    i = int(np.searchsorted(ts, x, side="right")) - 1
    lo = float(ts[i]) if i >= 0 else -math.inf
    hi = float(ts[i + 1]) if i + 1 < n else math.inf
    return (profile, lo, hi, value)


class Demand:
    """The load demand of a scenario at time ``t_s``: 0 before ``[load] start_s``, then its
    profile (set :attr:`profile` to change what is drawn from the next lookup on). One
    definition for the closed loop and the hardware-in-the-loop twin."""

    def __init__(self, cfg: ScenarioConfig) -> None:
        self.start_s = cfg.load.start_s
        self.profile = load_profile(cfg)
        self._held: tuple[loads.LoadProfile, float, float, float] | None = None
        """(profile, lo, hi, value): ``profile.at(x) == value`` for every ``lo <= x < hi``."""

    def at(self, t_s: float) -> float:
        start = self.start_s
        if not t_s >= start:
            return 0.0
        x = t_s - start
        held = self._held
        if held is not None and held[0] is self.profile and held[1] <= x < held[2]:
            return held[3]  # still inside the hold interval of the last lookup
        value = self.profile.at(x)
        self._held = _hold_interval(self.profile, x, value)
        return value


def n_steps(cfg: ScenarioConfig) -> int:
    return math.ceil(cfg.sim.duration_s / cfg.sim.dt_s - 1e-9)


Hook = Callable[[float], None]


class PlantPort(Protocol):
    """What the BMS half of the loop needs of a plant: sensors to read into a core's
    measurements and actuators to take its commands. The simulator
    (:class:`~.plant_io.SimulatedPlant`) is one; a CAN bus
    (:class:`~packpilot.io.can.plant.CanPlant`) is another."""

    def measure(self, arenas: Arenas, m_row: int) -> None: ...

    def apply(self, arenas: Arenas, cmd_row: int) -> None: ...


def control(
    core: Core,
    plant: PlantPort,
    links: PackLinks,
    t: float,
    dt_s: float,
    faults: FaultInjector | None = None,
    hooks: Sequence[Hook] = (),
    unpowered: NDArray[np.bool_] | None = None,
) -> None:
    """The BMS half of one period, whatever stands behind the port: hooks and plant-side
    faults, charger status over the links, sensors, sensor faults, the supervised core, the
    actuators, charger setpoints over the links. :meth:`ClosedLoop.step` runs it before the
    plant's physics; the runtime (:mod:`packpilot.runtime`) runs it against a CAN bus.
    ``unpowered``: packs whose BMU is browned out (their events and charger setpoints are
    dropped, :func:`mute`)."""
    m = core.m
    for hook in hooks:
        hook(t)
    if faults is not None:
        faults.before_step(t)
    if links:
        links.poll(t, m)
    plant.measure(core.arenas, int(core.directory[DIR_M]))
    if faults is not None:
        faults.filter(m)
    core.step_batch(m, dt_s)
    if unpowered is not None:
        mute(core, unpowered)
    plant.apply(core.arenas, int(core.directory[DIR_CMD]))
    if links:
        links.send(t, core.cmd)


def mute(core: Core, packs: NDArray[np.bool_]) -> None:
    """Drop what the core decided for ``packs`` this step (BMUs that are browned out): their
    events leave the buffer and their charger is commanded off (their gates and aux DC/DC are
    held open by the plant, ``Pack.hold_unpowered``)."""
    ev, cmd = core.ev, core.cmd
    keep = 0
    for k in range(int(ev.n[0])):
        if packs[int(ev.pack[k])]:
            continue
        if keep != k:
            for arr in (ev.pack, ev.src, ev.code, ev.battery, ev.t_s, ev.val):
                arr[keep] = arr[k]
        keep += 1
    ev.n[0] = keep
    cmd.charger_set[packs] = True
    cmd.charger_enable[packs] = False
    cmd.charger_a[packs] = 0.0


def with_supply(
    kinds: list[list[str]] | None, supply: Sequence[tuple[int, Event]], n_packs: int
) -> list[list[str]] | None:
    """The core's event kinds per pack followed by the loop's own (load supply)."""
    if not supply:
        return kinds
    out = kinds or [[] for _ in range(n_packs)]
    for p, e in supply:
        out[p].append(e.kind)
    return out


class StepRecord:
    """What one period did, for the recorders: the plant's flows and the events.

    The events are rendered (messages formatted) only when read, and must be read before the
    loop steps again: the core's event buffer holds one step. A campaign never reads them.
    """

    __slots__ = ("_events", "_loop", "_n", "_supply", "iv", "k")

    def __init__(
        self, k: int, iv: Interval, loop: ClosedLoop, supply: Sequence[tuple[int, Event]] = ()
    ) -> None:
        self.k = k
        self.iv = iv
        self._loop = loop
        self._n = loop.n_stepped
        self._supply = supply
        self._events: list[list[Event]] | None = None

    @property
    def events(self) -> list[list[Event]]:
        """The step's events per pack: the core's, then the loop's own (load supply)."""
        if self._events is None:
            loop = self._loop
            if loop.n_stepped != self._n:
                raise RuntimeError(
                    f"the events of step {self.k} were read after the loop stepped again"
                )
            core = loop.core
            out = core.events() if core.ev.n[0] else [[] for _ in range(core.n_packs)]
            for p, e in self._supply:
                out[p].append(e)
            self._events = out
        return self._events


@dataclass
class ClosedLoop:
    """P packs of one scenario under one core, stepped together."""

    cfg: ScenarioConfig
    plant: SimulatedPlant
    core: Core
    links: PackLinks
    faults: FaultInjector | None = None
    hooks: Sequence[Hook] = ()
    m: MeasArrays = field(init=False)
    was_supplied: NDArray[np.bool_] = field(init=False)
    unsupplied_s: Array = field(init=False)

    def __post_init__(self) -> None:
        P = self.plant.n_packs
        self.m = self.core.m
        self.was_supplied = np.ones(P, np.bool_)
        self.unsupplied_s = np.zeros(P)
        self.n_stepped = 0
        """Periods stepped so far (a record's events are readable until the next one)."""
        self._all_supplied = True
        """Every pack was supplied at the last step (so ``unsupplied_s`` is all zero)."""
        self._all_true = np.ones(P, np.bool_).tobytes()
        self._demand = Demand(self.cfg)
        self.metrics = Metrics(P, self.plant.pack.n_strings, self.cfg.sim.dt_s)
        self._traction = np.array(self.plant.topology.traction, np.int64)

    @classmethod
    def of(
        cls,
        cfg: ScenarioConfig,
        n_packs: int = 1,
        overrides: dict[str, Any] | None = None,
        core: Core | None = None,
        links: Sequence[ChargerLink] | None = None,
        hooks: Sequence[Hook] = (),
        plant: SimulatedPlant | None = None,
    ) -> ClosedLoop:
        """The loop of ``cfg`` over ``n_packs`` packs. ``links``: one charger link per pack
        (driven by :class:`ChargerLinks`); ``None``: the scenario's, i.e. the compiled
        TC/Elcon model (:class:`~packpilot.sim.elcon.ElconLinks`) when its link is modelled
        (:func:`~packpilot.sim.links.modelled`), else :func:`default_links`."""
        if plant is None:
            plant = SimulatedPlant(cfg, n_packs, overrides)
        if core is None:
            core = build_core(cfg, plant.infos)
        chargers: PackLinks
        silenceable: list[Silenceable]
        model = pack_links(cfg, plant.pack) if links is None else None
        if model is not None:  # the compiled TC/Elcon link of every pack
            chargers, silenceable = model, [model]
        else:
            raw = default_links(cfg, plant.pack) if links is None else list(links)
            if cfg.faults:
                raw = [SilenceableLink(x) for x in raw]
            chargers, silenceable = ChargerLinks(cfg, raw), list(raw)  # type: ignore[arg-type]
        faults = FaultInjector(cfg, plant.pack, silenceable) if cfg.faults else None
        if cfg.sensors is not None and cfg.sensors.soc0_error > 0.0:
            start_soc_wrong(core, plant.pack, plant.traction, cfg.sensors.soc0_error)
        return cls(cfg, plant, core, chargers, faults, hooks)

    def demand(self, t_s: float) -> float:
        return self._demand.at(t_s)

    @property
    def profile(self) -> loads.LoadProfile:
        return self._demand.profile

    @profile.setter
    def profile(self, value: loads.LoadProfile) -> None:
        self._demand.profile = value

    def step(self, k: int, dt_s: float) -> StepRecord:
        """One period of every pack."""
        plant, core = self.plant, self.core
        t = plant.t_s
        powered = plant.pack.bmu_on
        if powered.all():
            control(core, plant, self.links, t, dt_s, self.faults, self.hooks)
        else:
            self._unpowered(t, dt_s, powered.copy())
        iv = plant.step(dt_s, np.full(plant.n_packs, self.demand(t)), self.profile.kind)
        self.n_stepped += 1
        kinds = core.event_kinds() if core.ev.n[0] else None
        if plant.pack.bmu_changed.any():
            # a BMU that powers up again boots afresh: its methods' state starts over
            core.reboot(plant.pack.bmu_changed & plant.pack.bmu_on)
        supply = self._supply_events(t, iv, dt_s)
        self.metrics.add(plant.pack, iv, self._traction, with_supply(kinds, supply, plant.n_packs))
        stop = self.cfg.sim.stop_when_unsupplied_s
        if stop is not None:
            self.metrics.stop(self.unsupplied_s >= stop, plant.pack)
        return StepRecord(k, iv, self, supply)

    def _unpowered(self, t: float, dt_s: float, powered: NDArray[np.bool_]) -> None:
        """A period in which some pack's BMU is browned out: that BMU runs nothing — no
        measurement, no decision, no event, no command, no charger heartbeat (the charger
        then times out) — so it logs no stage it cannot act on (issue #24 item 5). With no
        BMU powered the core does not step at all; in a batch with some powered, the core
        steps and the unpowered packs' events and charger setpoints are dropped (their gates
        are held open by the plant)."""
        core = self.core
        if powered.any():
            control(core, self.plant, self.links, t, dt_s, self.faults, self.hooks, ~powered)
            return
        for hook in self.hooks:
            hook(t)
        if self.faults is not None:
            self.faults.before_step(t)
        self.plant.pack.hold_unpowered()  # whatever a hook did, an unpowered BMU drives nothing
        core.ev.n[0] = 0

    @property
    def running(self) -> bool:
        """Some pack has not stopped yet."""
        return bool(self.metrics.live.any())

    def _supply_events(self, t: float, iv: Interval, dt: float) -> list[tuple[int, Event]]:
        """(pack, event) of every pack whose load supply changed at this step."""
        pack = self.plant.pack
        bmu: list[tuple[int, Event]] = []
        if pack.bmu_changed.any():
            bmu = self._bmu_events(t)
        supplied = iv.supplied
        if self._all_supplied and supplied.tobytes() == self._all_true:
            return bmu  # supply unchanged: was_supplied all True, unsupplied_s all zero
        out: list[tuple[int, Event]] = bmu
        for p in np.nonzero(supplied != self.was_supplied)[0].tolist():
            if not supplied[p]:
                data = {"bus_v": float(iv.bus_v[p]), "demand_a": float(iv.load_demand_a[p])}
                msg = "bus cannot supply the load"
                out.append((p, Event(t, LOOP_EVENT_KINDS[0], None, msg, data)))
            else:
                out.append((p, Event(t, LOOP_EVENT_KINDS[1], None, "load supplied again")))
        self.was_supplied = supplied.copy()
        self.unsupplied_s = np.where(supplied, 0.0, self.unsupplied_s + dt)
        self._all_supplied = bool(supplied.all())
        return out

    def _bmu_events(self, t: float) -> list[tuple[int, Event]]:
        """(pack, event) of every pack whose BMU browned out or restarted in the step starting
        at ``t`` (the aux voltage is read at its end; stamped like the load-supply events and
        the trace row of that step, which already shows the switches open)."""
        pack = self.plant.pack
        a = pack.aux_index
        out: list[tuple[int, Event]] = []
        if a is None:
            return out
        cut = pack.bmu_cutoff_v
        for p in np.nonzero(pack.bmu_changed)[0].tolist():
            v = float(pack.battery_v_aux()[p])
            data = {"aux_v": v, "cutoff_v": cut}
            if not pack.bmu_on[p]:
                why = f"{v:.3f} V < {cut:.3f} V" if v < cut else f"empty at {v:.3f} V"
                msg = f"BMU browned out: aux battery {why}, every switch open"
                out.append((p, Event(t, LOOP_EVENT_KINDS[2], None, msg, data)))
            else:
                dock = " (powered by the dock)" if pack.dock_supplies_bmu()[p] else ""
                msg = f"BMU restarted{dock}: aux battery {v:.3f} V"
                out.append((p, Event(t, LOOP_EVENT_KINDS[3], None, msg, data)))
        return out

    def close(self) -> None:
        self.links.close()


def sample(loop: ClosedLoop, rec: StepRecord, p: int = 0) -> StepSample:
    """Pack ``p``'s record of the step (plant truth, controller status over all strings)."""
    pack = loop.plant.pack
    iv = rec.iv
    soc, temp = pack.cell_states()
    chg, dsg = pack.effective_gates()
    starts = pack.string_cell_starts
    cap = pack.capacity_ah[p]
    rem = np.minimum.reduceat(soc[p] * cap, starts)
    full = np.minimum.reduceat(cap, starts)
    rows = np.column_stack(
        (
            iv.battery_v[p],
            iv.string_a[p],
            rem / full,
            np.maximum.reduceat(temp[p], starts),
            np.minimum.reduceat(iv.cell_v[p], starts),
            np.maximum.reduceat(iv.cell_v[p], starts),
            rem,
            full,
            chg[p],
            dsg[p],
            iv.chg_diode_a[p],
            iv.dsg_diode_a[p],
            iv.balancer_in_w[p],
        )
    )
    group = np.where(pack.group_table >= 0, iv.group_v[p][pack.group_table], np.nan)
    topo = loop.plant.topology
    status = {name: topo.spread(vals) for name, vals in loop.core.status_of(p).items()}
    return StepSample(
        step=rec.k,
        t_s=iv.t_s,
        bus_v=float(iv.bus_v[p]),
        load_demand_a=float(iv.load_demand_a[p]),
        load_a=float(iv.load_a[p]),
        charger_v=float(iv.charger_v[p]),
        charger_a=float(iv.charger_a[p]),
        battery=rows,
        group_v=group,
        status=status,  # type: ignore[arg-type]
    )


def wall() -> float:
    return time.perf_counter()


__all__ = [
    "LOOP_EVENT_KINDS",
    "ClosedLoop",
    "Demand",
    "PlantPort",
    "StepRecord",
    "build_core",
    "control",
    "load_profile",
    "n_steps",
    "sample",
]
