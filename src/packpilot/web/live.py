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
import functools
import math
import re
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
from packpilot.contract.soc_source import LABELS as SOC_LABELS
from packpilot.contract.soc_source import shown_soc
from packpilot.contract.topology import Topology
from packpilot.errors import PackPilotError
from packpilot.sim.verdict import RunWatch
from packpilot.web.power import PowerPanel

MAX_SPEED = 10_000.0
"""Fastest pace the page may ask for (simulated seconds per wall second); 0 means unpaced."""

CHART_CHANNELS: tuple[str, ...] = ("voltage_v", "current_a", "soc", "temp_c")
"""Per-battery channels kept in the chart history (the four charts of the page); ``soc`` is
the SOC the core uses (:func:`core_soc`), the others the recorded battery columns."""

_CHART_COLS = [BATTERY_CHANNELS.index(c) for c in CHART_CHANNELS]

STATES = ("idle", "starting", "running", "finished", "stopped", "error")

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


_BATTERY_NO = re.compile(r"\bbattery (\d+)\b(?![.\d])")
"""A controller's battery index in a message ("battery 0: charge FET off ... from battery 1");
not a voltage ("aux battery 12.3 V")."""


def name_batteries(message: str, topology: Topology) -> str:
    """``message`` with each controller battery index replaced by the battery's name.

    The core names batteries in its messages since PackInfo carries the names; recordings
    made before that (and a reason label such as "R1 battery 1 inserted") still carry indices,
    so they are renamed here, where the names are known: "battery 1" → "battery B"."""

    def name(m: re.Match[str]) -> str:
        shown = topology.battery_name(int(m.group(1)))
        return f"battery {shown}" if shown is not None else m.group(0)

    return _BATTERY_NO.sub(name, message)


def event_dict(index: int, e: Event, topology: Topology) -> dict[str, Any]:
    """One event as sent to browsers; ``battery_name`` spares the page an index lookup (an
    event's battery counts traction batteries only, as in the report), and the message names
    batteries as the page does."""
    b = e.battery
    return jsonable_dict(
        {
            "index": index,
            "t_s": e.t_s,
            "kind": e.kind,
            "severity": row_of(e.kind).severity.label,
            "battery": b,
            "battery_name": topology.battery_name(b),
            "message": name_batteries(e.message, topology),
            "data": dict(e.data),
        }
    )


@functools.cache
def cell_window(cell: str) -> tuple[float | None, float | None]:
    """A cell set's voltage window (minimum, maximum); times the cells in series in a group,
    the fixed axis of the page's per-group bars, so a 49 mV spread looks like 49 mV of a
    1.2 V window, not like 5:1. ``(None, None)`` when the set cannot be loaded (the page then
    falls back to a round window around the groups' own voltages)."""
    from packpilot.model.cell import load_parameter_file, load_parameter_set

    try:
        if cell.endswith((".json", ".toml", ".npz")) or "/" in cell:
            prm = load_parameter_file(Path(cell))
        else:
            prm = load_parameter_set(cell)
        return float(prm.v_min_v), float(prm.v_max_v)
    except (PackPilotError, OSError, ValueError):
        return None, None


def pack_layout(config: Mapping[str, Any] | None, names: Sequence[str]) -> dict[str, Any]:
    """What the page's pack schematic draws: each battery's role, switch kind and group count,
    and whether the pack has a charger, a load and balancers (from the run's config)."""
    cfg = config or {}
    pack = cfg.get("pack") if isinstance(cfg.get("pack"), Mapping) else {}
    assert isinstance(pack, Mapping)
    default_switch = (pack.get("switch") or {}).get("kind", "mosfet_pair")
    by_name = {b.get("name"): b for b in pack.get("batteries") or () if isinstance(b, Mapping)}
    batteries = []
    for n in names:
        b = by_name.get(n, {})
        sw = (b.get("switch") or {}).get("kind", default_switch)
        lo, hi = cell_window(str(b.get("cell") or pack.get("cell") or "uav_5ah"))
        n_cells = b.get("cells_per_group") or 1  # a group's cells are in series
        batteries.append(
            {
                "name": n,
                "role": b.get("role") or "traction",
                "switch": sw,
                "series_groups": b.get("series_groups"),
                "group_v_min": lo * n_cells if config is not None and lo is not None else None,
                "group_v_max": hi * n_cells if config is not None and hi is not None else None,
            }
        )
    load = cfg.get("load") or {}
    return {
        "batteries": batteries,
        "charger": bool((cfg.get("charger") or {}).get("present", False)),
        "load": (load.get("kind") or "none") != "none",
        "balancer": bool((cfg.get("balancer") or {}).get("present", False)),
    }


MOVING_A = 0.05
"""Pack current below which the headline times are not shown (rest: nothing to extrapolate)."""


def headline(latest: Mapping[str, Any] | None, roles: Sequence[str]) -> dict[str, Any]:
    """The three numbers a pilot asks first (Victron style), from a ``sample_summary``:

    - ``time_to_go_s``: traction batteries' remaining Ah at the present discharge current;
    - ``time_to_cutoff_s``: the soonest protection trip predicted (``protection_time_to_trip_s``
      of the protection controller; None without it or when no voltage is falling);
    - ``time_to_full_s``: the Ah still missing at the present charge current (an optimistic
      bound: the constant-voltage taper makes the real charge longer).

    With the battery observer (``[soc]``, issue #28) all three come from it instead: its SOC
    and capacity at the recent average load (3 minutes, so the figures move smoothly), the
    soonest battery's time to cut-off solved forward on its model, and the last battery's time
    to the end of its CC/CV charge (``soc_time_to_full_s``; ``docs/safety.md`` §2a).
    """
    out: dict[str, Any] = {"time_to_go_s": None, "time_to_cutoff_s": None, "time_to_full_s": None}
    if not latest:
        return out
    bats = [
        b
        for i, b in enumerate(latest.get("batteries") or ())
        if (roles[i] if i < len(roles) else "traction") != "aux"
    ]
    observed = _observer_headline(bats)
    if observed is not None:
        return observed
    cur = sum(_num(b.get("current_a")) for b in bats)
    if cur > MOVING_A:
        left = sum(max(0.0, _num(b.get("remaining_ah"))) for b in bats)
        out["time_to_go_s"] = left * 3600.0 / cur
    elif cur < -MOVING_A:
        missing = sum(max(0.0, _num(b.get("full_ah")) - _num(b.get("remaining_ah"))) for b in bats)
        out["time_to_full_s"] = missing * 3600.0 / -cur
    trips = [
        t
        for b in bats
        if isinstance(t := (b.get("status") or {}).get("protection_time_to_trip_s"), int | float)
        and math.isfinite(t)
    ]
    out["time_to_cutoff_s"] = min(trips) if trips else None
    return out


def _observer_headline(bats: Sequence[Mapping[str, Any]]) -> dict[str, Any] | None:
    """The headline times from the observer's status channels, or None when a traction
    battery lacks them (no ``[soc]``, or the cell tables unknown)."""
    keys = ("soc_est", "soc_capacity_ah", "soc_load_avg_a")
    rows = [b.get("status") or {} for b in bats]
    if not rows or not all(
        isinstance(r.get(k), int | float) and math.isfinite(r[k]) for r in rows for k in keys
    ):
        return None
    avg = sum(float(r["soc_load_avg_a"]) for r in rows)
    left = sum(float(r["soc_est"]) * float(r["soc_capacity_ah"]) for r in rows)
    full = sum(float(r["soc_capacity_ah"]) for r in rows)
    ttc = [
        float(t)
        for r in rows
        if isinstance(t := r.get("soc_time_to_cutoff_s"), int | float) and math.isfinite(t)
    ]
    ttf = [r.get("soc_time_to_full_s") for r in rows]
    if all(isinstance(t, int | float) and math.isfinite(t) for t in ttf):
        to_full = max(float(t) for t in ttf if isinstance(t, int | float))  # the last one
    else:  # a recording without the core's CC/CV prediction (before h28ttf)
        to_full = (full - left) * 3600.0 / -avg
    return {
        "time_to_go_s": left * 3600.0 / avg if avg > MOVING_A else None,
        "time_to_cutoff_s": min(ttc) if ttc and avg > MOVING_A else None,
        "time_to_full_s": to_full if avg < -MOVING_A else None,
    }


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) else 0.0


def core_soc(s: StepSample) -> list[tuple[float, str]]:
    """Per battery row of ``s``: the SOC the core uses and its source
    (``contract/soc_source.py``; the battery's own report where the core has no estimate:
    what the BMS read of it, ``bms_soc``, else the recorded value)."""

    def at(name: str, i: int) -> object:
        vals = s.status.get(name)
        return vals[i] if vals is not None and i < len(vals) else None

    soc_col = BATTERY_CHANNELS.index("soc")
    out = []
    for i, row in enumerate(s.battery):
        reported = at("bms_soc", i) if "bms_soc" in s.status else float(row[soc_col])
        out.append(shown_soc(at("soc_est", i), at("soc_observer_ok", i), at("soc_sigma", i),
                             reported))  # fmt: skip
    return out


def sample_summary(s: StepSample, names: Sequence[str]) -> dict[str, Any]:
    """The latest step in full: pack values, every battery channel, every controller status,
    and the SOC the core uses with its source (``soc_core``, ``soc_source``,
    ``soc_source_label``)."""
    batteries = []
    for i, (row, (soc, source)) in enumerate(zip(s.battery, core_soc(s), strict=True)):
        bat: dict[str, Any] = {"name": names[i] if i < len(names) else str(i)}
        bat.update(zip(BATTERY_CHANNELS, row.tolist(), strict=True))
        bat["group_v"] = s.group_v[i].tolist() if i < len(s.group_v) else []
        bat["status"] = {k: v[i] for k, v in s.status.items() if i < len(v)}
        bat.update(soc_core=soc, soc_source=source, soc_source_label=SOC_LABELS[source])
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
    """One point of the chart history; its ``soc`` is the SOC the core uses (the page's SOC
    chart shows what the BMS acts on, not the plant's truth)."""
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
    point["soc"] = [x for x, _ in core_soc(s)]
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
    kind: str = "live"
    """``live`` (a run going on here), ``recorded`` (a run read from a telemetry file) or
    ``attached`` (a run another process is still writing, followed read-only)."""
    source: str | None = None
    """Where the run comes from: the scenario file, or the telemetry file and run id."""
    report: str | None = None
    """URL path of the run's HTML report once one exists (shown as a link at the end)."""
    notice: str | None = None
    """A remark for the page that is not the run's error (e.g. why no report was written)."""

    def __post_init__(self) -> None:
        if self.max_points < 4:
            raise ValueError(f"max_points must be >= 4, got {self.max_points}")
        if not (self.speed >= 0 and math.isfinite(self.speed)):
            raise ValueError(f"speed must be finite and >= 0, got {self.speed}")
        self._lock = threading.Lock()
        self._control = threading.Condition()
        self._paused = False
        self._epoch = 0  # bumps on every pause / resume / speed change / stop request
        self.layout: dict[str, Any] = pack_layout(None, self.battery_names)
        self.config: Mapping[str, Any] | None = None
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
        self.power = PowerPanel(None, self.battery_names, self.topology.roles)
        """The state-of-power panel of this run (``web/power.py``)."""

    # ------------------------------------------------------------------ writer side
    def on_start(
        self, battery_names: Sequence[str], config: Mapping[str, Any] | None = None
    ) -> None:
        with self._lock:
            self.battery_names = list(battery_names)
            self.topology = Topology.of_config(config, battery_names)
            self.layout = pack_layout(config, battery_names)
            self.config = config
            self._watch = RunWatch(config, battery_names)
            self._pending = []
            self.power = PowerPanel(config, battery_names, self.topology.roles,
                                    on_done=self._touch)  # fmt: skip
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

    def _touch(self) -> None:
        """Something readers show changed outside a sample (a state of power landed)."""
        with self._lock:
            self._version += 1

    def _fold(self) -> None:
        """Feed the pending samples to the physics checks (holding the lock)."""
        self._watch.physics.feed_samples(self._pending)
        self._pending = []

    def set_report(self, url: str) -> None:
        with self._lock:
            self.report = url
            self._version += 1

    def note(self, text: str) -> None:
        with self._lock:
            self.notice = text
            self._version += 1

    # ------------------------------------------------------------------ controls
    @property
    def paused(self) -> bool:
        return self._paused

    def pace(self) -> tuple[int, float, bool]:
        """(epoch, speed, paused) as the pacing hook reads them, consistently."""
        with self._control:
            return self._epoch, self.speed, self._paused

    def _changed(self) -> None:
        """Wake the pacing hook and the readers (holding ``_control``)."""
        self._epoch += 1
        self._control.notify_all()
        self._version += 1

    def set_paused(self, paused: bool) -> None:
        with self._control:
            if self._paused != paused:
                self._paused = paused
                self._changed()

    def set_speed(self, speed: float) -> None:
        if not (0 <= speed <= MAX_SPEED):
            raise ValueError(f"speed must be 0..{MAX_SPEED:g} (0: as fast as possible)")
        with self._control:
            self.speed = float(speed)
            self._changed()

    def request_stop(self) -> None:
        with self._control:
            self.stop_requested.set()
            self._changed()

    def wait_control(self, epoch: int, timeout_s: float | None) -> bool:
        """Sleep until a control changes (True) or ``timeout_s`` passes (False)."""
        with self._control:
            return self._control.wait_for(
                lambda: self._epoch != epoch or self.stop_requested.is_set(), timeout_s
            )

    # ------------------------------------------------------------------ reader side
    def verdict(self) -> dict[str, Any]:
        """The run's verdict and alarms so far (the same checks as the report and the CLI)."""
        with self._lock:
            self._fold()
            out = jsonable_dict(self._watch.verdict().as_dict())
            topology = self.topology
        for alarm in out.get("alarms") or ():  # an event's message is the alarm's cause
            if isinstance(alarm.get("cause"), str):
                alarm["cause"] = name_batteries(alarm["cause"], topology)
        return out

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
        power = self.power.latest(latest, final=state in ("finished", "stopped", "error"))
        t_s = latest.t_s if latest is not None else 0.0
        summary = None if latest is None else sample_summary(latest, names)
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
                "paused": self._paused,
                "kind": self.kind,
                "source": self.source,
                "report": self.report,
                "notice": self.notice,
                "headline": headline(summary, self.topology.roles),
                "power": power,
                "power_note": self.power.note,
                "n_events": n_events,
                "verdict": verdict,
                "latest": summary,
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


CATCH_UP_S = 0.5
"""How far behind its pace a live run may fall before the pace restarts from the present step
(a kernel compiled at the first step took tens of seconds, and the run then raced through its
whole length in a burst that the page never showed)."""


def pacing_hook(live: LiveRun) -> Callable[[Any, float], None]:
    """Runner hook: hold simulated time to ``live.speed`` × wall time, hold still while
    paused, raise when asked to stop.

    Speed and pause are read at every step, so the page's controls act within one step (a
    sleep wakes at once on a change). ``speed <= 0`` runs as fast as possible. Sleeping
    happens only when more than 2 ms ahead, so fast paces cost no sleep call per step. After
    a change the pace restarts from the present step, so a resume does not race to catch up.
    """
    origin: list[float] = []  # wall time, simulated time, epoch
    stopped = "stopped by the dashboard at t = {:.1f} s"

    def hook(runner: Any, t_s: float) -> None:
        while True:
            if live.stop_requested.is_set():
                raise RunStopped(stopped.format(t_s))
            epoch, speed, paused = live.pace()
            if not paused:
                break
            live.wait_control(epoch, None)
        if speed <= 0:
            origin.clear()
            return
        now = time.perf_counter()
        if not origin or origin[2] != epoch:
            origin[:] = [now, t_s, epoch]
        ahead = origin[0] + (t_s - origin[1]) / speed - now
        if ahead < -CATCH_UP_S:  # behind (a first-run compile, a slow step): pace from here,
            origin[:] = [now, t_s, epoch]  # do not race through the run to catch up
            return
        if ahead > 0.002 and live.wait_control(epoch, ahead) and live.stop_requested.is_set():
            raise RunStopped(stopped.format(t_s))

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
        self.on_result: Callable[[LiveRun, Any], None] | None = None
        """Called with the ``Result`` of a run that finished (e.g. to write its report)."""
        runner.hooks = (*runner.hooks, pacing_hook(live))

    def run(self) -> None:
        try:
            if self.db is not None:
                from packpilot.io.telemetry import SQLiteRecorder

                with SQLiteRecorder(self.db) as rec:
                    self.runner.recorder = DashboardRecorder(self.live, rec)
                    result = self.runner.run()
            else:
                self.runner.recorder = DashboardRecorder(self.live)
                result = self.runner.run()
            if self.on_result is not None:
                self.on_result(self.live, result)
        except RunStopped as err:
            self.live.fail(str(err))
        except PackPilotError as err:
            self.live.fail(str(err))
        except Exception as err:  # shown on the page; the server keeps serving what there is
            self.live.fail(f"{type(err).__name__}: {err}")

    def stop(self, timeout_s: float = 10.0) -> None:
        self.live.request_stop()
        if self.is_alive():
            self.join(timeout_s)
