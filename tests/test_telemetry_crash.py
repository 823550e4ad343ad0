"""Crash-safe telemetry (issue #18 §4) and storage failures (§3): commits every 0.5 s of wall
time, a run whose writer died reads back ``aborted``, a full disk / a directory / read-only
media is one clean error. The SIGKILL test of a real ``simulate --db`` is in
``tests/test_kill_simulate.py``."""

from __future__ import annotations

import multiprocessing
import sqlite3
import time
from pathlib import Path

import pytest

from packpilot.errors import InputError
from packpilot.io.telemetry import SQLiteRecorder, list_runs, liveness, load_run
from packpilot.report.html import run_info_from_db
from tests.test_telemetry_sqlite import NAMES, make_samples


def _rows(db: Path) -> int:
    with sqlite3.connect(db) as conn:
        return int(conn.execute("SELECT COUNT(*) FROM pack_samples").fetchone()[0])


def test_samples_are_committed_by_wall_time_not_only_by_count(tmp_path: Path) -> None:
    """flush_every = 500 kept up to 1.78 s of samples uncommitted; the wall clock now commits."""
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=10_000, commit_every_s=0.05)
    rec.start({}, NAMES)
    samples = make_samples(4)
    rec.record(samples[0])
    time.sleep(0.06)
    rec.record(samples[1])  # past the interval: both rows are committed now
    assert _rows(db) == 2
    rec.record(samples[2])  # within the interval: buffered
    assert _rows(db) == 2
    rec.finish({})
    rec.close()
    assert _rows(db) == 3


def test_the_default_commit_interval_is_at_most_a_second(tmp_path: Path) -> None:
    rec = SQLiteRecorder(tmp_path / "t.sqlite")
    assert 0 < rec.commit_every_s <= 1.0
    rec.close()


def _die_while_recording(db: str) -> None:
    rec = SQLiteRecorder(db)
    rec.start({}, NAMES)
    for s in make_samples(3):
        rec.record(s)
    rec.flush()
    import os

    os._exit(0)  # no finish, no close: as if killed


def test_a_run_whose_writer_died_is_aborted(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    proc = multiprocessing.get_context("fork").Process(target=_die_while_recording, args=(db,))
    proc.start()
    proc.join(30)
    (run,) = list_runs(db)
    assert run["status"] == "aborted"  # computed by a reader, the file is not touched
    assert run_info_from_db(db).status == "aborted"  # what the report's header shows
    assert load_run(db).trace.t_s.size == 3  # every committed row is there
    with sqlite3.connect(db) as conn:
        assert conn.execute("SELECT status FROM runs").fetchone()[0] == "running"
    SQLiteRecorder(db).close()  # a writer opening the file stores it
    with sqlite3.connect(db) as conn:
        status, finished = conn.execute("SELECT status, finished_at FROM runs").fetchone()
    assert status == "aborted" and finished is not None


def test_a_live_writer_stays_running(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db)
    rec.start({}, NAMES)
    rec.record(make_samples(1)[0])
    rec.flush()
    assert list_runs(db)[0]["status"] == "running"
    SQLiteRecorder(db).close()  # another writer does not abort a live one
    assert list_runs(db)[0]["status"] == "running"
    rec.finish({})
    rec.close()
    assert list_runs(db)[0]["status"] == "ok"


def test_writer_on_another_host_is_gone_after_a_stale_heartbeat() -> None:
    old = "2000-01-01T00:00:00.000+00:00"
    assert liveness.writer_gone(1, "elsewhere.example", old)
    now = liveness._dt.datetime.now(liveness._dt.UTC).isoformat()
    assert not liveness.writer_gone(1, "elsewhere.example", now)
    assert not liveness.writer_gone(None, None, None)  # an unstamped (older) run: unknown


def test_a_directory_as_db_is_a_clean_error(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is a directory"):
        SQLiteRecorder(tmp_path)


def test_a_full_disk_is_a_clean_error(tmp_path: Path) -> None:
    """SQLITE_FULL, made by capping the file's page count (the same error a full disk gives)."""
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=100_000, commit_every_s=1e9)
    rec.start({}, NAMES)
    conn = rec._connection()
    pages = conn.execute("PRAGMA page_count").fetchone()[0]
    conn.execute(f"PRAGMA max_page_count = {pages + 1}")
    for s in make_samples(400):
        rec.record(s)
    with pytest.raises(InputError, match=r"t\.sqlite: cannot write telemetry: the disk .* full"):
        rec.flush()
    rec.close()


def test_a_finished_run_on_read_only_media_can_be_read(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Read-only media cannot hold the WAL's -shm file, so ``mode=ro`` fails to open; the
    reader falls back to ``immutable``. (Root ignores permission bits, so the failing
    ``mode=ro`` open is simulated.)"""
    db = tmp_path / "t.sqlite"
    with SQLiteRecorder(db) as rec:
        rec.start({}, NAMES)
        for s in make_samples(5):
            rec.record(s)
        rec.finish({})
    real = sqlite3.connect

    def no_shm(database: str, *a: object, **kw: object) -> sqlite3.Connection:
        if "mode=ro" in database:
            raise sqlite3.OperationalError("unable to open database file")
        return real(database, *a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(sqlite3, "connect", no_shm)
    assert load_run(db).trace.t_s.size == 5
    assert list_runs(db)[0]["status"] == "ok"


def test_a_read_only_directory_is_refused_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The up-front check creates a file in the directory; on read-only media that fails."""
    import tempfile

    from packpilot.io.outputs import check_output

    def read_only(*a: object, **kw: object) -> tuple[int, str]:
        raise OSError(30, "Read-only file system")

    monkeypatch.setattr(tempfile, "mkstemp", read_only)
    with pytest.raises(InputError, match=r"--db .*cannot write in .*Read-only file system"):
        check_output(tmp_path / "x.sqlite", "--db")


def test_ctrl_c_inside_record_loses_at_most_that_row_and_no_traceback(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A KeyboardInterrupt can land between any two statements of ``record``. It used to leave
    a step counted in one buffer and not in another, and the final flush raised "zip() argument
    2 is shorter than argument 1" instead of the run ending "interrupted" (found by the Ctrl-C
    test once status recording grew). Now the row is complete or not there."""
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=10_000, commit_every_s=60.0)
    rec.start({}, NAMES)
    samples = make_samples(3)
    rec.record(samples[0])
    rec.record(samples[1])

    def interrupted(*args: object, **kw: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(rec, "_record_status", interrupted)
    with pytest.raises(KeyboardInterrupt):
        rec.record(samples[2])  # interrupted after its row, inside its status bookkeeping
    rec._steps.append(99)  # and a next row interrupted after its step, before it was counted
    rec.finish({}, status="interrupted")
    rec.close()
    assert _rows(db) == 3
    assert load_run(db).metrics == {}


@pytest.mark.parametrize("inside", ["_store_moved", "_store_rendered"])
def test_a_real_ctrl_c_inside_a_flush_ends_the_run_interrupted_with_every_row_once(
    tmp_path: Path, inside: str
) -> None:
    """CI caught ``simulate`` answering Ctrl-C with "UNIQUE constraint failed:
    status_samples..." and a traceback: the signal landed inside a flush, after some status
    rows were derived and before the bookkeeping that says so, and the run's final flush
    wrote them again. A real SIGINT is raised at that point now (the handler a terminal gives
    Python); the flush completes, then the interrupt ends the run as ``interrupted``."""
    import signal
    import threading

    from packpilot.config import load_config
    from packpilot.sim.runner import Runner

    assert threading.current_thread() is threading.main_thread()
    cfg = load_config(Path(__file__).resolve().parents[1] / "examples" / "uav_mission.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 3000.0, "progress": False})}
    )
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=200, commit_every_s=60.0)
    original = getattr(rec, inside)
    calls = [0]

    def with_ctrl_c(*args: object, **kw: object) -> object:
        calls[0] += 1
        out = original(*args, **kw)
        if calls[0] == 3:  # a flush well into the run, after this part of it has run
            signal.raise_signal(signal.SIGINT)
        return out

    setattr(rec, inside, with_ctrl_c)
    old = signal.signal(signal.SIGINT, signal.default_int_handler)  # xdist workers ignore it
    try:
        runner = Runner(cfg, recorder=rec, progress=False)
        with pytest.raises(KeyboardInterrupt):
            runner.run()
    finally:
        signal.signal(signal.SIGINT, old)
    rec.close()
    assert calls[0] >= 3
    run = list_runs(db)[0]
    assert run["status"] == "interrupted"
    with sqlite3.connect(db) as conn:
        steps = [r[0] for r in conn.execute("SELECT step FROM pack_samples ORDER BY step")]
    # every step recorded, once (the step whose recording was interrupted is in, not counted)
    assert runner.steps_done < 2000 and steps == list(range(runner.steps_done + 1))
