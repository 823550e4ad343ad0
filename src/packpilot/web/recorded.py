"""A recorded run (a SQLite telemetry file) on the dashboard, finished or still being written.

A finished run is replayed into a :class:`LiveRun` in one go, so the page, the verdict and the
API are the ones of a live run that has ended; only ``kind`` says ``recorded``. A run whose
writer is still at it (``packpilot run --db``, ``simulate --db`` in another process) is
*followed*: ``kind`` is ``attached``, and :meth:`Recording.poll` feeds the rows committed since
the last poll (the writer commits about once a second). The dashboard only reads the file: it
cannot pause, steer or stop the run it follows. The chart history is the LiveRun's bounded
overview; the scrubber reads the full-rate sample it needs back from the file, one block of
:data:`SCRUB_BLOCK` samples at a time, so memory does not grow with the run's length.
"""

from __future__ import annotations

import bisect
import sqlite3
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
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


def _read(tail: RunTail, max_steps: int | None = None) -> Chunk:
    try:
        return tail.read(max_steps)
    except sqlite3.Error as err:  # a file changed under us, a locked or damaged page
        raise InputError(f"{tail.path}: cannot read ({err})") from None


SCRUB_BLOCK = 4096
"""Samples read at a time: the page is fed block by block and the scrubber reads back the one
block that holds the asked time, so the dashboard never holds a run's full-rate trace (a 1-day
run held that way took 0.93 GB, issue #26 §3)."""


@dataclass(frozen=True)
class _Block:
    """Where one block of samples is in the file: enough to read it again (:meth:`RunTail.seek`)."""

    start: int
    """Index of its first sample in the run."""
    n: int
    t_first: float
    position: tuple[int, dict[str, list[StatusValue]]]


class Recording:
    """One recorded run: ``live`` for the page, :meth:`at` for the scrubber, :meth:`poll`
    while its writer is still running (``following``).

    The run is read in blocks of :data:`SCRUB_BLOCK` samples, each fed to the page's
    :class:`LiveRun` (whose history and checks are bounded) and then dropped; what stays per
    block is where it starts in the file and the forward-filled status there, so the
    scrubber reads back just the block it needs. Memory: the LiveRun, the events and a few
    numbers per block, not the trace."""

    def __init__(self, path: Path, run_id: int | None = None, max_points: int = 2000) -> None:
        try:
            tail = RunTail(path, run_id)
        except sqlite3.Error as err:
            raise InputError(f"{path}: cannot read ({err})") from None
        self._tail = tail
        self.path = path
        self.run_id = tail.run_id
        self.names = list(tail.names)
        self.events: list[Event] = []
        self._blocks: list[_Block] = []
        self._n = 0
        self._t_head: list[float] = []  # the run's first two sample times (its step)
        self._t_last = float("nan")
        self._cache: tuple[int, Trace, NDArray[np.int64]] | None = None
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
            kind="recorded",
            source=f"{path.name}, run {self.run_id}",
            db=str(path),
        )
        self.live.run_id = self.run_id
        self.live.on_start(self.names, config)
        try:
            last = self._read_blocks()
        except BaseException:
            tail.close()
            raise
        self.following = last.status == "running"
        self.ended: str | None = None
        """The status the followed run ended with (None while followed, or if reading failed)."""
        if self.following:
            self.live.kind = "attached"
        else:
            tail.close()
            if self._n == 0:
                raise InputError(f"{path}: run {tail.run_id} has no samples")
            self.live.duration_s = self._t_last + (dt_s or self._dt_guess())
            self._end(last)

    def _dt_guess(self) -> float:
        return self._t_head[1] - self._t_head[0] if len(self._t_head) > 1 else 0.0

    @property
    def n_samples(self) -> int:
        return self._n

    def _read_blocks(self) -> Chunk:
        """Read and feed what was committed since the last read, a block at a time; the last
        block's chunk (its status is the run's)."""
        while True:
            position = self._tail.position()
            chunk = _read(self._tail, SCRUB_BLOCK)
            self._add(chunk, position)
            if len(chunk.steps) < SCRUB_BLOCK:
                return chunk

    def _add(self, chunk: Chunk, position: tuple[int, dict[str, list[StatusValue]]]) -> None:
        """Note where a block of new rows is and feed it to the page's run."""
        tr = chunk.result.trace
        n = len(chunk.steps)
        if n:
            with self._lock:
                self._blocks.append(_Block(self._n, n, float(tr.t_s[0]), position))
                self._n += n
                self._t_last = float(tr.t_s[-1])
                self._t_head.extend(tr.t_s[: 2 - len(self._t_head)].tolist())
            for k in range(n):
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
            chunk = self._read_blocks()
        except InputError as err:
            self.following = False
            self._tail.close()
            self.live.fail(str(err))
            return False
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

    def _block(self, j: int) -> tuple[Trace, NDArray[np.int64]]:
        """Block ``j`` read again from the file (the last one read is kept)."""
        with self._lock:
            cached, block = self._cache, self._blocks[j]
        if cached is not None and cached[0] == j:
            return cached[1], cached[2]
        try:
            tail = RunTail(self.path, self.run_id)
        except sqlite3.Error as err:
            raise InputError(f"{self.path}: cannot read ({err})") from None
        try:
            tail.seek(*block.position)
            chunk = _read(tail, block.n)
        finally:
            tail.close()
        if len(chunk.steps) != block.n:
            raise InputError(f"{self.path}: run {self.run_id} changed under the dashboard")
        with self._lock:
            self._cache = (j, chunk.result.trace, chunk.steps)
        return chunk.result.trace, chunk.steps

    def sample(self, k: int) -> StepSample:
        """Row ``k`` of the trace as the StepSample it was recorded from."""
        with self._lock:
            j = bisect.bisect_right(self._blocks, k, key=lambda b: b.start) - 1
            start = self._blocks[j].start
        tr, steps = self._block(j)
        return _row(tr, steps, k - start)

    def at(self, t_s: float) -> dict[str, Any]:
        """The full-rate sample at or just before ``t_s`` (clamped to the run), with the
        headline numbers then and how many events had happened by then."""
        with self._lock:
            n_blocks, events = len(self._blocks), list(self.events)
            # 1 µs of slack: a step's time accumulated in floating point (4.999999 for 5.0)
            j = bisect.bisect_right(self._blocks, t_s + 1e-6, key=lambda b: b.t_first) - 1
            j = max(0, j)
            start = self._blocks[j].start if n_blocks else 0
        if n_blocks == 0:
            raise InputError(f"{self.path}: run {self.run_id} has no samples yet")
        tr, steps = self._block(j)
        found = int(np.searchsorted(tr.t_s, t_s + 1e-6, side="right"))
        i = max(0, min(len(tr.t_s) - 1, found - 1))
        s = _row(tr, steps, i)
        summary = sample_summary(s, self.names)
        t = float(tr.t_s[i])
        n_events = sum(1 for e in events if not e.t_s > t)
        return jsonable_dict(
            {
                "index": start + i,
                "t_s": t,
                "latest": summary,
                "headline": headline(summary, self.live.topology.roles),
                "power": self.live.power.compute(s),
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
