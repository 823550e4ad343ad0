"""SQLite telemetry: record a run while it runs, read it back as a ``Result``, export it.

Why SQLite: one file, no server, safe to read while a run writes (WAL mode), and a crashed run
keeps whatever was flushed. Writes are buffered and sent with ``executemany`` every
``flush_every`` samples so recording costs far less than simulating. The schema is documented in
``docs/telemetry.md``; bump ``SCHEMA_VERSION`` when it changes.
"""

from __future__ import annotations

import csv
import datetime as _dt
import importlib.metadata
import json
import math
import platform
import sqlite3
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.record import BATTERY_CHANNELS, Result, StatusValue, StepSample, Trace
from packpilot.control.types import Event
from packpilot.errors import InputError

SCHEMA_VERSION = 1

PACK_COLUMNS: tuple[str, ...] = (
    "t_s",
    "bus_v",
    "load_demand_a",
    "load_a",
    "charger_v",
    "charger_a",
)

_BAT_COLS = ", ".join(f"{c} REAL" for c in BATTERY_CHANNELS)

_SCHEMA = f"""
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    started_at TEXT NOT NULL,
    finished_at TEXT,
    status TEXT NOT NULL,
    config TEXT NOT NULL,
    versions TEXT NOT NULL,
    battery_names TEXT NOT NULL,
    metrics TEXT,
    channels TEXT NOT NULL,
    status_kinds TEXT
);
CREATE TABLE IF NOT EXISTS pack_samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    step INTEGER NOT NULL,
    t_s REAL, bus_v REAL, load_demand_a REAL, load_a REAL, charger_v REAL, charger_a REAL,
    PRIMARY KEY (run_id, step)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS battery_samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    step INTEGER NOT NULL,
    battery INTEGER NOT NULL,
    {_BAT_COLS},
    group_v BLOB NOT NULL,
    PRIMARY KEY (run_id, step, battery)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS aux_samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    step INTEGER NOT NULL,
    {_BAT_COLS},
    PRIMARY KEY (run_id, step)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS status_samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    step INTEGER NOT NULL,
    battery INTEGER NOT NULL,
    channel TEXT NOT NULL,
    value,
    PRIMARY KEY (run_id, step, channel, battery)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    run_id INTEGER NOT NULL REFERENCES runs(id),
    t_s REAL,
    kind TEXT NOT NULL,
    battery INTEGER,
    message TEXT NOT NULL,
    data TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS events_run ON events (run_id, id);
"""

_PACK_INSERT = f"INSERT INTO pack_samples VALUES ({', '.join('?' * (2 + len(PACK_COLUMNS)))})"
_BAT_INSERT = f"INSERT INTO battery_samples VALUES ({', '.join('?' * (4 + len(BATTERY_CHANNELS)))})"
_AUX_INSERT = f"INSERT INTO aux_samples VALUES ({', '.join('?' * (2 + len(BATTERY_CHANNELS)))})"
_STATUS_INSERT = "INSERT INTO status_samples VALUES (?, ?, ?, ?, ?)"
_EVENT_INSERT = (
    "INSERT INTO events (run_id, t_s, kind, battery, message, data) VALUES (?, ?, ?, ?, ?, ?)"
)


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _json_default(obj: Any) -> Any:
    """Make numpy values, paths and other odd config values JSON-able instead of crashing."""
    if isinstance(obj, np.ndarray | np.generic):
        return obj.tolist()
    if isinstance(obj, Mapping):
        return dict(obj)
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    return str(obj)


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=_json_default)


def _versions() -> dict[str, str]:
    try:
        pp = importlib.metadata.version("packpilot")
    except importlib.metadata.PackageNotFoundError:
        pp = "unknown"
    return {"packpilot": pp, "numpy": np.__version__, "python": platform.python_version()}


_UNSET = object()


def _status_cell(value: Any) -> tuple[StatusValue, str]:
    """Value to store (numbers as SQL numbers, text as TEXT, None/NaN as NULL) and its kind."""
    if value is None:
        return None, "none"
    if isinstance(value, bool | np.bool_):
        return int(bool(value)), "bool"
    if isinstance(value, int | np.integer):
        return int(value), "int"
    if isinstance(value, float | np.floating):
        f = float(value)
        return (None if math.isnan(f) else f), "float"
    return str(value), "str"


def _check_schema(conn: sqlite3.Connection, path: Path | str) -> None:
    row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    if row is None or row[0] != str(SCHEMA_VERSION):
        found = "none" if row is None else row[0]
        raise InputError(
            f"{path}: telemetry schema version {found}, this PackPilot reads {SCHEMA_VERSION}"
        )


class SQLiteRecorder:
    """The default ``Recorder``: runs, samples and events in one SQLite file (WAL mode).

    Several runs may share one file. A run is inserted with status ``running`` at ``start`` and
    committed at once, so a run that dies without ``finish`` stays visible as ``running`` with
    every flushed sample; ``finish(status="error")`` marks it failed. Leaving a ``with`` block
    on an exception finishes an unfinished run with status ``error``.
    """

    def __init__(self, path: Path | str, *, flush_every: int = 500) -> None:
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        self.path = Path(path)
        self.flush_every = flush_every
        conn = sqlite3.connect(self.path, isolation_level=None)
        try:
            conn.execute("PRAGMA journal_mode=WAL")
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.executescript(_SCHEMA)
            conn.execute(
                "INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),)
            )
            _check_schema(conn, self.path)
        except sqlite3.DatabaseError as err:
            conn.close()
            raise InputError(f"{self.path}: not a PackPilot telemetry database ({err})") from err
        except InputError:
            conn.close()
            raise
        self._conn: sqlite3.Connection | None = conn
        self._run_id: int | None = None
        self._pending = 0
        self._steps: list[int] = []
        self._aux_steps: list[int] = []
        self._pack_buf: NDArray[np.float64] | None = None
        self._bat_buf: NDArray[np.float64] | None = None
        self._grp_buf: NDArray[np.float64] | None = None
        self._aux_buf: NDArray[np.float64] | None = None
        self._status_rows: list[tuple[Any, ...]] = []
        self._event_rows: list[tuple[Any, ...]] = []
        self._status_kinds: dict[str, set[str]] = {}
        self._status_prev: dict[tuple[str, int], Any] = {}
        self._status_prev_seq: dict[str, tuple[Any, ...]] = {}

    @property
    def run_id(self) -> int | None:
        """The run being recorded, or None between runs."""
        return self._run_id

    def _connection(self) -> sqlite3.Connection:
        if self._conn is None:
            raise RuntimeError(f"telemetry recorder for {self.path} is closed")
        return self._conn

    def _require_run(self) -> int:
        if self._run_id is None:
            raise RuntimeError("no run in progress: call start() first")
        return self._run_id

    def start(self, config: Mapping[str, Any], battery_names: Sequence[str]) -> int:
        """Insert a new run (status ``running``) and return its id."""
        conn = self._connection()
        if self._run_id is not None:
            raise RuntimeError(f"run {self._run_id} is still in progress; finish() it first")
        cur = conn.execute(
            "INSERT INTO runs (started_at, status, config, versions, battery_names, channels)"
            " VALUES (?, 'running', ?, ?, ?, ?)",
            (
                _utc_now(),
                _dumps(config),
                _dumps(_versions()),
                _dumps(list(battery_names)),
                _dumps(list(BATTERY_CHANNELS)),
            ),
        )
        run_id = cur.lastrowid
        assert run_id is not None
        self._run_id = run_id
        self._status_kinds = {}
        self._status_prev = {}
        self._status_prev_seq = {}
        self._bat_buf = None  # re-sized from the first sample of the new run
        return run_id

    def _alloc(self, sample: StepSample) -> None:
        """Size the sample buffers from the first sample of a run (group count is per pack)."""
        n, shape_b, shape_g = self.flush_every, sample.battery.shape, sample.group_v.shape
        self._pack_buf = np.empty((n, len(PACK_COLUMNS)))
        self._bat_buf = np.empty((n, *shape_b))
        self._grp_buf = np.empty((n, *shape_g))
        self._aux_buf = np.full((n, len(BATTERY_CHANNELS)), np.nan)

    def record(self, sample: StepSample) -> None:
        """Buffer one step (copied into arrays); flush to disk every ``flush_every`` samples."""
        run_id = self._require_run()
        k = self._pending
        if self._bat_buf is None:
            self._alloc(sample)
        assert self._pack_buf is not None and self._bat_buf is not None
        assert self._grp_buf is not None and self._aux_buf is not None
        step = int(sample.step)
        self._pack_buf[k] = (
            sample.t_s,
            sample.bus_v,
            sample.load_demand_a,
            sample.load_a,
            sample.charger_v,
            sample.charger_a,
        )
        self._bat_buf[k] = sample.battery
        self._grp_buf[k] = sample.group_v
        self._steps.append(step)  # only now: a mis-shaped sample above leaves no partial row
        if sample.aux is not None:
            self._aux_buf[k] = sample.aux
            self._aux_steps.append(k)
        if sample.status:
            self._record_status(run_id, step, sample.status)
        self._pending = k + 1
        if self._pending >= self.flush_every:
            self.flush()

    def _record_status(self, run_id: int, step: int, status: Mapping[str, Sequence[Any]]) -> None:
        """Store a status value only when it differs from the last one stored (same type too).

        Most channels (stage, mode, tripped flags) change a few times per run; writing every
        step made status the bulk of the rows. Readers forward-fill (see docs/telemetry.md).
        """
        kinds = self._status_kinds
        prev = self._status_prev
        prev_seq = self._status_prev_seq
        rows = self._status_rows
        for channel, seq in status.items():
            values = tuple(seq)
            # Whole-tuple compare in C first: an unchanged channel costs one comparison. It
            # treats 1 == 1.0 == True as unchanged, so a change of type alone is not recorded.
            if prev_seq.get(channel) == values:
                continue
            prev_seq[channel] = values
            seen = kinds.get(channel)
            if seen is None:
                seen = kinds[channel] = set()
            for i, v in enumerate(values):
                key = (channel, i)
                p = prev.get(key, _UNSET)
                if type(v) is type(p) and (v == p or (v != v and p != p)):
                    continue
                prev[key] = v
                if type(v) is float:
                    seen.add("float")
                    rows.append((run_id, step, i, channel, None if v != v else v))
                elif type(v) is str:
                    seen.add("str")
                    rows.append((run_id, step, i, channel, v))
                else:
                    stored, kind = _status_cell(v)
                    seen.add(kind)
                    rows.append((run_id, step, i, channel, stored))

    def record_events(self, events: Sequence[Event]) -> None:
        """Buffer events; they are written with the next flush."""
        run_id = self._require_run()
        for e in events:
            self._event_rows.append(
                (
                    run_id,
                    float(e.t_s),
                    e.kind,
                    None if e.battery is None else int(e.battery),
                    e.message,
                    _dumps(dict(e.data)),
                )
            )

    def _sample_rows(
        self, run_id: int
    ) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]], list[tuple[Any, ...]]]:
        """Turn the buffered arrays into pack, battery and aux rows (vectorized where it pays)."""
        k = self._pending
        if k == 0 or self._bat_buf is None:
            return [], [], []
        assert self._pack_buf is not None and self._grp_buf is not None
        assert self._aux_buf is not None
        steps = self._steps
        pack = [
            (run_id, st, *row) for st, row in zip(steps, self._pack_buf[:k].tolist(), strict=True)
        ]
        n_b = self._bat_buf.shape[1]
        # Group voltages as one little-endian float64 BLOB per row: exact, NaN-preserving and
        # ~50x cheaper than JSON text or a long table (see docs/telemetry.md for the numbers).
        flat_g = np.ascontiguousarray(self._grp_buf[:k].reshape(k * n_b, -1), dtype="<f8")
        gblob = [row.tobytes() for row in flat_g]
        flat_b = self._bat_buf[:k].reshape(k * n_b, -1).tolist()
        bat = [
            (run_id, steps[j // n_b], j % n_b, *row, g)
            for j, (row, g) in enumerate(zip(flat_b, gblob, strict=True))
        ]
        aux = [(run_id, steps[j], *self._aux_buf[j].tolist()) for j in self._aux_steps]
        return pack, bat, aux

    def flush(self) -> None:
        """Write every buffered row in one transaction."""
        conn = self._connection()
        if not (self._pending or self._event_rows):
            return
        run_id = self._run_id
        pack, bat, aux = self._sample_rows(run_id) if run_id is not None else ([], [], [])
        conn.execute("BEGIN")
        try:
            conn.executemany(_PACK_INSERT, pack)
            conn.executemany(_BAT_INSERT, bat)
            if aux:
                conn.executemany(_AUX_INSERT, aux)
            if self._status_rows:
                conn.executemany(_STATUS_INSERT, self._status_rows)
            if self._event_rows:
                conn.executemany(_EVENT_INSERT, self._event_rows)
            if run_id is not None and self._status_kinds:
                conn.execute(
                    "UPDATE runs SET status_kinds = ? WHERE id = ?",
                    (_dumps({k: sorted(v) for k, v in self._status_kinds.items()}), run_id),
                )
        except BaseException:
            conn.execute("ROLLBACK")
            raise
        conn.execute("COMMIT")
        self._steps.clear()
        self._aux_steps.clear()
        if self._aux_buf is not None:
            self._aux_buf.fill(np.nan)
        self._status_rows.clear()
        self._event_rows.clear()
        self._pending = 0

    def finish(self, metrics: Mapping[str, Any], status: str = "ok") -> None:
        """Flush, then stamp the run with its end time, status and metrics."""
        conn = self._connection()
        run_id = self._require_run()
        try:
            self.flush()
        finally:
            conn.execute(
                "UPDATE runs SET finished_at = ?, status = ?, metrics = ? WHERE id = ?",
                (_utc_now(), status, _dumps(dict(metrics)), run_id),
            )
            self._run_id = None

    def close(self) -> None:
        """Flush what is buffered and close; an unfinished run stays ``running``."""
        if self._conn is None:
            return
        try:
            self.flush()
        finally:
            self._conn.close()
            self._conn = None

    def __enter__(self) -> SQLiteRecorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc is not None and self._run_id is not None and self._conn is not None:
                self.finish({"error": f"{type(exc).__name__}: {exc}"}, status="error")
        finally:
            self.close()


# --------------------------------------------------------------------------- reading back


def _open_ro(path: Path | str) -> sqlite3.Connection:
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: telemetry database not found")
    try:
        conn = sqlite3.connect(f"{p.resolve().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error as err:
        raise InputError(f"{p}: cannot open telemetry database ({err})") from err
    try:
        conn.execute("SELECT 1 FROM runs LIMIT 1").fetchall()
        _check_schema(conn, p)
    except sqlite3.DatabaseError as err:
        conn.close()
        raise InputError(f"{p}: not a PackPilot telemetry database ({err})") from err
    except InputError:
        conn.close()
        raise
    return conn


def _resolve_run(conn: sqlite3.Connection, path: Path | str, run_id: int | None) -> int:
    if run_id is None:
        row = conn.execute("SELECT MAX(id) FROM runs").fetchone()
        if row is None or row[0] is None:
            raise InputError(f"{path}: telemetry database holds no runs")
        return int(row[0])
    if conn.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is None:
        raise InputError(f"{path}: no run with id {run_id}")
    return run_id


def _float_matrix(rows: list[tuple[Any, ...]], width: int) -> NDArray[np.float64]:
    """Rows of REAL/NULL into a float array; NULL (how SQLite stores NaN) becomes NaN."""
    if not rows:
        return np.empty((0, width), dtype=np.float64)
    return np.array(rows, dtype=np.float64)


def _restore_status(value: Any, kinds: set[str]) -> StatusValue:
    if value is None:
        return math.nan if ("float" in kinds and "none" not in kinds) else None
    if isinstance(value, int):
        numeric = kinds & {"bool", "int", "float"}
        if numeric == {"bool"}:
            return bool(value)
        if "float" in numeric and "int" not in numeric and "bool" not in numeric:
            return float(value)
    return value  # type: ignore[no-any-return]


def _forward_fill_status(
    rows: list[tuple[str, int, int, Any]],
    steps: NDArray[np.int64],
    kinds: dict[str, set[str]],
) -> dict[str, list[Sequence[StatusValue]]]:
    """Rebuild one tuple per step per channel from change-only rows, from its first step on."""
    by_channel: dict[str, dict[int, list[tuple[int, StatusValue]]]] = {}
    for channel, step, b, value in rows:
        restored = _restore_status(value, kinds.get(channel, set()))
        by_channel.setdefault(channel, {}).setdefault(step, []).append((b, restored))
    step_list = steps.tolist()
    out: dict[str, list[Sequence[StatusValue]]] = {}
    # The recorder's channel order (first seen), as Trace.from_samples keeps it.
    for channel in [*kinds, *sorted(set(by_channel) - set(kinds))]:
        changes = by_channel.get(channel)
        if not changes:
            continue
        first = min(changes)
        current: list[StatusValue] = []
        seqs: list[Sequence[StatusValue]] = []
        last: tuple[StatusValue, ...] = ()
        for st in step_list:
            if st < first:
                continue
            upd = changes.get(st)
            if upd is not None:
                for b, v in upd:
                    while len(current) <= b:
                        current.append(None)
                    current[b] = v
                last = tuple(current)
            seqs.append(last)
        out[channel] = seqs
    return out


def load_run(path: Path | str, run_id: int | None = None) -> Result:
    """Rebuild a run's ``Result`` (latest run when ``run_id`` is None).

    Known losses: a status value that was ``None`` in a channel that also carried NaN comes
    back as ``None`` (SQLite stores NaN as NULL); status is stored on change, so a channel runs
    from the first step that carried it to the end of the run, and a per-step sequence never
    shrinks (a battery index once seen keeps its last value).
    """
    return _load(path, run_id)[0]


def _load(path: Path | str, run_id: int | None) -> tuple[Result, NDArray[np.int64]]:
    """``load_run`` plus the recorded step numbers (the Trace has no step column)."""
    conn = _open_ro(path)
    try:
        rid = _resolve_run(conn, path, run_id)
        names_j, metrics_j, kinds_j, channels_j = conn.execute(
            "SELECT battery_names, metrics, status_kinds, channels FROM runs WHERE id = ?", (rid,)
        ).fetchone()
        names: list[str] = json.loads(names_j)
        if json.loads(channels_j) != list(BATTERY_CHANNELS):
            raise InputError(
                f"{path}: run {rid} was recorded with battery channels {json.loads(channels_j)},"
                f" this version expects {list(BATTERY_CHANNELS)}"
            )
        n_b = len(names)
        n_c = len(BATTERY_CHANNELS)
        pack = conn.execute(
            f"SELECT step, {', '.join(PACK_COLUMNS)} FROM pack_samples WHERE run_id = ?"
            " ORDER BY step",
            (rid,),
        ).fetchall()
        pm = _float_matrix(pack, 1 + len(PACK_COLUMNS))
        steps = np.array([r[0] for r in pack], dtype=np.int64)
        n_s = len(steps)

        bat_rows = conn.execute(
            f"SELECT step, battery, {', '.join(BATTERY_CHANNELS)}, group_v FROM battery_samples"
            " WHERE run_id = ? ORDER BY step, battery",
            (rid,),
        ).fetchall()
        battery = np.full((n_s, n_b, n_c), np.nan)
        max_groups = max((len(r[-1]) // 8 for r in bat_rows), default=0)
        group_v = np.full((n_s, n_b, max_groups), np.nan)
        if bat_rows:
            si = np.searchsorted(steps, np.array([r[0] for r in bat_rows], dtype=np.int64))
            bi = np.array([r[1] for r in bat_rows], dtype=np.int64)
            battery[si, bi, :] = _float_matrix([r[2:-1] for r in bat_rows], n_c)
            blobs = [r[-1] for r in bat_rows]
            if all(len(b) == 8 * max_groups for b in blobs):
                gm = np.frombuffer(b"".join(blobs), dtype="<f8").reshape(len(blobs), max_groups)
                group_v[si, bi, :] = gm
            else:
                for j, blob in enumerate(blobs):
                    g = np.frombuffer(blob, dtype="<f8")
                    group_v[si[j], bi[j], : len(g)] = g

        aux_rows = conn.execute(
            f"SELECT step, {', '.join(BATTERY_CHANNELS)} FROM aux_samples WHERE run_id = ?"
            " ORDER BY step",
            (rid,),
        ).fetchall()
        aux: NDArray[np.float64] | None = None
        if aux_rows:
            aux = np.full((n_s, n_c), np.nan)
            ai = np.searchsorted(steps, np.array([r[0] for r in aux_rows], dtype=np.int64))
            aux[ai, :] = _float_matrix([r[1:] for r in aux_rows], n_c)

        kinds = {k: set(v) for k, v in json.loads(kinds_j or "{}").items()}
        status = _forward_fill_status(
            conn.execute(
                "SELECT channel, step, battery, value FROM status_samples WHERE run_id = ?"
                " ORDER BY channel, step, battery",
                (rid,),
            ).fetchall(),
            steps,
            kinds,
        )

        events = [
            Event(
                t_s=t_s if t_s is not None else math.nan,
                kind=kind,
                battery=b,
                message=message,
                data=json.loads(data),
            )
            for t_s, kind, b, message, data in conn.execute(
                "SELECT t_s, kind, battery, message, data FROM events WHERE run_id = ? ORDER BY id",
                (rid,),
            )
        ]
    finally:
        conn.close()

    trace = Trace(
        t_s=pm[:, 1].copy(),
        bus_v=pm[:, 2].copy(),
        load_demand_a=pm[:, 3].copy(),
        load_a=pm[:, 4].copy(),
        charger_v=pm[:, 5].copy(),
        charger_a=pm[:, 6].copy(),
        battery=battery,
        group_v=group_v,
        status=status,
        aux=aux,
    )
    result = Result(
        battery_names=names,
        trace=trace,
        events=events,
        metrics=json.loads(metrics_j) if metrics_j else {},
        run_id=rid,
    )
    return result, steps


def list_runs(path: Path | str) -> list[dict[str, Any]]:
    """Every run in the file, oldest first, with its JSON columns decoded and its step count."""
    conn = _open_ro(path)
    try:
        rows = conn.execute(
            "SELECT id, started_at, finished_at, status, config, versions, battery_names,"
            " metrics, (SELECT COUNT(*) FROM pack_samples p WHERE p.run_id = runs.id)"
            " FROM runs ORDER BY id"
        ).fetchall()
    finally:
        conn.close()
    return [
        {
            "id": r[0],
            "started_at": r[1],
            "finished_at": r[2],
            "status": r[3],
            "config": json.loads(r[4]),
            "versions": json.loads(r[5]),
            "battery_names": json.loads(r[6]),
            "metrics": json.loads(r[7]) if r[7] else None,
            "n_steps": r[8],
        }
        for r in rows
    ]


# --------------------------------------------------------------------------- export


def _status_column(seqs: list[Sequence[StatusValue]], b: int) -> list[StatusValue]:
    return [s[b] if b < len(s) else None for s in seqs]


WideColumn = NDArray[np.float64] | NDArray[np.int64] | list[StatusValue]


def wide_columns(
    result: Result, steps: NDArray[np.int64] | None = None, *, status_runs_to_end: bool = False
) -> dict[str, WideColumn]:
    """The run as one row per step: pack columns, then ``<battery>_<channel>`` per battery.

    ``step`` is the recorded step number when ``steps`` is given, else the row index.

    Group voltages become ``<battery>_g<k>_v`` (k from 0), status channels
    ``<battery>_<channel>``, the auxiliary battery ``aux_<channel>``. A status channel shorter
    than the run is padded with empty values at the start when ``status_runs_to_end`` (true of
    a loaded run: channels are forward-filled to the end); otherwise its steps are unknown and
    it is left out with a warning.
    """
    tr = result.trace
    n_s = len(tr.t_s)
    cols: dict[str, WideColumn] = {
        "step": np.arange(n_s, dtype=np.int64) if steps is None else np.asarray(steps),
        "t_s": tr.t_s,
        "bus_v": tr.bus_v,
        "load_demand_a": tr.load_demand_a,
        "load_a": tr.load_a,
        "charger_v": tr.charger_v,
        "charger_a": tr.charger_a,
    }

    def put(name: str, col: WideColumn) -> None:
        if name in cols:
            raise InputError(f"wide export: column name {name!r} occurs twice (battery names?)")
        cols[name] = col

    aligned: dict[str, list[Sequence[StatusValue]]] = {}
    for channel, seqs in tr.status.items():
        if len(seqs) == n_s:
            aligned[channel] = seqs
        elif status_runs_to_end and len(seqs) < n_s:
            aligned[channel] = [*([()] * (n_s - len(seqs))), *seqs]
        else:
            warnings.warn(
                f"status channel {channel!r} has {len(seqs)} samples for {n_s} steps;"
                " left out of the wide export",
                stacklevel=3,
            )
    for b, name in enumerate(result.battery_names):
        for c, channel in enumerate(BATTERY_CHANNELS):
            put(f"{name}_{channel}", tr.battery[:, b, c])
        for g in range(tr.group_v.shape[2]):
            col = tr.group_v[:, b, g]
            if not np.all(np.isnan(col)):
                put(f"{name}_g{g}_v", col)
        for channel, seqs in aligned.items():
            put(f"{name}_{channel}", _status_column(seqs, b))
    if tr.aux is not None:
        for c, channel in enumerate(BATTERY_CHANNELS):
            put(f"aux_{channel}", tr.aux[:, c])
    return cols


def _csv_cells(col: WideColumn) -> list[Any]:
    """Floats written exactly (repr); NaN and None as empty cells, the spreadsheet norm."""
    if isinstance(col, np.ndarray):
        if col.dtype.kind != "f":
            return col.tolist()  # type: ignore[no-any-return]
        obj: NDArray[Any] = col.astype(object)
        obj[np.isnan(col)] = ""
        return obj.tolist()  # type: ignore[no-any-return]
    return ["" if v is None or (isinstance(v, float) and math.isnan(v)) else v for v in col]


def _write_csv(cols: Mapping[str, WideColumn], out_path: Path | str) -> None:
    cells = [_csv_cells(c) for c in cols.values()]
    with Path(out_path).open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(list(cols))
        w.writerows(zip(*cells, strict=True))


def trace_to_csv(result: Result, out_path: Path | str) -> None:
    """Write the wide table of an in-memory ``Result`` (the CLI's ``--trace-csv``)."""
    _write_csv(wide_columns(result), out_path)


def export_csv(db_path: Path | str, out_path: Path | str, run_id: int | None = None) -> None:
    """Export one run (latest by default) as a wide CSV."""
    result, steps = _load(db_path, run_id)
    _write_csv(wide_columns(result, steps, status_runs_to_end=True), out_path)


def export_parquet(db_path: Path | str, out_path: Path | str, run_id: int | None = None) -> None:
    """Export one run (latest by default) as a wide Parquet table (NaN kept as NaN)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    result, steps = _load(db_path, run_id)
    arrays: dict[str, Any] = {}
    for name, col in wide_columns(result, steps, status_runs_to_end=True).items():
        if isinstance(col, np.ndarray):
            arrays[name] = pa.array(col)
        else:
            try:
                arrays[name] = pa.array(col)
            except (pa.ArrowInvalid, pa.ArrowTypeError):
                arrays[name] = pa.array([None if v is None else str(v) for v in col])
    table = pa.table(arrays)
    table = table.replace_schema_metadata(
        {
            "packpilot.run_id": str(result.run_id),
            "packpilot.battery_names": _dumps(result.battery_names),
        }
    )
    pq.write_table(table, out_path)


def iter_runs(path: Path | str) -> Iterator[Result]:
    """Every run of a file as a ``Result``, oldest first (campaign post-processing)."""
    for run in list_runs(path):
        yield load_run(path, int(run["id"]))


__all__ = [
    "PACK_COLUMNS",
    "SCHEMA_VERSION",
    "SQLiteRecorder",
    "export_csv",
    "export_parquet",
    "iter_runs",
    "list_runs",
    "load_run",
    "trace_to_csv",
    "wide_columns",
]
