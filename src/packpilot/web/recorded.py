"""A recorded run (a SQLite telemetry file) on the dashboard, finished or still being written.

A finished run is replayed into a :class:`LiveRun` in one go, so the page, the verdict and the
API are the ones of a live run that has ended; only ``kind`` says ``recorded``. A run whose
writer is still at it (``packpilot run --db``, ``simulate --db`` in another process) is
*followed*: ``kind`` is ``attached``, and :meth:`Recording.poll` feeds the rows committed since
the last poll (the writer commits about once a second). The dashboard only reads the file: it
cannot pause, steer or stop the run it follows. The chart history is the LiveRun's bounded
overview; the scrubber reads the full-rate trace kept here, in the blocks it was read in.
"""

from __future__ import annotations

import bisect
import sqlite3
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event
from packpilot.contract.record import StepSample, Trace
from packpilot.errors import InputError
from packpilot.io.telemetry.reader import Chunk, RunTail
from packpilot.web.live import LiveRun, headline, jsonable_dict, sample_summary

SQLITE_MAGIC = b"SQLite format 3\x00"

_STATES = {"ok": "finished", "stopped": "stopped", "interrupted": "stopped"}

POLL_S = 0.5
"""How often a followed run is read again (its writer commits about once a second)."""


def is_sqlite(path: Path) -> bool:
    """The file starts with SQLite's header (what ``dashboard FILE`` takes for a recording)."""
    try:
        with path.open("rb") as f:
            return f.read(len(SQLITE_MAGIC)) == SQLITE_MAGIC
    except OSError:
        return False


def _section(config: dict[str, Any], name: str) -> dict[str, Any]:
    got = config.get(name)
    return got if isinstance(got, dict) else {}


def _read(tail: RunTail) -> Chunk:
    try:
        return tail.read()
    except sqlite3.Error as err:  # a file changed under us, a locked or damaged page
        raise InputError(f"{tail.path}: cannot read ({err})") from None


class Recording:
    """One recorded run: ``live`` for the page, :meth:`at` for the scrubber, :meth:`poll`
    while its writer is still running (``following``)."""

    def __init__(self, path: Path, run_id: int | None = None, max_points: int = 2000) -> None:
        try:
            tail = RunTail(path, run_id)
        except sqlite3.Error as err:
            raise InputError(f"{path}: cannot read ({err})") from None
        try:
            first = _read(tail)
        except BaseException:
            tail.close()
            raise
        self.following = first.status == "running"
        self.ended: str | None = None
        """The status the followed run ended with (None while followed, or if reading failed)."""
        if not self.following:
            tail.close()
            if len(first.steps) == 0:
                raise InputError(f"{path}: run {tail.run_id} has no samples")
        self._tail = tail
        self.path = path
        self.run_id = tail.run_id
        self.names = list(tail.names)
        self.events: list[Event] = []
        self._traces: list[Trace] = []
        self._steps: list[NDArray[np.int64]] = []
        self._starts: list[int] = []
        self._t_s: NDArray[np.float64] = np.empty(0)
        self._lock = threading.Lock()
        config = tail.config
        sim = _section(config, "sim")
        dt_s = float(sim.get("dt_s") or 0.0)
        self.live = LiveRun(
            scenario=str(_section(config, "pack").get("name") or path.stem),
            duration_s=0.0,
            dt_s=dt_s,
            speed=0.0,
            max_points=max_points,
            battery_names=self.names,
            kind="attached" if self.following else "recorded",
            source=f"{path.name}, run {self.run_id}",
            db=str(path),
        )
        self.live.run_id = self.run_id
        self.live.on_start(self.names, config)
        self._add(first)
        if not self.following:
            self.live.duration_s = float(self._t_s[-1]) + (dt_s or self._dt_guess())
            self._end(first)

    def _dt_guess(self) -> float:
        return float(self._t_s[1] - self._t_s[0]) if len(self._t_s) > 1 else 0.0

    @property
    def n_samples(self) -> int:
        return len(self._t_s)

    def _add(self, chunk: Chunk) -> None:
        """Keep a block of new rows for the scrubber and feed it to the page's run."""
        tr = chunk.result.trace
        if len(chunk.steps):
            with self._lock:
                self._starts.append(len(self._t_s))
                self._traces.append(tr)
                self._steps.append(chunk.steps)
                self._t_s = np.concatenate([self._t_s, tr.t_s])
            for k in range(len(chunk.steps)):
                self.live.on_sample(_row(tr, chunk.steps, k))
        if chunk.result.events:
            with self._lock:
                self.events.extend(chunk.result.events)
            self.live.on_events(chunk.result.events)

    def _end(self, chunk: Chunk) -> None:
        """The writer has finished (or died): the page's run ends with the run's status."""
        state = _STATES.get(chunk.status, "error")
        self.live.on_finish(chunk.result.metrics, state)
        if state != "finished":
            self.live.error = f"the recording's status is {chunk.status!r}"

    def poll(self) -> bool:
        """Read what the writer committed since the last poll; False once the run has ended
        (then the page's run is finished with the recorded status and metrics)."""
        if not self.following:
            return False
        try:
            chunk = _read(self._tail)
        except InputError as err:
            self.following = False
            self._tail.close()
            self.live.fail(str(err))
            return False
        self._add(chunk)
        if chunk.status != "running":
            self.following = False
            self._tail.close()
            self.ended = chunk.status
            self._end(chunk)
        return self.following

    def close(self) -> None:
        """Stop following (the page moved on); the file is left as it is."""
        if self.following:
            self.following = False
            self._tail.close()

    def sample(self, k: int) -> StepSample:
        """Row ``k`` of the trace as the StepSample it was recorded from."""
        j = bisect.bisect_right(self._starts, k) - 1
        return _row(self._traces[j], self._steps[j], k - self._starts[j])

    def at(self, t_s: float) -> dict[str, Any]:
        """The full-rate sample at or just before ``t_s`` (clamped to the run), with the
        headline numbers then and how many events had happened by then."""
        with self._lock:
            t_all, events = self._t_s, list(self.events)
        if len(t_all) == 0:
            raise InputError(f"{self.path}: run {self.run_id} has no samples yet")
        # 1 µs of slack: a step's time accumulated in floating point (4.999999 for 5.0)
        found = int(np.searchsorted(t_all, t_s + 1e-6, side="right"))
        k = max(0, min(len(t_all) - 1, found - 1))
        s = self.sample(k)
        summary = sample_summary(s, self.names)
        t = float(t_all[k])
        n_events = sum(1 for e in events if not e.t_s > t)
        return jsonable_dict(
            {
                "index": k,
                "t_s": t,
                "latest": summary,
                "headline": headline(summary, self.live.topology.roles),
                "n_events": n_events,
            }
        )


def _row(tr: Trace, steps: NDArray[np.int64], k: int) -> StepSample:
    """Row ``k`` of a block of trace as a StepSample. A status channel that began within the
    block is shorter than the block: it is aligned on the block's end."""
    n = len(tr.t_s)
    status = {ch: seq[k - n + len(seq)] for ch, seq in tr.status.items() if k >= n - len(seq)}
    return StepSample(
        step=int(steps[k]),
        t_s=float(tr.t_s[k]),
        bus_v=float(tr.bus_v[k]),
        load_demand_a=float(tr.load_demand_a[k]),
        load_a=float(tr.load_a[k]),
        charger_v=float(tr.charger_v[k]),
        charger_a=float(tr.charger_a[k]),
        battery=tr.battery[k],
        group_v=tr.group_v[k],
        status=status,
        aux=tr.aux[k] if tr.aux is not None else None,
    )


class Follower(threading.Thread):
    """Polls a followed recording until it ends or :meth:`stop`; ``on_end`` is told once the
    writer has finished or died (the session then reopens it as a plain recording, with a
    scrubber), not when the file could not be read (the page shows that error)."""

    def __init__(
        self, rec: Recording, on_end: Callable[[Recording], None], poll_s: float = POLL_S
    ) -> None:
        super().__init__(name=f"follow-{rec.path.name}", daemon=True)
        self.rec = rec
        self.on_end = on_end
        self.poll_s = poll_s
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.wait(self.poll_s):
            if not self.rec.poll():
                if self.rec.ended is not None:
                    self.on_end(self.rec)
                return

    def stop(self) -> None:
        self._stop_event.set()
        if self.is_alive() and threading.current_thread() is not self:
            self.join(timeout=5.0)
        self.rec.close()
