"""A simulated run recorded from the trace's numbers writes the same database as from samples.

``Runner`` hands a SQLite recorder the numbers of each step (``record_numbers``: no sample is
built, the status is rendered and compared in bulk at the flush) instead of a
:class:`StepSample` per step. Every table must hold the same rows as the per-sample path
writes: the same scenario is recorded both ways (the other through a recorder that only
has ``record``) and the files compared table by table, on a pack with an aux battery (status
laid out over strings) and one without, with flushes of odd sizes between them.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from packpilot.config import load_config
from packpilot.contract.bms import Event
from packpilot.contract.record import StepSample
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


class SamplesOnly:
    """A recorder that takes samples only (the path every recorder without numbers takes)."""

    def __init__(self, inner: SQLiteRecorder) -> None:
        self.inner = inner

    def start(self, config: Mapping[str, Any], battery_names: Sequence[str]) -> int:
        return self.inner.start(config, battery_names)

    def record(self, sample: StepSample) -> None:
        self.inner.record(sample)

    def record_events(self, events: Sequence[Event]) -> None:
        self.inner.record_events(events)

    def finish(self, metrics: Mapping[str, Any], status: str = "ok") -> None:
        self.inner.finish(metrics, status)


def _record(example: str, duration_s: float, db: Path, numbers: bool, flush: int) -> None:
    cfg = load_config(EXAMPLES / f"{example}.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": duration_s, "progress": False})}
    )
    with SQLiteRecorder(db, flush_every=flush) as rec:
        recorder: Any = rec if numbers else SamplesOnly(rec)
        Runner(cfg, recorder=recorder, progress=False).run()


def _tables(db: Path) -> dict[str, list[tuple[Any, ...]]]:
    conn = sqlite3.connect(db)
    try:
        out = {
            t: conn.execute(f"SELECT * FROM {t} ORDER BY 1, 2, 3").fetchall()
            for t in ("pack_samples", "battery_samples", "aux_samples")
        }
        out["status_samples"] = conn.execute(
            "SELECT run_id, step, battery, channel, value, typeof(value) FROM status_samples"
            " ORDER BY run_id, step, channel, battery"
        ).fetchall()
        out["events"] = conn.execute(
            "SELECT run_id, t_s, kind, battery, message, data FROM events ORDER BY id"
        ).fetchall()
        runs = conn.execute("SELECT config, battery_names, channels, status_kinds FROM runs")
        out["runs"] = [tuple(json.loads(x) for x in row) for row in runs.fetchall()]
    finally:
        conn.close()
    return out


@pytest.mark.parametrize(
    ("example", "duration_s", "flush"),
    [("uav_mission", 120.0, 37), ("evtol_charging", 60.0, 500), ("smart_battery", 30.0, 1)],
)
def test_numbers_and_samples_write_the_same_database(
    tmp_path: Path, example: str, duration_s: float, flush: int
) -> None:
    fast, slow = tmp_path / "numbers.sqlite", tmp_path / "samples.sqlite"
    _record(example, duration_s, fast, numbers=True, flush=flush)
    _record(example, duration_s, slow, numbers=False, flush=flush)
    got, want = _tables(fast), _tables(slow)
    assert got.keys() == want.keys()
    for table in want:
        assert len(got[table]) == len(want[table]), table
        assert got[table] == want[table], table
    assert len(want["status_samples"]) > 0 and len(want["pack_samples"]) > 0
    a, b = load_run(fast), load_run(slow)
    assert list(a.trace.status) == list(b.trace.status)
    for ch in b.trace.status:
        assert repr(a.trace.status[ch]) == repr(b.trace.status[ch]), ch


def test_a_run_mixing_samples_and_numbers_is_refused(tmp_path: Path) -> None:
    import numpy as np

    from packpilot.contract.record import StatusLayout

    with SQLiteRecorder(tmp_path / "m.sqlite") as rec:
        rec.start({}, ["a"])
        rec.record(
            StepSample(0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, np.zeros((1, 13)), np.zeros((1, 1)))
        )
        layout = StatusLayout((("x", 0, "f", {}),), (0,), 1)
        with pytest.raises(RuntimeError, match="cannot follow"):
            rec.record_numbers(
                1, np.zeros(6), np.zeros((1, 13)), np.zeros((1, 1)), np.zeros((1, 1)), layout
            )


@pytest.mark.parametrize("flush", [1, 3, 64])
def test_every_kind_and_odd_number_gives_the_rows_of_record(tmp_path: Path, flush: int) -> None:
    """Status numbers drawn from a pool of awkward values (NaN, -0.0 and 0.0, 1.2 and 1.7 that
    render as the same int, label -1 as None), every kind, two batteries laid out over three
    strings (an aux string in between): ``record_numbers`` stores the rows ``record`` stores
    from the rendered samples."""
    import numpy as np

    from packpilot.contract.record import StatusLayout

    labels = {"names": ["low", "high", "hot"]}
    chans = (("f", 0, "f", labels), ("o", 1, "o", labels), ("i", 2, "i", labels),
             ("b", 3, "b", labels), ("l", 4, "l:names", labels), ("m", 5, "m", labels))  # fmt: skip
    layout = StatusLayout(chans, (0, 2), 3)
    pool = np.array([np.nan, -0.0, 0.0, 1.0, 1.2, 1.7, 2.0, -1.0])
    rng = np.random.default_rng(7)
    rows = pool[rng.integers(0, len(pool), (120, 2, 6))]
    rows[:, :, 2] = np.nan_to_num(rows[:, :, 2])  # an int channel never holds NaN
    rows[:, :, 5] = np.abs(np.nan_to_num(rows[:, :, 5]))  # a battery set: a bit mask
    rows[:40] = rows[0]  # a stretch where nothing moves
    dbs = {}
    for how in ("numbers", "samples"):
        db = dbs[how] = tmp_path / f"{how}.sqlite"
        with SQLiteRecorder(db, flush_every=flush) as rec:
            rec.start({}, ["a", "b"])
            for k, row in enumerate(rows):
                bat, grp, sc = np.full((2, 13), float(k)), np.zeros((2, 1)), np.full(6, 0.5 * k)
                if how == "numbers":
                    rec.record_numbers(k, sc, bat, grp, row, layout)
                else:
                    rec.record(StepSample(k, *sc.tolist(), bat, grp, layout.render(row)))
            rec.finish({})
    got, want = _tables(dbs["numbers"]), _tables(dbs["samples"])
    assert len(want["status_samples"]) > 120
    for table in want:
        assert got[table] == want[table], table


@pytest.mark.parametrize("n", [0, 1, 63, 64, 65, 200])
def test_multi_row_inserts_store_the_rows_of_executemany(tmp_path: Path, n: int) -> None:
    """``_insert`` sends 64 rows per statement: the table holds exactly the rows (and their
    SQLite types: NULL, INTEGER, REAL, TEXT) that one ``executemany`` of single rows gives."""
    from packpilot.io.telemetry import writer
    from packpilot.io.telemetry.schema import _SCHEMA, _STATUS_INSERT

    values: list[Any] = [None, 1, 2.5, "charge", float("nan"), -0.0, True]
    rows = [(1, k // 3, k % 3, f"ch{k % 5}", values[k % len(values)]) for k in range(n)]
    got = []
    for how in ("multi", "single"):
        conn = sqlite3.connect(tmp_path / f"{how}.sqlite")
        conn.executescript(_SCHEMA)
        with conn:
            if how == "multi":
                writer._insert(conn, _STATUS_INSERT, rows)
            else:
                conn.executemany(_STATUS_INSERT, rows)
        got.append(
            conn.execute(
                "SELECT run_id, step, battery, channel, value, typeof(value) FROM status_samples"
                " ORDER BY step, channel, battery"
            ).fetchall()
        )
        conn.close()
    assert len(got[0]) == n
    assert got[0] == got[1]
