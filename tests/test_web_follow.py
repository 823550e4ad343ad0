"""The dashboard attached to a run another writer is still writing (#16 §1): the telemetry file
read in pieces as it grows (``RunTail``), followed read-only by the session, reopened as a
plain recording once the writer finishes, and shown as aborted when the writer dies."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.bms import Event
from packpilot.contract.record import Recorder, Result, StepSample
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.io.telemetry.reader import Chunk, RunTail
from packpilot.sim.runner import Runner
from packpilot.web.live import LiveRun
from packpilot.web.recorded import Recording
from packpilot.web.session import Session
from tests.test_web_app import WS_URL, scenario
from tests.test_web_controls import OK, app_client
from tests.test_web_security import recording

__all__ = ["recording"]  # the module-scoped fixture, shared


def wait_for(cond: Callable[[], bool], timeout_s: float = 20.0, what: str = "") -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.02)


# ---------------------------------------------------------------- the reader
class ReadWhileWriting:
    """A recorder that commits every ``every`` samples and reads the file back at once
    through a :class:`RunTail`, as a dashboard in another process would."""

    def __init__(self, path: Path, every: int) -> None:
        self.rec = SQLiteRecorder(path, flush_every=10**6, commit_every_s=1e9)
        self.path, self.every, self.n = path, every, 0
        self.chunks: list[Chunk] = []
        self.tail: RunTail | None = None

    def start(self, config: Any, battery_names: Any) -> int:
        run_id = self.rec.start(config, battery_names)
        self.tail = RunTail(self.path, run_id)
        self.chunks.append(self.tail.read())  # the run exists, no sample yet
        return run_id

    def record(self, sample: StepSample) -> None:
        self.rec.record(sample)
        self.n += 1
        if self.n % self.every == 0:
            self.rec.flush()
            assert self.tail is not None
            self.chunks.append(self.tail.read())

    def record_events(self, events: Any) -> None:
        self.rec.record_events(events)

    def finish(self, metrics: Any, status: str = "ok") -> None:
        self.rec.finish(metrics, status)
        assert self.tail is not None
        self.chunks.append(self.tail.read())
        self.tail.close()
        self.rec.close()


def joined(chunks: list[Chunk]) -> tuple[dict[str, Any], list[Event]]:
    tr = [c.result.trace for c in chunks if len(c.steps)]
    status: dict[str, list[Any]] = {}
    for t in tr:
        for ch, seq in t.status.items():
            status.setdefault(ch, []).extend(seq)
    arrays = {
        "t_s": np.concatenate([t.t_s for t in tr]),
        "bus_v": np.concatenate([t.bus_v for t in tr]),
        "battery": np.concatenate([t.battery for t in tr]),
        "group_v": np.concatenate([t.group_v for t in tr]),
        "steps": np.concatenate([c.steps for c in chunks]),
        "status": status,
    }
    return arrays, [e for c in chunks for e in c.result.events]


def test_a_run_read_while_it_is_written_is_the_run_read_at_once(tmp_path: Path) -> None:
    """Every block of rows is read once, in order, and the status stored on change is
    forward-filled across the blocks exactly as a whole read fills it."""
    db = tmp_path / "run.sqlite"
    w = ReadWhileWriting(db, every=23)
    recorder: Recorder = w
    Runner(parse_config(scenario(30.0)), recorder=recorder, progress=False).run()
    first, last = w.chunks[0], w.chunks[-1]
    assert first.status == "running" and len(first.steps) == 0
    assert all(c.status == "running" for c in w.chunks[:-1]) and last.status == "ok"
    assert last.result.metrics and not first.result.metrics
    assert sum(1 for c in w.chunks if len(c.steps)) > 5  # really read in pieces

    whole = load_run(db)
    got, events = joined(w.chunks)
    n = len(whole.trace.t_s)
    assert got["steps"].tolist() == list(range(n))
    assert np.array_equal(got["t_s"], whole.trace.t_s)
    assert np.array_equal(got["bus_v"], whole.trace.bus_v)
    assert np.array_equal(got["battery"], whole.trace.battery, equal_nan=True)
    assert np.array_equal(got["group_v"], whole.trace.group_v, equal_nan=True)
    assert got["status"].keys() == whole.trace.status.keys()
    for ch, seq in whole.trace.status.items():
        assert [tuple(x) for x in got["status"][ch]] == [tuple(x) for x in seq], ch
    assert [(e.t_s, e.kind, e.battery) for e in events] == [
        (e.t_s, e.kind, e.battery) for e in whole.events
    ]
    assert events  # the scenario has events to carry


# ---------------------------------------------------------------- the dashboard follows
class PacedWriter(threading.Thread):
    """Writes a recorded run again into a new file through the real recorder, stopping at
    ``holds`` (sample counts) until the test lets it go on: the dashboard is checked while
    the writer is provably mid-run."""

    def __init__(self, src: Path, dst: Path, holds: tuple[int, ...]) -> None:
        super().__init__(daemon=True)
        self.src = Recording(src)
        self.raw: Result = load_run(src)
        self.dst, self.holds = dst, holds
        self.reached = {h: threading.Event() for h in holds}
        self.go = {h: threading.Event() for h in holds}
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            self._write()
        except BaseException as err:  # shown by the test
            self.error = err

    def _write(self) -> None:
        events = list(self.raw.events)
        config = RunTail(self.src.path).config
        with SQLiteRecorder(self.dst, commit_every_s=0.05) as rec:
            rec.start(config, self.raw.battery_names)
            for k in range(self.src.n_samples):
                s = self.src.sample(k)
                rec.record(s)
                due = [e for e in events if e.t_s <= s.t_s]
                events = events[len(due) :]
                rec.record_events(due)
                if k + 1 in self.reached:
                    rec.flush()
                    self.reached[k + 1].set()
                    assert self.go[k + 1].wait(30.0)
            rec.finish(self.raw.metrics)


@pytest.fixture
def paced(recording: Path, tmp_path: Path) -> Iterator[PacedWriter]:
    w = PacedWriter(recording, tmp_path / "growing.sqlite", holds=(50, 100))
    w.start()
    yield w
    for g in w.go.values():
        g.set()
    w.join(30.0)
    assert w.error is None, w.error


def test_the_dashboard_follows_a_run_while_it_is_written(paced: PacedWriter) -> None:
    assert paced.reached[50].wait(30.0)
    session = Session(LiveRun())
    c = app_client(session)
    try:
        live = session.open_path(paced.dst)
        rec = session.recording
        assert rec is not None and rec.following and session.follower is not None
        assert live.kind == "attached" and live.state == "running"
        assert rec.n_samples == 50
        assert c.get("/api/status").json()["kind"] == "attached"
        # read-only: nothing on the page paces or stops a run it only reads
        assert c.post("/api/pause", json={}, headers=OK).status_code == 409
        with c.websocket_connect(WS_URL) as ws:
            hello = ws.receive_json()
            assert hello["kind"] == "attached" and hello["battery_names"] == ["A", "B"]
            assert ws.receive_json()["state"] == "running"

        paced.go[50].set()  # the writer goes on: the dashboard picks the new rows up
        assert paced.reached[100].wait(30.0)
        wait_for(lambda: rec.n_samples == 100, what="the follower to read the next block")
        assert session.live is live and live.state == "running"
        assert live.status()["t_s"] == pytest.approx(float(paced.raw.trace.t_s[99]))

        generation = session.generation
        paced.go[100].set()  # the writer finishes: the run is reopened as a recording
        wait_for(lambda: session.generation > generation, what="the reopened recording")
        done = session.live
        assert done.kind == "recorded" and done.state == "finished"
        assert live.state == "finished"  # the followed view ended too, with the metrics
        n = len(paced.raw.trace.t_s)
        assert session.recording is not None and session.recording.n_samples == n
        assert [e["kind"] for e in done.events()] == [e.kind for e in paced.raw.events]
        assert [e["kind"] for e in live.events()] == [e.kind for e in paced.raw.events]
        at = c.get("/api/at", params={"t_s": 1e9}).json()
        assert at["index"] == n - 1
        assert rec.following is False
    finally:
        session.stop()


def test_switching_away_stops_following(paced: PacedWriter, recording: Path) -> None:
    assert paced.reached[50].wait(30.0)
    session = Session(LiveRun())
    try:
        session.open_path(paced.dst)
        follower, rec = session.follower, session.recording
        assert follower is not None and rec is not None
        session.open_path(recording)  # the page opens another recording
        assert not follower.is_alive() and not rec.following
        assert session.follower is None and session.live.kind == "recorded"
    finally:
        session.stop()


WRITER = textwrap.dedent(
    """
    import sys, time
    import numpy as np
    from packpilot.contract.record import StepSample
    from packpilot.io.telemetry import SQLiteRecorder

    rec = SQLiteRecorder(sys.argv[1], commit_every_s=0.05)
    rec.start({"pack": {"name": "dies"}, "sim": {"dt_s": 0.1}}, ["A", "B"])
    for k in range(50):
        bat = np.full((2, 12), 3.7)
        rec.record(StepSample(step=k, t_s=0.1 * k, bus_v=22.0, load_demand_a=5.0,
                              load_a=5.0, charger_v=0.0, charger_a=0.0, battery=bat,
                              group_v=np.full((2, 6), 3.7), status={}))
    rec.flush()
    print("written", flush=True)
    time.sleep(600)
    """
)


def test_a_writer_that_dies_shows_as_aborted(tmp_path: Path) -> None:
    """A killed `run` leaves its run `running` in the file; the follower sees its process gone,
    ends the view with the run shown as aborted, and reopens what was written."""
    from packpilot.contract.record import BATTERY_CHANNELS

    db = tmp_path / "dies.sqlite"
    code = WRITER.replace("12)", f"{len(BATTERY_CHANNELS)})")
    proc = subprocess.Popen([sys.executable, "-c", code, str(db)], stdout=subprocess.PIPE)
    session = Session(LiveRun())
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == b"written"
        live = session.open_path(db)
        assert live.kind == "attached" and live.state == "running"
        proc.kill()
        proc.wait(10)
        wait_for(lambda: live.state != "running", what="the follower to see the writer gone")
        assert live.state == "error" and "aborted" in (live.error or "")
        wait_for(lambda: session.live is not live, what="the reopened recording")
        assert session.live.kind == "recorded" and session.live.state == "error"
        assert session.recording is not None and session.recording.n_samples == 50
    finally:
        proc.kill()
        session.stop()


def test_the_dashboard_follows_the_bms_runtime_recording(tmp_path: Path) -> None:
    """The writer is the BMS runtime itself (`packpilot run --db`, here in lock-step with the
    twin on a virtual bus): the session attaches mid-flight, sees the periods recorded so far
    and then the later ones, and ends with exactly what the runtime recorded."""
    from packpilot.cli import scenario_path
    from packpilot.config import load_config
    from packpilot.runtime.lockstep import Lockstep, run_lockstep

    cfg = load_config(scenario_path(Path("uav_mission")))
    db = tmp_path / "run.sqlite"
    session = Session(LiveRun())
    seen: dict[int, int] = {}

    def hook(ls: Lockstep, k: int) -> None:
        if k in (100, 200):
            # What the recorder's 1 s commit does in real time; here the loop is held, and a
            # slow first period (a cold compile) may have moved its 25-sample flushes.
            recorder.flush()
        if k == 100:
            live = session.open_path(db)
            assert live.kind == "attached" and live.state == "running"
        if k in (100, 200):
            rec = session.recording
            assert rec is not None
            wait_for(lambda: rec.n_samples == k, what=f"{k} periods read")
            seen[k] = rec.n_samples

    try:
        with SQLiteRecorder(db, flush_every=25) as recorder:
            ls = run_lockstep(cfg, 300, recorder=recorder, hook=hook)
            recorder.finish(ls.bms.metrics())
        assert seen == {100: 100, 200: 200}
        wait_for(lambda: session.live.kind == "recorded", what="the reopened recording")
        assert session.live.state == "finished"
        assert session.recording is not None and session.recording.n_samples == 300
        assert [e["kind"] for e in session.live.events()] == [e.kind for e in ls.bms.events]
        assert ls.bms.events  # the flight's joins and stage changes were there to carry
    finally:
        session.stop()
