"""A single closed-loop run (P = 1): the shell around the one loop for one pack.

:class:`Runner` keeps the plant, the BMS core and the charger link of one scenario, runs the
loop of :mod:`packpilot.sim.loop`, streams every step to a recorder and summarises the run
into metrics. Its controller is the scenario's core by default; any scalar
:class:`~packpilot.contract.bms.Controller` (a prototype, a test double) can stand in.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from packpilot.buildclock import build_seconds
from packpilot.config import ScenarioConfig
from packpilot.contract.bms import Controller, Event
from packpilot.contract.charger import ChargerLink
from packpilot.contract.record import Recorder, Result
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core
from packpilot.model import loads
from packpilot.model.pack import Pack
from packpilot.sim import record
from packpilot.sim.links import default_links, modelled
from packpilot.sim.loop import ClosedLoop, build_core, load_profile, n_steps
from packpilot.sim.plant_io import SimulatedPlant
from packpilot.sim.record import TraceBuffer


def as_core(controller: Any, info: PackInfo) -> Core:
    """The core that runs ``controller``: itself, a supervisor's core, or a Python part."""
    if isinstance(controller, Core):
        return controller
    core = getattr(controller, "core", None)
    if isinstance(core, Core):
        return core
    return Core([info], [controller])


@dataclass
class Runner:
    """One closed-loop run of one pack."""

    cfg: ScenarioConfig
    controller: Controller | Core | None = None
    recorder: Recorder | None = None
    charger_link: ChargerLink | None = None
    """The pack's charger link. By default the scenario's: a Python link (direct, or a
    python-can bus with a frame log, a named channel or a real interface) built here, or
    ``None`` when the link is modelled (:func:`~packpilot.sim.links.modelled`): the loop then
    runs the compiled model (``self.loop.links``). Set it to run any link of your own."""
    progress: bool | None = None
    hooks: Sequence[Callable[[Runner, float], None]] = ()
    """Called before each control step with (runner, t_s): fault injection, hot plugs."""
    pack_overrides: Mapping[str, Any] = field(default_factory=dict)
    """Extra keyword arguments for ``Pack(cfg, ...)`` (campaign draws: ``capacity_scale``,
    ``r_scale``, ``soc_offset``, ``ambient_c``)."""
    plant: SimulatedPlant = field(init=False)

    def __post_init__(self) -> None:
        self._build0 = build_seconds()
        """Kernel compile / cache-load time so far: the run reports its own apart."""
        self.plant = SimulatedPlant(self.cfg, 1, self.pack_overrides)
        self.info: PackInfo = self.plant.infos[0]
        self.traction = list(self.plant.topology.traction)
        if self.controller is None:
            self.controller = build_core(self.cfg, self.plant.infos)
        self._profile = load_profile(self.cfg)
        # Last: a python-can bus opened before a later error was never shut down (python-can
        # then warned "VirtualBus was not properly shut down" under the one-line error).
        if self.charger_link is None and self.cfg.charger.present and not modelled(self.cfg):
            self.charger_link = default_links(self.cfg, self.pack)[0]
        self.loop: ClosedLoop | None = None
        self.events: list[Event] = []
        self.steps_done = 0
        """Steps completed so far (where an interrupted run stopped)."""

    @property
    def profile(self) -> loads.LoadProfile:
        """The load demand of the run; set it (before or during a run, e.g. from a hook) to
        change what the loop draws from the next period on."""
        return self._profile

    @profile.setter
    def profile(self, value: loads.LoadProfile) -> None:
        self._profile = value
        if self.loop is not None:
            self.loop.profile = value

    @property
    def pack(self) -> Pack:
        return self.plant.pack

    def _prepare(
        self, core: Core, links: list[ChargerLink] | None, total: int
    ) -> tuple[ClosedLoop, TraceBuffer]:
        """The loop of this run and the buffer its trace goes into."""
        hooks = [lambda t, h=h: h(self, t) for h in self.hooks]
        loop = ClosedLoop.of(self.cfg, core=core, links=links, hooks=hooks, plant=self.plant)
        loop.profile = self._profile
        self.loop = loop
        buf = TraceBuffer(
            self.pack,
            self.plant.topology,
            core.status_channels(),
            core.status.shape[2],
            capacity=min(total, 1 << 16),
            max_rows=record.MAX_TRACE_ROWS,
        )
        return loop, buf

    def _recording(
        self, core: Core, buf: TraceBuffer
    ) -> Callable[[int, int, list[Event]], None] | None:
        """What hands step ``k`` (trace row ``row``) and its events to the recorder. A recorder
        that takes numbers (SQLite: ``record_numbers``) gets the trace's row as it is, with
        no sample built per step; a core with Python parts (status that is not numbers), or
        any other recorder, gets a :class:`StepSample`."""
        rec = self.recorder
        if rec is None:
            return None
        numbers = getattr(rec, "record_numbers", None)
        if numbers is None or core.python_status() is not None:

            def sample(k: int, row: int, events: list[Event]) -> None:
                rec.record(buf.sample(row))
                if events:
                    rec.record_events(events)

            return sample
        layout = buf.status_layout()

        def fast(k: int, row: int, events: list[Event]) -> None:
            numbers(k, buf.scalars[row], buf.battery[row], buf.group_v[row], buf.status[row],
                    layout)  # fmt: skip
            if events:
                rec.record_events(events)

        return fast

    def run(self) -> Result:
        cfg = self.cfg
        dt = cfg.sim.dt_s
        total = n_steps(cfg)
        assert self.controller is not None
        core = as_core(self.controller, self.info)
        links: list[ChargerLink] | None = None  # None: the compiled model, when modelled
        if self.charger_link is not None:
            links = [self.charger_link]
        elif not modelled(cfg):
            links = []
        loop, buf = self._prepare(core, links, total)
        self.run_id: int | None = None
        if self.recorder is not None:
            self.run_id = self.recorder.start(cfg.model_dump(mode="json"), self.pack.names)
        wall0 = time.perf_counter()
        built0 = build_seconds()
        status = "ok"
        enabled = cfg.sim.progress if self.progress is None else self.progress
        bar = _Progress(total, enabled, lines=self.progress is True and not sys.stderr.isatty())
        record = self._recording(core, buf)
        try:
            for k in range(total):
                rec = loop.step(k, dt)
                row = buf.add(k, rec.iv, core.status, core.python_status(), core.m)
                new_events = rec.events[0]
                if new_events:
                    self.events.extend(new_events)
                if record is not None:
                    record(k, row, new_events)
                bar.update(k + 1)
                self.steps_done = k + 1
                if not loop.running:
                    break
        except KeyboardInterrupt:
            status = "interrupted"  # the user stopped it (Ctrl-C): not a failure of the run
            raise
        except BaseException:
            status = "error"
            raise
        finally:
            bar.close()
            loop.close()
            built = build_seconds()
            # Simulation time only: compiling (or loading) a kernel at its first call is not.
            wall = time.perf_counter() - wall0 - (built - built0)
            metrics = (
                loop.metrics.of(0, wall, self.pack.names) if buf.rows else {"wall_time_s": wall}
            )
            if self.recorder is not None:  # the build time travels with the run, kept apart
                self.recorder.finish(
                    {**metrics, "build_time_s": built - self._build0}, status=status
                )
        return Result(
            battery_names=list(self.pack.names),
            trace=buf.trace(),
            events=self.events,
            metrics=metrics,
            run_id=self.run_id,
            build_time_s=built - self._build0,
        )


LINE_EVERY_S = 1.5
"""Longest pause between two plain progress lines."""


class _Progress:
    """Progress on **stderr** (stdout stays clean for ``--json``): a rich bar on a terminal
    once a run has taken more than ~1 s; with ``lines`` (progress asked for explicitly, stderr
    not a terminal: ``make demo`` in CI, a log file) one plain line per tenth of the run."""

    def __init__(self, total: int, enabled: bool, lines: bool = False) -> None:
        self.total = total
        self.enabled = enabled and (lines or sys.stderr.isatty())
        self.lines = lines
        self.t0 = time.perf_counter()
        self.done = 0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None
        if self.enabled and lines:
            # Lines also while a step takes long (the first one loads the compiled kernels).
            self._beat = threading.Thread(target=self._heartbeat, daemon=True)
            self._beat.start()
        self.bar: Any = None
        self.task: Any = None
        self.next_at = max(1, -(-total // 10))
        """Steps done at which the next plain line is due (one per tenth)."""
        self.last_line = self.t0

    def update(self, done: int) -> None:
        if not self.enabled:
            return
        if self.lines:
            self.done = done  # what the heartbeat says while a step takes long
            # A line per tenth of the run, and at least every LINE_EVERY_S (``make demo``
            # never leaves its reader more than 2 s without output).
            if done >= self.next_at or time.perf_counter() - self.last_line >= LINE_EVERY_S:
                self._line(done)
            return
        if done % 200:
            return
        if self.bar is None:
            if time.perf_counter() - self.t0 < 1.0:
                return
            self._start()
        self.bar.update(self.task, completed=done)

    def _line(self, done: int) -> None:
        with self._lock:
            self.done = done
            self.next_at = -(-(done * 10 // self.total + 1) * self.total // 10)  # ceil
            self.last_line = time.perf_counter()
            wall = self.last_line - self.t0
            print(
                f"simulating: {100 * done // self.total:3d} %"
                f" ({done}/{self.total} steps, {wall:.0f} s)",
                file=sys.stderr,
                flush=True,
            )

    def _heartbeat(self) -> None:
        while not self._stop.wait(LINE_EVERY_S / 3):
            if time.perf_counter() - self.last_line >= LINE_EVERY_S:
                self._line(self.done)

    def _start(self) -> None:
        from rich.console import Console
        from rich.progress import BarColumn, Progress, TaskProgressColumn, TimeRemainingColumn

        self.bar = Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            TaskProgressColumn(),
            TimeRemainingColumn(),
            transient=True,
            console=Console(stderr=True),
        )
        self.bar.start()
        self.task = self.bar.add_task("simulating", total=self.total)

    def close(self) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join()
        if self.bar is not None:
            self.bar.stop()


def simulate(cfg: ScenarioConfig, **kw: Any) -> Result:
    """Convenience: build a runner from a config and run it."""
    return Runner(cfg, **kw).run()
