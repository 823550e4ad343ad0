"""Compiling kernels is said aloud and reported apart from the simulation (issue #25 §3, §6),
and recording telemetry reads only the status channels that changed (§4) with the same rows."""

from __future__ import annotations

import dataclasses
import io
import sqlite3
import time
from pathlib import Path
from typing import Any

import numba
import pytest
from numba.core import event as nb_event

from packpilot.buildclock import COMPILING, _Announcer, announce_compiles, build_seconds
from packpilot.config import load_config
from packpilot.contract.record import StepSample
from packpilot.io.telemetry import SQLiteRecorder
from packpilot.sim.runner import Runner

ROOT = Path(__file__).resolve().parents[1]


def _fresh_kernel() -> Any:
    """A function numba has never seen (no cache): calling it compiles it."""

    def f(x: float) -> float:
        acc = 0.0
        for k in range(10):
            acc += x * k
        return acc

    return numba.njit(f)


def test_a_compile_is_announced_and_a_compiled_call_is_silent() -> None:
    out = io.StringIO()
    fn = _fresh_kernel()
    with announce_compiles(out):
        assert fn(2.0) == 90.0
    text = out.getvalue()
    assert text.startswith(COMPILING), text
    assert "1 kernels compiled, last" in text and "test_build_time" in text
    quiet = io.StringIO()
    with announce_compiles(quiet):
        assert fn(3.0) == 135.0  # compiled already: nothing to say
    assert quiet.getvalue() == ""


@pytest.mark.parametrize("stream", ["file", "memory"])
def test_a_long_compile_gets_a_heartbeat(stream: str, tmp_path: Path) -> None:
    """The announcer speaks at least every ``every_s`` while a kernel compiles (the compile is
    stood in for by real numba events around a sleep: its length must be known), from a child
    process when the stream is a file (numba can hold the GIL for seconds), else a thread;
    and falls silent when the compile is over."""
    path = tmp_path / "stderr.txt"
    with path.open("w") as f:
        out: Any = f if stream == "file" else io.StringIO()
        ann = _Announcer(out, every_s=0.1)
        data = {"dispatcher": _fresh_kernel(), "args": (), "return_type": None}
        try:
            ann.on_start(nb_event.Event("numba:compile", nb_event.EventStatus.START, data))
            time.sleep(1.0)
            ann.on_end(nb_event.Event("numba:compile", nb_event.EventStatus.END, data))
            time.sleep(0.5)  # compiled: nothing more to say
        finally:
            ann.close()
        text = path.read_text() if stream == "file" else out.getvalue()
    lines = text.splitlines()
    beats = [x for x in lines if "0 kernels compiled, now" in x]
    assert len(beats) >= 4, lines
    assert lines[-1].startswith(f"{COMPILING}: 1 kernels compiled, last"), lines


def test_wall_time_is_the_simulation_alone() -> None:
    """A kernel compiled during the run (here by a hook) counts in ``build_time_s``, not in
    ``wall_time_s``."""
    cfg = load_config(ROOT / "examples" / "smart_battery.toml")
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": 2.0})})
    Runner(cfg).run()  # the scenario's own kernels: compiled or loaded before we measure
    fn = _fresh_kernel()
    spent: list[float] = []

    def compile_once(runner: Runner, t: float) -> None:
        if not spent:
            t0 = time.perf_counter()
            fn(1.0)
            spent.append(time.perf_counter() - t0)

    b0 = build_seconds()
    t0 = time.perf_counter()
    res = Runner(cfg, hooks=[compile_once]).run()
    elapsed = time.perf_counter() - t0
    assert spent and spent[0] > 0.0
    assert res.build_time_s >= 0.9 * spent[0]
    assert build_seconds() - b0 >= 0.9 * spent[0]
    assert res.metrics["wall_time_s"] <= elapsed - 0.9 * spent[0]
    assert res.metrics["wall_time_s"] > 0.0


class _Plain:
    """A recorder in front of SQLite that hands it every channel of every step (a plain dict,
    as before the status row named what changed)."""

    def __init__(self, inner: SQLiteRecorder) -> None:
        self.inner = inner

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)

    def record(self, sample: StepSample) -> None:
        full = {k: list(v) for k, v in sample.status.items()}
        self.inner.record(dataclasses.replace(sample, status=full))


def _status_rows(db: Path) -> list[tuple[Any, ...]]:
    with sqlite3.connect(db) as conn:
        rows = conn.execute(
            "SELECT step, battery, channel, value, typeof(value) FROM status_samples"
            " ORDER BY step, channel, battery"
        ).fetchall()
        kinds = conn.execute("SELECT status_kinds FROM runs").fetchall()
    return [*rows, *kinds]


def test_db_records_the_same_status_rows_reading_only_changed_channels(tmp_path: Path) -> None:
    cfg = load_config(ROOT / "examples" / "uav_mission.toml")
    sim = {"duration_s": 1500.0, "progress": False}  # through take-off, flight and landing
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update=sim)})
    with SQLiteRecorder(tmp_path / "changed.sqlite") as rec:
        Runner(cfg, recorder=rec).run()
    with SQLiteRecorder(tmp_path / "plain.sqlite") as rec:
        Runner(cfg, recorder=_Plain(rec)).run()  # type: ignore[arg-type]
    changed = _status_rows(tmp_path / "changed.sqlite")
    assert len(changed) > 1000
    assert changed == _status_rows(tmp_path / "plain.sqlite")
