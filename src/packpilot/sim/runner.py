"""The closed loop: measure → controller.step → commands → plant step. Wiring lives here.

The runner is the imperative shell around the pure controllers: it owns the clock (simulated
time only), applies commands to the plant, turns plant happenings into events (the load going
unsupplied), streams every step to a recorder, and summarises the run into metrics.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from packpilot.config import METHOD_SECTIONS, ScenarioConfig, validate_section
from packpilot.control.types import (
    ChargerCommand,
    ChargerStatus,
    Commands,
    ComposedController,
    Controller,
    ControlOutput,
    Event,
    NullController,
    PackInfo,
)
from packpilot.model import loads
from packpilot.model.charger import ChargerView
from packpilot.model.pack import Interval, Pack
from packpilot.sim.faults import FaultInjector, SilenceableLink
from packpilot.sim.result import BATTERY_CHANNELS, Recorder, Result, StepSample, Trace
from packpilot.sim.sensors import measure, pack_info, traction_indices

CONTROLLER_CLASSES: dict[str, str] = {
    "protection": "packpilot.control.protection:ProtectionController",
    "sequencing": "packpilot.control.sequencing:SequencingController",
    "charging": "packpilot.control.charging:ChargingController",
    "equalization": "packpilot.control.equalization:EqualizationController",
}


SAFETY_CLASSES: dict[str, str] = {
    "limits": "packpilot.control.limits:LimitsController",
    "plausibility": "packpilot.control.plausibility:PlausibilityMonitor",
}


def _instantiate(path: str, section: str, cfg: ScenarioConfig, info: PackInfo) -> Controller:
    mod_name, cls_name = path.split(":")
    cls = getattr(importlib.import_module(mod_name), cls_name)
    section_cfg = validate_section(section, getattr(cfg, section), "<config>")
    ctrl: Controller = cls(section_cfg, info)
    return ctrl


def build_controller(cfg: ScenarioConfig, info: PackInfo, pack: Pack | None = None) -> Controller:
    """Compose the methods the scenario enables, in the order it lists them.

    With a ``[supervisor]``, ``[limits]`` or ``[plausibility]`` section the methods run under
    the :class:`~packpilot.control.supervisor.Supervisor` with the enabled safety layers.
    """
    parts = [_instantiate(CONTROLLER_CLASSES[s], s, cfg, info) for s in cfg.controller]
    if cfg.supervised:
        from packpilot.control.supervisor import Supervisor

        safety = [
            _instantiate(path, s, cfg, info)
            for s, path in SAFETY_CLASSES.items()
            if getattr(cfg, s) is not None
        ]
        if cfg.soc is not None and pack is not None:
            safety.append(_soc_estimator(cfg, info, pack))
        sup_cfg = validate_section("supervisor", cfg.supervisor, "<config>")
        return Supervisor(sup_cfg, info, methods=parts, safety=safety)  # type: ignore[arg-type]
    if not parts:
        return NullController()
    if len(parts) == 1:
        return parts[0]
    return ComposedController(parts)


assert set(CONTROLLER_CLASSES) == set(METHOD_SECTIONS)


def _soc_estimator(cfg: ScenarioConfig, info: PackInfo, pack: Pack) -> Controller:
    """The BMS's own SOC estimate, given the OCV table of the traction cells as data."""
    from packpilot.control.soc import SocEstimator

    soc_cfg = validate_section("soc", cfg.soc, "<config>")
    first_cell = int(np.nonzero(~pack.is_aux[pack.cell_string])[0][0])
    params = next(b.params for b in pack.banks if np.any(b.idx % pack.n_cells == first_cell))
    est = SocEstimator.from_config(
        soc_cfg,  # type: ignore[arg-type]
        info,
        params.ocv_soc,
        params.ocv_table_v,
    )
    return est


def apply_commands(pack: Pack, traction: Sequence[int], cmds: Sequence[Commands | None]) -> None:
    """Apply one controller's commands to each pack of the plant (``cmds[p]``; ``None`` or a
    ``None`` field leaves that pack's switch, balancer or aux setting as it is). The charger
    setpoint is not a plant input: the runner sends it over its link."""
    chg = pack.chg_on.copy()
    dsg = pack.dsg_on.copy()
    bal: np.ndarray[Any, np.dtype[np.float64]] | None = None
    aux_a: np.ndarray[Any, np.dtype[np.float64]] | None = None
    for p, cmd in enumerate(cmds):
        if cmd is None:
            continue
        for k, i in enumerate(traction):
            if k < len(cmd.chg_on) and cmd.chg_on[k] is not None:
                chg[p, i] = bool(cmd.chg_on[k])
            if k < len(cmd.dsg_on) and cmd.dsg_on[k] is not None:
                dsg[p, i] = bool(cmd.dsg_on[k])
        if pack.aux_index is not None and cmd.aux_relay_closed is not None:
            chg[p, pack.aux_index] = dsg[p, pack.aux_index] = cmd.aux_relay_closed
        if cmd.balancer_a is not None:
            if bal is None:
                bal = pack.balancer_a.copy()
            row = np.zeros(pack.n_groups)
            for k, i in enumerate(traction):
                if k < len(cmd.balancer_a):
                    g0 = int(pack.string_group_starts[i])
                    vals = cmd.balancer_a[k][: pack.groups_per_string[i]]
                    row[g0 : g0 + len(vals)] = vals
            bal[p] = row
        if cmd.aux_charge_a is not None:
            if aux_a is None:
                aux_a = pack.aux_charge_a.copy()
            aux_a[p] = cmd.aux_charge_a
    pack.set_gates(chg, dsg)
    if bal is not None:
        pack.set_balancer(bal)
    if aux_a is not None:
        pack.set_aux_charge(aux_a)


class ChargerLink(Protocol):
    """How charger setpoints reach the dock and its status comes back (direct or CAN)."""

    def send(self, command: ChargerCommand, t_s: float) -> None: ...

    def poll(self, t_s: float) -> ChargerStatus | None: ...


@dataclass
class DirectChargerLink:
    """Setpoints written straight into the plant's charger: a request every control period."""

    charger: ChargerView

    def send(self, command: ChargerCommand, t_s: float) -> None:
        self.charger.request(command.voltage_v, command.current_a, command.enable, t_s)

    def poll(self, t_s: float) -> ChargerStatus | None:
        v, a = self.charger.output()
        f = self.charger.fault_flags
        return ChargerStatus(output_v=v, output_a=a, online=True, **f)


def _can_link(cfg: ScenarioConfig, pack: Pack) -> ChargerLink:
    """Charger setpoints over python-can: an emulated dock on a virtual bus, or real hardware."""
    from packpilot.io.can.link import CanChargerLink

    assert cfg.can is not None
    emulate = cfg.can.interface == "virtual"
    return CanChargerLink(
        pack.charger.view(0) if emulate else None,
        interface=cfg.can.interface,
        channel=cfg.can.channel,
        log_path=cfg.can.log,
        heartbeat_timeout_s=cfg.charger.heartbeat_timeout_s,
    )


def load_profile(cfg: ScenarioConfig) -> loads.LoadProfile:
    lc = cfg.load
    if lc.kind == "none":
        return loads.constant("none", 0.0)
    if lc.profile is None:
        return loads.constant(lc.kind, lc.value)
    if lc.profile.endswith(".csv"):
        prof = loads.from_csv(Path(lc.profile), repeat=lc.repeat)
        return prof
    prof = loads.builtin(lc.profile, lc.value, lc.kind)
    return loads.LoadProfile(kind=prof.kind, t_s=prof.t_s, value=prof.value, repeat=lc.repeat)


@dataclass
class Runner:
    """One closed-loop run of one pack."""

    cfg: ScenarioConfig
    controller: Controller | None = None
    recorder: Recorder | None = None
    charger_link: ChargerLink | None = None
    progress: bool | None = None
    hooks: Sequence[Callable[[Runner, float], None]] = ()
    """Called before each control step with (runner, t_s): fault injection, hot plugs."""
    pack_overrides: Mapping[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for ``Pack(cfg, ...)`` (campaign draws: ``capacity_scale``,
    ``r_scale``, ``soc_offset``, ``ambient_c``)."""
    pack: Pack = field(init=False)
    info: PackInfo = field(init=False)

    def __post_init__(self) -> None:
        self.pack = Pack(self.cfg, **self.pack_overrides)
        self.info = pack_info(self.pack)
        if self.controller is None:
            self.controller = build_controller(self.cfg, self.info, self.pack)
        if self.charger_link is None and self.cfg.charger.present:
            if self.cfg.can is not None:
                self.charger_link = _can_link(self.cfg, self.pack)
            else:
                self.charger_link = DirectChargerLink(self.pack.charger.view(0))
        self.profile = load_profile(self.cfg)
        self.traction = traction_indices(self.pack)
        self.faults: FaultInjector | None = None
        if self.cfg.faults:
            link = SilenceableLink(self.charger_link) if self.charger_link is not None else None
            self.charger_link = link
            self.faults = FaultInjector(self.cfg, self.pack, link)
        self.events: list[Event] = []
        self.samples: list[StepSample] = []

    # ----------------------------------------------------------------- commands
    def apply(self, cmd: Commands, t_s: float) -> None:
        apply_commands(self.pack, self.traction, [cmd])
        if self.charger_link is not None:
            c = self.cfg.charger
            command = cmd.charger or ChargerCommand(c.voltage_v, c.current_a, c.enable)
            self.charger_link.send(command, t_s)

    # ----------------------------------------------------------------- loop
    def run(self) -> Result:
        cfg = self.cfg
        dt = cfg.sim.dt_s
        n_steps = math.ceil(cfg.sim.duration_s / dt - 1e-9)
        assert self.controller is not None
        controller = self.controller
        if self.recorder is not None:
            self.run_id: int | None = self.recorder.start(
                cfg.model_dump(mode="json"), self.pack.names
            )
        else:
            self.run_id = None
        wall0 = time.perf_counter()
        unsupplied_s = 0.0
        was_supplied = True
        status = "ok"
        bar = _Progress(
            n_steps, enabled=cfg.sim.progress if self.progress is None else self.progress
        )
        try:
            charger_status: ChargerStatus | None = None
            for k in range(n_steps):
                t = self.pack.t_s
                for hook in self.hooks:
                    hook(self, t)
                if self.faults is not None:
                    self.faults.before_step(self, t)
                if self.charger_link is not None:
                    charger_status = self._charger_status(t, charger_status)
                meas = measure(self.pack, charger_status)
                if self.faults is not None:
                    meas = self.faults.filter(meas)
                out: ControlOutput = controller.step(meas, dt)
                self.apply(out.commands, t)
                value = self.profile.at(t - cfg.load.start_s) if t >= cfg.load.start_s else 0.0
                iv = self.pack.step(dt, self.profile.kind, np.array([value]))
                new_events = list(out.events)
                supplied = bool(iv.supplied[0])
                if not supplied and was_supplied:
                    new_events.append(
                        Event(
                            t,
                            "LoadUnsupplied",
                            None,
                            "bus cannot supply the load",
                            {"bus_v": float(iv.bus_v[0]), "demand_a": float(iv.load_demand_a[0])},
                        )
                    )
                elif supplied and not was_supplied:
                    new_events.append(Event(t, "LoadResupplied", None, "load supplied again"))
                was_supplied = supplied
                unsupplied_s = unsupplied_s + dt if not supplied else 0.0
                sample = self._sample(k, iv, out)
                self.samples.append(sample)
                if new_events:
                    self.events.extend(new_events)
                if self.recorder is not None:
                    self.recorder.record(sample)
                    if new_events:
                        self.recorder.record_events(new_events)
                bar.update(k + 1)
                stop = cfg.sim.stop_when_unsupplied_s
                if stop is not None and unsupplied_s >= stop:
                    break
        except BaseException:
            status = "error"
            raise
        finally:
            bar.close()
            close = getattr(self.charger_link, "close", None)
            if callable(close):
                close()
            wall = time.perf_counter() - wall0
            metrics = compute_metrics(self, wall) if self.samples else {"wall_time_s": wall}
            if self.recorder is not None:
                self.recorder.finish(metrics, status=status)
        return Result(
            battery_names=list(self.pack.names),
            trace=Trace.from_samples(self.samples),
            events=self.events,
            metrics=metrics,
            run_id=self.run_id,
        )

    def _charger_status(self, t_s: float, last: ChargerStatus | None) -> ChargerStatus | None:
        """Latest charger status; marked offline once nothing arrived for the timeout."""
        assert self.charger_link is not None
        status = self.charger_link.poll(t_s)
        if status is not None:
            self._charger_seen_s = t_s
            return status
        seen = getattr(self, "_charger_seen_s", None)
        timeout = self.cfg.charger.heartbeat_timeout_s
        if last is not None and seen is not None and t_s - seen > timeout and last.online:
            return dataclasses.replace(last, online=False)
        return last

    def _sample(self, k: int, iv: Interval, out: ControlOutput) -> StepSample:
        pack = self.pack
        soc, temp = pack.cell_states()
        chg, dsg = pack.effective_gates()
        starts = pack.string_cell_starts
        cap = pack.capacity_ah[0]
        rem = np.minimum.reduceat(soc[0] * cap, starts)
        full = np.minimum.reduceat(cap, starts)
        rows = np.column_stack(
            (
                iv.battery_v[0],
                iv.string_a[0],
                rem / full,
                np.maximum.reduceat(temp[0], starts),
                np.minimum.reduceat(iv.cell_v[0], starts),
                np.maximum.reduceat(iv.cell_v[0], starts),
                rem,
                full,
                chg[0],
                dsg[0],
                iv.chg_diode_a[0],
                iv.dsg_diode_a[0],
                iv.balancer_in_w[0],
            )
        )
        group = np.where(pack.group_table >= 0, iv.group_v[0][pack.group_table], np.nan)
        status = {}
        if out.status:
            # Controller channels are per traction battery; spread them over all strings.
            for name, vals in out.status.items():
                full_vals: list[Any] = [None] * pack.n_strings
                for kk, i in enumerate(self.traction):
                    if kk < len(vals):
                        full_vals[i] = vals[kk]
                status[name] = full_vals
        return StepSample(
            step=k,
            t_s=iv.t_s,
            bus_v=float(iv.bus_v[0]),
            load_demand_a=float(iv.load_demand_a[0]),
            load_a=float(iv.load_a[0]),
            charger_v=float(iv.charger_v[0]),
            charger_a=float(iv.charger_a[0]),
            battery=rows,
            group_v=group,
            status=status,
        )


def compute_metrics(runner: Runner, wall_s: float) -> dict[str, Any]:
    """Summary of a run: energy, extremes, peak currents, heat, events by kind."""
    s = runner.samples
    dt = runner.cfg.sim.dt_s
    bus_v = np.array([x.bus_v for x in s])
    load_a = np.array([x.load_a for x in s])
    demand = np.array([x.load_demand_a for x in s])
    ch_v = np.array([x.charger_v for x in s])
    ch_a = np.array([x.charger_a for x in s])
    bat = np.stack([x.battery for x in s])
    col = BATTERY_CHANNELS.index
    cur = bat[:, :, col("current_a")]
    traction = runner.traction
    # "While the pack supplies a load": the load draws current and no charger feeds the bus;
    # current into a battery while a charger (dock, float rectifier) delivers is charging.
    supplying = (load_a > 1e-3) & (ch_a < 1e-3)
    into = np.maximum(-cur[:, traction], 0.0)
    peak_cross = float(into[supplying].max()) if supplying.any() else 0.0
    peak_idx = np.argmax(np.abs(cur), axis=0)
    peak_string = [float(cur[peak_idx[i], i]) for i in range(cur.shape[1])]
    p = runner.pack
    events = Counter(e.kind for e in runner.events)
    heat_j = float(p.joule_j[0].sum())
    return {
        "sim_time_s": float(len(s) * dt),
        "wall_time_s": float(wall_s),
        "steps": len(s),
        "energy_out_wh": float(np.sum(bus_v * load_a) * dt / 3600.0),
        "energy_in_wh": float(np.sum(ch_v * ch_a) * dt / 3600.0),
        "min_cell_v": float(np.nanmin(bat[:, :, col("min_cell_v")])),
        "max_cell_v": float(np.nanmax(bat[:, :, col("max_cell_v")])),
        "max_temp_c": float(np.nanmax(bat[:, :, col("temp_c")])),
        "final_soc": [float(x) for x in bat[-1, :, col("soc")]],
        "peak_string_current_a": peak_string,
        "peak_cross_current_a": peak_cross,
        "joule_heat_j": heat_j,
        "load_unsupplied_s": float(np.sum((demand > 1e-9) & (load_a < demand - 1e-6)) * dt),
        "chg_diode_energy_j": [float(x) for x in p.chg_diode_j[0]],
        "dsg_diode_energy_j": [float(x) for x in p.dsg_diode_j[0]],
        "events": dict(events),
        "battery_names": list(p.names),
    }


class _Progress:
    """A rich progress bar that appears only once a run has taken more than ~1 s."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total = total
        self.enabled = enabled
        self.t0 = time.perf_counter()
        self.bar: Any = None
        self.task: Any = None

    def update(self, done: int) -> None:
        if not self.enabled or done % 200:
            return
        if self.bar is None:
            if time.perf_counter() - self.t0 < 1.0:
                return
            from rich.progress import (
                BarColumn,
                Progress,
                TaskProgressColumn,
                TimeRemainingColumn,
            )

            self.bar = Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                TaskProgressColumn(),
                TimeRemainingColumn(),
                transient=True,
            )
            self.bar.start()
            self.task = self.bar.add_task("simulating", total=self.total)
        self.bar.update(self.task, completed=done)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def simulate(cfg: ScenarioConfig, **kw: Any) -> Result:
    """Convenience: build a runner from a config and run it."""
    return Runner(cfg, **kw).run()
