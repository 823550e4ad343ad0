"""SQLite telemetry: record synthetic steps, read them back exactly, export them."""

from __future__ import annotations

import csv
import math
import sqlite3
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.csv as pacsv
import pyarrow.parquet as pq
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Result, StatusValue, StepSample, Trace
from packpilot.errors import InputError
from packpilot.io.telemetry import (
    SQLiteRecorder,
    export_csv,
    export_parquet,
    list_runs,
    load_run,
    trace_to_csv,
)
from tests.budget import budget

NAMES = ["left", "right"]
N_C = len(BATTERY_CHANNELS)


def make_samples(n: int, *, aux: bool = False, seed: int = 0) -> list[StepSample]:
    """Two batteries, 3 and 2 groups (NaN pads the second), four kinds of status channel."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        bat = rng.normal(3.7, 0.3, size=(2, N_C))
        grp = rng.normal(3.6, 0.05, size=(2, 3))
        grp[1, 2] = np.nan
        if i == 3:
            bat[0, BATTERY_CHANNELS.index("temp_c")] = np.nan  # a lying sensor
        out.append(
            StepSample(
                step=i,
                t_s=0.1 * i,
                bus_v=float(rng.normal(14.8, 0.1)),
                load_demand_a=10.0,
                load_a=9.5 if i != 2 else math.nan,
                charger_v=0.0,
                charger_a=0.0,
                battery=bat,
                group_v=grp,
                status={
                    "stage": ("cc" if i < n // 2 else "cv", "idle"),
                    "limit_a": (1.5 * i, math.nan),
                    "tripped": (i % 3 == 0, False),
                    "count": (i, -i),
                },
                aux=rng.normal(12.8, 0.1, size=N_C) if aux else None,
            )
        )
    return out


EVENTS = [
    Event(t_s=0.2, kind="StageChanged", battery=0, message="cc -> cv", data={"from": "cc"}),
    Event(t_s=0.3, kind="Fault", battery=None, message="", data={"v": 1.5, "ok": False, "n": 3}),
    Event(t_s=0.3, kind="ProtectionTripped", battery=1, data={"x": None}),
]


def record_run(
    db: Path,
    samples: Sequence[StepSample],
    *,
    events: Sequence[Event] = EVENTS,
    flush_every: int = 4,
    metrics: dict[str, object] | None = None,
) -> int:
    with SQLiteRecorder(db, flush_every=flush_every) as rec:
        run_id = rec.start({"pack": {"n": 2}, "dt_s": 0.1}, NAMES)
        for i, s in enumerate(samples):
            rec.record(s)
            if i == 1:
                rec.record_events(events)
        rec.finish(metrics if metrics is not None else {"energy_j": 12.5, "trips": 1})
    return run_id


def status_equal(a: Sequence[StatusValue], b: Sequence[StatusValue]) -> bool:
    if len(a) != len(b):
        return False
    for x, y in zip(a, b, strict=True):
        if isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y):
            continue
        if type(x) is not type(y) or x != y:
            return False
    return True


def assert_same_trace(got: Trace, want: Trace) -> None:
    for name in ("t_s", "bus_v", "load_demand_a", "load_a", "charger_v", "charger_a"):
        np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=name)
    np.testing.assert_array_equal(got.battery, want.battery)
    np.testing.assert_array_equal(got.group_v, want.group_v)
    if want.aux is None:
        assert got.aux is None
    else:
        assert got.aux is not None
        np.testing.assert_array_equal(got.aux, want.aux)
    assert list(got.status) == list(want.status)
    for ch in want.status:
        assert len(got.status[ch]) == len(want.status[ch]), ch
        for g, w in zip(got.status[ch], want.status[ch], strict=True):
            assert status_equal(g, w), (ch, g, w)


def test_round_trip_is_exact(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    samples = make_samples(11, aux=True)
    run_id = record_run(db, samples)
    res = load_run(db)
    assert res.run_id == run_id
    assert res.battery_names == NAMES
    assert res.metrics == {"energy_j": 12.5, "trips": 1}
    assert res.events == EVENTS
    assert_same_trace(res.trace, Trace.from_samples(samples))


def test_nan_survives_as_nan(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    record_run(db, make_samples(5))
    tr = load_run(db).trace
    assert math.isnan(tr.load_a[2]) and not math.isnan(tr.load_a[1])
    assert math.isnan(tr.channel("temp_c")[3, 0])
    assert np.isnan(tr.group_v[:, 1, 2]).all() and not np.isnan(tr.group_v[:, 0, 2]).any()
    assert all(math.isnan(v[1]) for v in tr.status["limit_a"])  # type: ignore[arg-type]


def test_wal_mode_and_schema(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    record_run(db, make_samples(3))
    conn = sqlite3.connect(db)
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        tables = {r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        assert {"runs", "pack_samples", "battery_samples", "status_samples", "events"} <= tables
        # numbers stay SQL numbers, text stays text, NaN is NULL
        types = dict(
            conn.execute(
                "SELECT channel, group_concat(DISTINCT typeof(value)) FROM status_samples"
                " WHERE battery = 0 GROUP BY channel"
            ).fetchall()
        )
        assert types == {
            "stage": "text",
            "limit_a": "real",
            "tripped": "integer",
            "count": "integer",
        }
        assert conn.execute(
            "SELECT typeof(value) FROM status_samples WHERE channel='limit_a' AND battery=1 LIMIT 1"
        ).fetchone() == ("null",)
    finally:
        conn.close()


def test_several_runs_in_one_file(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    first = record_run(db, make_samples(4, seed=1), metrics={"n": 1})
    second = record_run(db, make_samples(7, seed=2), events=[], metrics={"n": 2})
    assert second > first
    runs = list_runs(db)
    assert [r["id"] for r in runs] == [first, second]
    assert [r["n_steps"] for r in runs] == [4, 7]
    assert all(r["status"] == "ok" and r["finished_at"] for r in runs)
    assert runs[0]["battery_names"] == NAMES
    assert runs[0]["config"] == {"pack": {"n": 2}, "dt_s": 0.1}
    assert set(runs[0]["versions"]) == {"packpilot", "numpy", "python"}
    assert runs[0]["started_at"].endswith("+00:00")
    latest = load_run(db)
    assert latest.run_id == second and latest.metrics == {"n": 2} and latest.events == []
    old = load_run(db, first)
    assert len(old.trace.t_s) == 4 and old.events == EVENTS
    assert_same_trace(old.trace, Trace.from_samples(make_samples(4, seed=1)))


def test_one_recorder_records_two_runs(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    with SQLiteRecorder(db, flush_every=3) as rec:
        a = rec.start({}, NAMES)
        for s in make_samples(5, seed=3):
            rec.record(s)
        rec.finish({})
        b = rec.start({}, ["solo"])
        one = [
            StepSample(i, float(i), 1.0, 0.0, 0.0, 0.0, 0.0, np.ones((1, N_C)), np.ones((1, 4)))
            for i in range(4)
        ]
        for s in one:
            rec.record(s)
        rec.finish({})
    assert load_run(db, a).trace.battery.shape == (5, 2, N_C)
    rb = load_run(db, b)
    assert rb.battery_names == ["solo"] and rb.trace.group_v.shape == (4, 1, 4)
    assert rb.trace.status == {} and rb.trace.aux is None


def _count(db: Path, table: str) -> int:
    conn = sqlite3.connect(db)
    try:
        return int(conn.execute(f"SELECT COUNT(*) FROM {table}").fetchone()[0])
    finally:
        conn.close()


def test_abandoned_run_keeps_flushed_rows_and_stays_running(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=10)
    rec.start({}, NAMES)
    for s in make_samples(25):
        rec.record(s)
    # A reader sees the two full flushes while the run is still going.
    assert _count(db, "pack_samples") == 20
    assert _count(db, "battery_samples") == 40
    assert list_runs(db)[0]["status"] == "running"
    rec.close()  # no finish(): the process "died" after flushing what it had
    runs = list_runs(db)
    assert runs[0]["status"] == "running" and runs[0]["finished_at"] is None
    assert runs[0]["n_steps"] == 25
    res = load_run(db)
    assert len(res.trace.t_s) == 25 and res.metrics == {}


def test_finish_error_keeps_buffer(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    rec = SQLiteRecorder(db, flush_every=100)
    rec.start({}, NAMES)
    for s in make_samples(7):
        rec.record(s)
    rec.record_events(EVENTS[:1])
    assert _count(db, "pack_samples") == 0
    rec.finish({"why": "plant diverged"}, status="error")
    rec.close()
    run = list_runs(db)[0]
    assert run["status"] == "error" and run["finished_at"] and run["n_steps"] == 7
    assert load_run(db).events == EVENTS[:1]


def test_exception_in_with_block_marks_error(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    with pytest.raises(ZeroDivisionError), SQLiteRecorder(db, flush_every=100) as rec:
        rec.start({}, NAMES)
        for s in make_samples(3):
            rec.record(s)
        _ = 1 / 0
    run = list_runs(db)[0]
    assert run["status"] == "error" and run["n_steps"] == 3
    assert "ZeroDivisionError" in run["metrics"]["error"]


def test_misuse_raises(tmp_path: Path) -> None:
    rec = SQLiteRecorder(tmp_path / "t.sqlite")
    with pytest.raises(RuntimeError, match="start"):
        rec.record(make_samples(1)[0])
    rec.start({}, NAMES)
    with pytest.raises(RuntimeError, match="in progress"):
        rec.start({}, NAMES)
    rec.close()
    with pytest.raises(RuntimeError, match="closed"):
        rec.finish({})
    with pytest.raises(ValueError, match="flush_every"):
        SQLiteRecorder(tmp_path / "u.sqlite", flush_every=0)


def test_mis_shaped_sample_leaves_no_partial_row(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    with SQLiteRecorder(db) as rec:
        rec.start({}, NAMES)
        good = make_samples(2)
        rec.record(good[0])
        bad = StepSample(1, 0.1, 1, 1, 1, 1, 1, np.ones((3, N_C)), np.ones((2, 3)))
        with pytest.raises(ValueError):
            rec.record(bad)
        rec.record(good[1])
        rec.finish({})
    assert len(load_run(db).trace.t_s) == 2


def test_numpy_scalars_and_odd_json_are_recorded(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    s = make_samples(1)[0]
    # Controllers may hand numpy scalars; the recorder must store them as plain values.
    status: dict[str, Any] = {
        "flag": (np.bool_(True), np.bool_(False)),
        "n": (np.int64(3), np.int32(4)),
    }
    odd = StepSample(0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, s.battery, s.group_v, status=status)
    with SQLiteRecorder(db) as rec:
        rec.start({"arr": np.arange(3), "path": Path("/x"), "f": np.float32(0.5)}, NAMES)
        rec.record(odd)
        rec.finish({"m": np.float64(2.0), "v": np.array([1.0, 2.0])})
    res = load_run(db)
    assert res.trace.status == {"flag": [(True, False)], "n": [(3, 4)]}
    assert res.metrics == {"m": 2.0, "v": [1.0, 2.0]}
    assert list_runs(db)[0]["config"] == {"arr": [0, 1, 2], "path": "/x", "f": 0.5}


def test_bad_inputs_name_the_file(tmp_path: Path) -> None:
    missing = tmp_path / "nope.sqlite"
    with pytest.raises(InputError, match=r"nope\.sqlite"):
        load_run(missing)
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(InputError, match=r"junk\.sqlite"):
        load_run(junk)
    with pytest.raises(InputError, match=r"junk\.sqlite"):
        SQLiteRecorder(junk)
    db = tmp_path / "t.sqlite"
    SQLiteRecorder(db).close()
    with pytest.raises(InputError, match="no runs"):
        load_run(db)
    record_run(db, make_samples(2))
    with pytest.raises(InputError, match="no run with id 99"):
        load_run(db, 99)


def test_run_without_samples_loads_empty(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    with SQLiteRecorder(db) as rec:
        rec.start({}, NAMES)
        rec.finish({"aborted": True}, status="error")
    res = load_run(db)
    assert res.trace.battery.shape == (0, 2, N_C) and len(res.trace.t_s) == 0


def expected_columns(n_groups: tuple[int, int], status: Sequence[str], aux: bool) -> list[str]:
    cols = ["step", "t_s", "bus_v", "load_demand_a", "load_a", "charger_v", "charger_a"]
    for b, name in enumerate(NAMES):
        cols += [f"{name}_{c}" for c in BATTERY_CHANNELS]
        cols += [f"{name}_g{g}_v" for g in range(n_groups[b])]
        cols += [f"{name}_{c}" for c in status]
    if aux:
        cols += [f"aux_{c}" for c in BATTERY_CHANNELS]
    return cols


STATUS = ("stage", "limit_a", "tripped", "count")


def test_export_csv(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    samples = make_samples(9, aux=True)
    record_run(db, samples)
    out = tmp_path / "run.csv"
    export_csv(db, out)
    with out.open(newline="") as fh:
        rows = list(csv.reader(fh))
    want_cols = expected_columns((3, 2), STATUS, aux=True)
    assert rows[0] == want_cols
    assert len(rows) == 1 + 9
    body = [dict(zip(rows[0], r, strict=True)) for r in rows[1:]]
    assert [int(r["step"]) for r in body] == list(range(9))
    assert float(body[4]["left_voltage_v"]) == samples[4].battery[0, 0]  # exact repr
    assert body[2]["load_a"] == "" and body[3]["left_temp_c"] == ""  # NaN -> empty cell
    assert body[0]["right_stage"] == "idle" and body[0]["left_tripped"] == "True"
    # pyarrow reads it too, with the same shape
    table = pacsv.read_csv(out)
    assert table.num_rows == 9 and table.column_names == want_cols


def test_export_parquet(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    samples = make_samples(6)
    first = record_run(db, samples)
    record_run(db, make_samples(2, seed=5))
    out = tmp_path / "run.parquet"
    export_parquet(db, out, run_id=first)
    table = pq.read_table(out)
    assert table.num_rows == 6
    assert table.column_names == expected_columns((3, 2), STATUS, aux=False)
    d = table.to_pydict()
    np.testing.assert_array_equal(d["right_soc"], [s.battery[1, 2] for s in samples])
    assert math.isnan(d["load_a"][2])  # NaN stays a float NaN, not a null
    assert d["left_stage"][0] == "cc" and d["right_count"][5] == -5
    assert d["left_tripped"][3] is True
    assert table.schema.metadata[b"packpilot.run_id"] == str(first).encode()


def test_trace_to_csv_without_database(tmp_path: Path) -> None:
    samples = make_samples(4)
    result = Result(NAMES, Trace.from_samples(samples), [], {})
    out = tmp_path / "trace.csv"
    trace_to_csv(result, out)
    table = pacsv.read_csv(out)
    assert table.num_rows == 4
    assert table.column_names == expected_columns((3, 2), STATUS, aux=False)


def test_wide_export_rejects_colliding_names(tmp_path: Path) -> None:
    s = make_samples(2)
    # battery "a_b" + channel "soc" would not collide, but two batteries with one name do
    result = Result(["x", "x"], Trace.from_samples(s), [], {})
    with pytest.raises(InputError, match="twice"):
        trace_to_csv(result, tmp_path / "c.csv")


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)


@budget(200)
@given(
    vals=st.lists(finite, min_size=N_C * 2 + 6 + 4, max_size=N_C * 2 + 6 + 4),
    flush_every=st.integers(1, 5),
)
def test_any_float_round_trips(vals: list[float], flush_every: int) -> None:
    bat = np.array(vals[: N_C * 2]).reshape(2, N_C)
    grp = np.array(vals[N_C * 2 : N_C * 2 + 4]).reshape(2, 2)
    pack = vals[N_C * 2 + 4 :]
    samples = [
        StepSample(i, pack[0], pack[1], pack[2], pack[3], pack[4], pack[5], bat, grp)
        for i in range(3)
    ]
    with tempfile.TemporaryDirectory() as d:
        db = Path(d) / "t.sqlite"
        record_run(db, samples, events=[], flush_every=flush_every)
        assert_same_trace(load_run(db).trace, Trace.from_samples(samples))


def test_recording_is_fast(tmp_path: Path) -> None:
    """36,000 steps of a 2-battery pack: measured ~0.7 s; fail only on a gross regression."""
    samples = make_samples(36_000)
    rec = SQLiteRecorder(tmp_path / "t.sqlite")
    rec.start({}, NAMES)
    t0 = time.perf_counter()
    for s in samples:
        rec.record(s)
    rec.finish({})
    elapsed = time.perf_counter() - t0
    rec.close()
    assert elapsed < 6.0, f"recording 36,000 steps took {elapsed:.2f} s"


def _one_battery(i: int, status: dict[str, Any]) -> StepSample:
    return StepSample(
        i, float(i), 1.0, 0.0, 0.0, 0.0, 0.0, np.ones((2, N_C)), np.ones((2, 1)), status=status
    )


def test_status_is_stored_on_change_and_forward_filled(tmp_path: Path) -> None:
    db = tmp_path / "t.sqlite"
    samples = []
    for i in range(50):
        st_: dict[str, Any] = {"mode": ("idle" if i < 30 else "run", "idle")}
        if i >= 10:
            st_["late"] = (math.nan, float(i // 20))  # appears at step 10
        samples.append(_one_battery(i, st_))
    record_run(db, samples, events=[], flush_every=7)
    # mode: 2 rows at step 0, 1 change at step 30; late: 2 rows at step 10, changes at 20, 40
    assert _count(db, "status_samples") == 3 + 4
    tr = load_run(db).trace
    assert_same_trace(tr, Trace.from_samples(samples))
    assert len(tr.status["late"]) == 40


STATUS_STRATEGIES = {
    "float": st.floats(allow_infinity=True, allow_nan=True, width=64),
    "int": st.one_of(st.none(), st.integers(-(2**62), 2**62)),
    "bool": st.one_of(st.none(), st.booleans()),
    "str": st.one_of(st.none(), st.text(max_size=5)),
}


@budget(200)
@given(n_steps=st.integers(1, 8), data=st.data())
def test_any_status_round_trips(n_steps: int, data: st.DataObject) -> None:
    """Channels keep one type each (as controllers do); values of that type survive exactly.

    Values repeat often (small pools) so the change-only storage is exercised.
    """
    kinds = data.draw(st.lists(st.sampled_from(sorted(STATUS_STRATEGIES)), min_size=3, max_size=3))
    pools = [data.draw(st.lists(STATUS_STRATEGIES[k], min_size=1, max_size=3)) for k in kinds]
    samples = []
    for i in range(n_steps):
        status = {
            f"c{j}": tuple(data.draw(st.sampled_from(pool)) for _ in range(2))
            for j, pool in enumerate(pools)
        }
        samples.append(_one_battery(i, status))
    with tempfile.TemporaryDirectory() as d:
        db = Path(d) / "t.sqlite"
        record_run(db, samples, events=[], flush_every=2)
        assert_same_trace(load_run(db).trace, Trace.from_samples(samples))


@pytest.mark.filterwarnings("ignore:status channel 'early'")
def test_late_status_channel_in_wide_exports(tmp_path: Path) -> None:
    samples = [
        _one_battery(i, {"late": ("on", "off")} if i >= 3 else {"early": (1, 2)}) for i in range(6)
    ]
    db = tmp_path / "t.sqlite"
    record_run(db, samples, events=[])
    out = tmp_path / "run.parquet"
    export_parquet(db, out)
    d = pq.read_table(out).to_pydict()
    # From the database the channel's steps are known: empty before it first appeared.
    assert d["left_late"] == [None, None, None, "on", "on", "on"]
    assert d["right_early"] == [2] * 6  # forward-filled to the end
    # In memory they are not (it has 3 values for 6 steps): left out, with a warning.
    with pytest.warns(UserWarning, match="late"):
        trace_to_csv(Result(NAMES, Trace.from_samples(samples), [], {}), tmp_path / "m.csv")
    assert "left_late" not in pacsv.read_csv(tmp_path / "m.csv").column_names


def test_samples_committed_counts_what_a_reader_can_see(tmp_path: Path) -> None:
    """What a watcher of a writer starting up reads: 0 with no file, no run or no sample yet,
    then the committed samples of the latest run only (buffered ones are not there yet)."""
    from packpilot.io.telemetry import samples_committed

    db = tmp_path / "grow.sqlite"
    assert samples_committed(db) == 0
    rec = SQLiteRecorder(db, flush_every=10**6, commit_every_s=1e9)
    try:
        assert samples_committed(db) == 0  # the schema, no run
        rec.start({}, NAMES)
        assert samples_committed(db) == 0
        for s in make_samples(7):
            rec.record(s)
        assert samples_committed(db) == 0  # buffered, not committed
        rec.flush()
        assert samples_committed(db) == 7
        rec.finish({})
        rec.start({}, NAMES)  # a second run: its own count
        rec.record(make_samples(1)[0])
        rec.flush()
        assert samples_committed(db) == 1
    finally:
        rec.close()


def test_reading_a_run_back_holds_no_row_list_of_the_whole_run(tmp_path: Path) -> None:
    """Issue #26 §3: ``load_run`` fetched every row as Python tuples before filling its arrays
    (a 1-day run: 2.4 GB peak for ``packpilot report``, 0.6 GB since). Rows now go into
    preallocated arrays in blocks: the reader's peak allocation stays within 2.5 times the
    arrays it returns."""
    import tracemalloc

    from packpilot.contract.record import BATTERY_CHANNELS, StepSample
    from packpilot.io.telemetry import SQLiteRecorder, load_run

    n, n_c = 60_000, len(BATTERY_CHANNELS)
    db = tmp_path / "long.sqlite"
    with SQLiteRecorder(db, flush_every=5000) as rec:
        rec.start({}, ["A", "B"])
        bat, grp = np.full((2, n_c), 3.7), np.full((2, 6), 3.7)
        for k in range(n):
            rec.record(StepSample(k, k * 0.1, 22.2, 10.0, 10.0, 0.0, 0.0, bat, grp))
        rec.finish({})
    tracemalloc.start()
    try:
        result = load_run(db)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    tr = result.trace
    arrays = sum(a.nbytes for a in vars(tr).values() if isinstance(a, np.ndarray))
    assert len(tr.t_s) == n and tr.battery.shape == (n, 2, n_c)
    # measured: 46.6 MB peak for 26 MB of arrays; 147.6 MB before (the rows as tuples)
    assert peak < 2.5 * arrays, (peak / 1e6, arrays / 1e6)
