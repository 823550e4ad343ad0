"""A closed-loop run watched while it runs: the state a dashboard reads, fed by a recorder.

The simulation thread writes, web handlers read. Writes must stay cheap because they happen
every control step: ``record`` keeps a reference to the latest sample and appends a few numbers
to a bounded chart history (every ``stride``-th step; the stride doubles whenever the history
fills up, so a long run keeps an even-spaced overview in O(max_points) memory). Readers *pull*
what is new since their cursor, so a slow or vanished browser never blocks the simulation and
any number of browsers can watch. Everything leaving here goes through :func:`jsonable`, which
turns NaN and ±inf into None (JSON has no NaN).
"""

from __future__ import annotations

import bisect
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Recorder, StepSample
from packpilot.contract.severity import row_of
from packpilot.contract.topology import Topology
from packpilot.errors import PackPilotError
from packpilot.sim.verdict import RunWatch

CHART_CHANNELS: tuple[str, ...] = ("voltage_v", "current_a", "soc", "temp_c")
"""Per-battery channels kept in the chart history (the four charts of the page)."""

_CHART_COLS = [BATTERY_CHANNELS.index(c) for c in CHART_CHANNELS]

STATES = ("starting", "running", "finished", "stopped", "error")

WATCH_CHUNK = 256
"""Samples the writer holds before it folds them into the physics checks (readers fold what is
pending whenever they ask for the verdict), so a step costs one append."""


class RunStopped(Exception):
    """Raised by the pacing hook inside the runner when the dashboard shuts down."""


def jsonable(obj: Any) -> Any:
    """A JSON-safe copy: numpy → Python, NaN/±inf → None, tuples → lists, keys → str."""
    if obj is None or isinstance(obj, bool | str | int):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.ndarray):
        return [jsonable(x) for x in obj.tolist()]
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple | set | frozenset):
        return [jsonable(x) for x in obj]
    return str(obj)


def jsonable_dict(obj: Mapping[str, Any]) -> dict[str, Any]:
    """:func:`jsonable` for a mapping, typed as one."""
    out = jsonable(obj)
    assert isinstance(out, dict)
    return out


def event_dict(index: int, e: Event, topology: Topology) -> dict[str, Any]:
    """One event as sent to browsers; ``battery_name`` spares the page an index lookup (an
    event's battery counts traction batteries only, as in the report)."""
    b = e.battery
    return jsonable_dict(
        {
            "index": index,
            "t_s": e.t_s,
            "kind": e.kind,
            "severity": row_of(e.kind).severity.label,
            "battery": b,
            "battery_name": topology.battery_name(b),
            "message": e.message,
            "data": dict(e.data),
        }
    )


def sample_summary(s: StepSample, names: Sequence[str]) -> dict[str, Any]:
    """The latest step in full: pack values, every battery channel, every controller status."""
    batteries = []
    for i, row in enumerate(s.battery):
        bat: dict[str, Any] = {"name": names[i] if i < len(names) else str(i)}
        bat.update(zip(BATTERY_CHANNELS, row.tolist(), strict=True))
        bat["group_v"] = s.group_v[i].tolist() if i < len(s.group_v) else []
        bat["status"] = {k: v[i] for k, v in s.status.items() if i < len(v)}
        batteries.append(bat)
    mode = s.status.get("mode")
    out: dict[str, Any] = {
        "step": s.step,
        "t_s": s.t_s,
        "bus_v": s.bus_v,
        "load_demand_a": s.load_demand_a,
        "load_a": s.load_a,
        "charger_v": s.charger_v,
        "charger_a": s.charger_a,
        "mode": next((m for m in mode if m is not None), None) if mode else None,
        "batteries": batteries,
    }
    if s.aux is not None:
        out["aux"] = dict(zip(BATTERY_CHANNELS, s.aux.tolist(), strict=True))
    return jsonable_dict(out)


def _chart_point(s: StepSample) -> dict[str, Any]:
    cols = s.battery[:, _CHART_COLS]
    point: dict[str, Any] = {
        "step": s.step,
        "t_s": s.t_s,
        "bus_v": s.bus_v,
        "load_a": s.load_a,
        "charger_a": s.charger_a,
    }
    for j, name in enumerate(CHART_CHANNELS):
        point[name] = cols[:, j].tolist()
    return point


def _progress(state: str, t_s: float, duration_s: float) -> float | None:
    """Share of the scenario done (a sample's t_s is the start of its step, hence the 1.0)."""
    if state == "finished":
        return 1.0
    return min(1.0, t_s / duration_s) if duration_s > 0 else None


@dataclass
class Update:
    """What one reader has not seen yet (see :meth:`LiveRun.update_since`)."""

    points: list[dict[str, Any]]
    events: list[dict[str, Any]]
    cursor: tuple[int, int]
    """(last chart step sent, number of events sent): pass back to get the next update."""
    changed: bool


@dataclass
class LiveRun:
    """The dashboard's view of one run; thread-safe between one writer and many readers."""

    scenario: str = "scenario"
    duration_s: float = 0.0
    dt_s: float = 0.0
    speed: float = 0.0
    max_points: int = 2000
    battery_names: list[str] = field(default_factory=list)
    state: str = "starting"
    error: str | None = None
    metrics: dict[str, Any] | None = None
    run_id: int | None = None
    db: str | None = None
    stop_requested: threading.Event = field(default_factory=threading.Event)

    def __post_init__(self) -> None:
        if self.max_points < 4:
            raise ValueError(f"max_points must be >= 4, got {self.max_points}")
        self._lock = threading.Lock()
        self._latest: StepSample | None = None
        self._version = 0  # bumps on every write; readers compare to skip idle pushes
        self._points: list[dict[str, Any]] = []
        self._steps: list[int] = []
        self._stride = 1
        self._events: list[Event] = []
        self.topology = Topology.of_config(None, self.battery_names)
        self._started_wall: float | None = None
        self._finished_wall: float | None = None
        self._watch = RunWatch(None, self.battery_names)
        self._pending: list[StepSample] = []

    # ------------------------------------------------------------------ writer side
    def on_start(
        self, battery_names: Sequence[str], config: Mapping[str, Any] | None = None
    ) -> None:
        with self._lock:
            self.battery_names = list(battery_names)
            self.topology = Topology.of_config(config, battery_names)
            self._watch = RunWatch(config, battery_names)
            self._pending = []
            self.state = "running"
            self._started_wall = time.time()
            self._version += 1

    def on_sample(self, s: StepSample) -> None:
        with self._lock:
            self._latest = s
            self._version += 1
            self._pending.append(s)
            if len(self._pending) >= WATCH_CHUNK:
                self._fold()
            if s.step % self._stride:
                return
            self._points.append(_chart_point(s))
            self._steps.append(s.step)
            if len(self._points) > self.max_points:
                self._stride *= 2
                keep = [k for k, st in enumerate(self._steps) if st % self._stride == 0]
                self._points = [self._points[k] for k in keep]
                self._steps = [self._steps[k] for k in keep]

    def on_events(self, events: Sequence[Event]) -> None:
        with self._lock:
            self._events.extend(events)
            self._watch.events.feed(events)
            self._version += 1

    def on_finish(self, metrics: Mapping[str, Any], state: str, error: str | None = None) -> None:
        if state not in STATES:
            raise ValueError(f"unknown run state {state!r}")
        with self._lock:
            s = self._latest
            # The chart must end where the run ended, whatever the stride.
            if s is not None and (not self._steps or self._steps[-1] != s.step):
                self._points.append(_chart_point(s))
                self._steps.append(s.step)
            self.metrics = dict(metrics)
            self.state = state
            if error is not None:
                self.error = error
            self._finished_wall = time.time()
            self._version += 1

    def fail(self, error: str) -> None:
        """The run died outside the recorder (e.g. the telemetry file could not be opened)."""
        with self._lock:
            if self.state in ("starting", "running"):
                self.state = "stopped" if self.stop_requested.is_set() else "error"
            self.error = error
            self._finished_wall = self._finished_wall or time.time()
            self._version += 1

    def _fold(self) -> None:
        """Feed the pending samples to the physics checks (holding the lock)."""
        self._watch.physics.feed_samples(self._pending)
        self._pending = []

    # ------------------------------------------------------------------ reader side
    def verdict(self) -> dict[str, Any]:
        """The run's verdict and alarms so far (the same checks as the report and the CLI)."""
        with self._lock:
            self._fold()
            return jsonable_dict(self._watch.verdict().as_dict())

    @property
    def version(self) -> int:
        return self._version

    @property
    def finished(self) -> bool:
        return self.state in ("finished", "stopped", "error")

    def status(self) -> dict[str, Any]:
        """``GET /api/status``: run state, progress, latest sample summary, metrics at the end."""
        with self._lock:
            latest = self._latest
            n_events = len(self._events)
            state, metrics, error = self.state, self.metrics, self.error
            names = list(self.battery_names)
        verdict = self.verdict()
        t_s = latest.t_s if latest is not None else 0.0
        return jsonable_dict(
            {
                "state": state,
                "scenario": self.scenario,
                "battery_names": names,
                "t_s": t_s,
                "step": latest.step if latest is not None else None,
                "duration_s": self.duration_s,
                "dt_s": self.dt_s,
                "progress": _progress(state, t_s, self.duration_s),
                "speed": self.speed,
                "n_events": n_events,
                "verdict": verdict,
                "latest": None if latest is None else sample_summary(latest, names),
                "metrics": metrics,
                "error": error,
                "run_id": self.run_id,
                "db": self.db,
                "started_at": self._started_wall,
                "finished_at": self._finished_wall,
            }
        )

    def events(self, since: int = 0, limit: int | None = None) -> list[dict[str, Any]]:
        with self._lock:
            end = len(self._events) if limit is None else min(len(self._events), since + limit)
            chunk = self._events[max(0, since) : end]
            topology = self.topology
        return [event_dict(since + k, e, topology) for k, e in enumerate(chunk)]

    def points(self, after_step: int = -1) -> list[dict[str, Any]]:
        """Chart history points with a step greater than ``after_step``."""
        with self._lock:
            k = bisect.bisect_right(self._steps, after_step)
            return [jsonable(p) for p in self._points[k:]]

    def update_since(self, cursor: tuple[int, int], max_events: int = 500) -> Update:
        """New chart points and events after ``cursor``; cursor (-1, 0) means everything."""
        last_step, n_seen = cursor
        pts = self.points(last_step)
        evs = self.events(n_seen, max_events)
        new_cursor = (pts[-1]["step"] if pts else last_step, n_seen + len(evs))
        return Update(pts, evs, new_cursor, bool(pts or evs))


class DashboardRecorder:
    """A :class:`Recorder` that feeds a :class:`LiveRun` and optionally tees to another one.

    With a tee (``SQLiteRecorder``) the run is also recorded for ``packpilot report``. A run
    ended by the dashboard (``stop_requested``) is finished as ``stopped``, not ``error``.
    """

    def __init__(self, live: LiveRun, tee: Recorder | None = None) -> None:
        self.live = live
        self.tee = tee

    def start(self, config: Mapping[str, Any], battery_names: Sequence[str]) -> int:
        run_id = self.tee.start(config, battery_names) if self.tee is not None else 0
        self.live.run_id = run_id if self.tee is not None else None
        self.live.on_start(battery_names, config)
        return run_id

    def record(self, sample: StepSample) -> None:
        if self.tee is not None:
            self.tee.record(sample)
        self.live.on_sample(sample)

    def record_events(self, events: Sequence[Event]) -> None:
        if self.tee is not None:
            self.tee.record_events(events)
        self.live.on_events(events)

    def finish(self, metrics: Mapping[str, Any], status: str = "ok") -> None:
        if status != "ok" and self.live.stop_requested.is_set():
            status = "stopped"
        try:
            if self.tee is not None:
                self.tee.finish(metrics, status=status)
        finally:
            state = {"ok": "finished", "stopped": "stopped", "interrupted": "stopped"}.get(
                status, "error"
            )
            self.live.on_finish(metrics, state)


def pacing_hook(live: LiveRun, speed: float) -> Callable[[Any, float], None]:
    """Runner hook: hold simulated time to ``speed`` × wall time; raise when asked to stop.

    ``speed <= 0`` runs as fast as possible. Sleeping happens only when more than 2 ms ahead,
    so fast paces cost no sleep call per step; the stop flag doubles as the sleep so a stop
    request is seen at once.
    """
    origin: list[float] = []

    def hook(runner: Any, t_s: float) -> None:
        if live.stop_requested.is_set():
            raise RunStopped(f"stopped by the dashboard at t = {t_s:.1f} s")
        if speed <= 0:
            return
        now = time.perf_counter()
        if not origin:
            origin.extend((now, t_s))
        ahead = origin[0] + (t_s - origin[1]) / speed - now
        if ahead > 0.002 and live.stop_requested.wait(ahead):
            raise RunStopped(f"stopped by the dashboard at t = {t_s:.1f} s")

    return hook


class SimThread(threading.Thread):
    """Runs a prepared ``Runner`` into a ``LiveRun``; opens the SQLite tee in its own thread.

    SQLite connections belong to the thread that opened them, hence ``db`` is opened here.
    """

    def __init__(self, runner: Any, live: LiveRun, db: Path | None = None) -> None:
        super().__init__(name="packpilot-sim", daemon=True)
        self.runner = runner
        self.live = live
        self.db = db
        runner.hooks = (*runner.hooks, pacing_hook(live, live.speed))

    def run(self) -> None:
        try:
            if self.db is not None:
                from packpilot.io.telemetry import SQLiteRecorder

                with SQLiteRecorder(self.db) as rec:
                    self.runner.recorder = DashboardRecorder(self.live, rec)
                    self.runner.run()
            else:
                self.runner.recorder = DashboardRecorder(self.live)
                self.runner.run()
        except RunStopped as err:
            self.live.fail(str(err))
        except PackPilotError as err:
            self.live.fail(str(err))
        except Exception as err:  # shown on the page; the server keeps serving what there is
            self.live.fail(f"{type(err).__name__}: {err}")

    def stop(self, timeout_s: float = 10.0) -> None:
        self.live.stop_requested.set()
        if self.is_alive():
            self.join(timeout_s)
