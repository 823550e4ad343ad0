"""Reading recorded runs back: a run as a ``Result`` (:func:`load_run`), the list of runs.

Status is stored on change; reading forward-fills it to one value per step again.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
from packpilot.contract.record import BATTERY_CHANNELS, Result, Trace
from packpilot.errors import InputError
from packpilot.io.telemetry.liveness import shown_status, writer_columns
from packpilot.io.telemetry.schema import PACK_COLUMNS, _check_schema


def _open_ro(path: Path | str, any_thread: bool = False) -> sqlite3.Connection:
    """Open a telemetry file for reading only. A WAL file needs its ``-shm`` beside it, which
    read-only media cannot hold: then the file is opened ``immutable`` (no locks, no WAL), which
    reads every committed row of a run that finished (its WAL was checkpointed on close).
    ``any_thread``: the connection may be used from a thread other than this one (one at a
    time: the caller serializes)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: telemetry database not found")
    try:
        return _connect_checked(p, "mode=ro", any_thread)
    except sqlite3.OperationalError:
        pass  # read-only media: no -shm can be created next to the file
    except sqlite3.DatabaseError as err:
        raise InputError(f"{p}: not a PackPilot telemetry database ({err})") from None
    try:
        return _connect_checked(p, "immutable=1", any_thread)
    except sqlite3.DatabaseError as err:
        raise InputError(f"{p}: not a PackPilot telemetry database ({err})") from None


def _connect_checked(p: Path, query: str, any_thread: bool = False) -> sqlite3.Connection:
    """A connection by URI (``query``) whose file holds a readable PackPilot schema."""
    uri = f"{p.resolve().as_uri()}?{query}"
    conn = sqlite3.connect(uri, uri=True, check_same_thread=not any_thread)
    try:
        conn.execute("SELECT 1 FROM runs LIMIT 1").fetchall()
        _check_schema(conn, p)
    except (sqlite3.DatabaseError, InputError):
        conn.close()
        raise
    return conn


MAX_RUN_ID = 2**63 - 1
"""SQLite's largest integer: a larger run id raised OverflowError inside the query."""


def _resolve_run(conn: sqlite3.Connection, path: Path | str, run_id: int | None) -> int:
    if run_id is not None and not 1 <= run_id <= MAX_RUN_ID:
        raise InputError(f"{path}: run id {run_id} is not 1..{MAX_RUN_ID}")
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
    state: dict[str, list[StatusValue]],
) -> dict[str, list[Sequence[StatusValue]]]:
    """Rebuild one tuple per step per channel from change-only rows, from its first step on.

    ``state`` holds each started channel's values after the previous block of steps (empty
    for a whole run) and is updated, so a run read in pieces fills exactly as read at once."""
    by_channel: dict[str, dict[int, list[tuple[int, StatusValue]]]] = {}
    for channel, step, b, value in rows:
        restored = _restore_status(value, kinds.get(channel, set()))
        by_channel.setdefault(channel, {}).setdefault(step, []).append((b, restored))
    step_list = steps.tolist()
    out: dict[str, list[Sequence[StatusValue]]] = {}
    # The recorder's channel order (first seen), as Trace.from_samples keeps it.
    others = sorted((set(by_channel) | set(state)) - set(kinds))
    for channel in [*kinds, *others]:
        changes = by_channel.get(channel, {})
        current = state.get(channel)
        if current is None and not changes:
            continue
        first = min(changes) if current is None else -1
        current = [] if current is None else current
        seqs: list[Sequence[StatusValue]] = []
        last: tuple[StatusValue, ...] = tuple(current)
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
        state[channel] = current
        out[channel] = seqs
    return out


def load_run(path: Path | str, run_id: int | None = None) -> Result:
    """Rebuild a run's ``Result`` (latest run when ``run_id`` is None).

    Known losses: a status value that was ``None`` in a channel that also carried NaN comes
    back as ``None`` (SQLite stores NaN as NULL); status is stored on change, so a channel runs
    from the first step that carried it to the end of the run, and a per-step sequence never
    shrinks (a battery index once seen keeps its last value).
    """
    tail = RunTail(path, run_id)
    try:
        return tail.read().result
    finally:
        tail.close()


@dataclass
class Chunk:
    """What one :meth:`RunTail.read` found: the rows committed since the previous read."""

    result: Result
    """The new samples (a Trace of just them), the new events, the run's metrics so far."""
    steps: NDArray[np.int64]
    """The recorded step number of each new sample."""
    status: str
    """The run's status as :func:`list_runs` shows it: ``running`` while its writer lives."""


class RunTail:
    """A run read while it is written: each :meth:`read` returns what was committed since the
    previous one (the first, the whole run so far); :func:`load_run` is one read.

    The writer commits a block of samples, their status changes and events and the run's row
    in one transaction, and each read is one read transaction, so a read sees whole steps
    only. Forward-filled status carries over from one read to the next. This is how the
    dashboard follows ``packpilot run`` (or ``simulate --db``) in another process.
    """

    def __init__(self, path: Path | str, run_id: int | None = None) -> None:
        self.path = path
        conn = _open_ro(path, any_thread=True)  # the dashboard follows a run from its own thread
        conn.isolation_level = None  # reads open their own transaction: one snapshot each
        try:
            self.run_id = _resolve_run(conn, path, run_id)
            names_j, channels_j, config_j = conn.execute(
                "SELECT battery_names, channels, config FROM runs WHERE id = ?", (self.run_id,)
            ).fetchone()
            if json.loads(channels_j) != list(BATTERY_CHANNELS):
                raise InputError(
                    f"{path}: run {self.run_id} was recorded with battery channels"
                    f" {json.loads(channels_j)}, this version expects {list(BATTERY_CHANNELS)}"
                )
        except BaseException:
            conn.close()
            raise
        self._conn = conn
        self.names: list[str] = json.loads(names_j)
        config = json.loads(config_j)
        self.config: dict[str, Any] = config if isinstance(config, dict) else {}
        """The run's configuration as recorded (the scenario, resolved)."""
        self._after_step = -1
        self._after_event = 0
        self._status_state: dict[str, list[StatusValue]] = {}

    def close(self) -> None:
        self._conn.close()

    def count(self) -> int:
        """Samples committed after the last read (all of them before the first)."""
        (n,) = self._conn.execute(
            "SELECT COUNT(*) FROM pack_samples WHERE run_id = ? AND step > ?",
            (self.run_id, self._after_step),
        ).fetchone()
        return int(n)

    def read(self, max_steps: int | None = None) -> Chunk:
        """The rows committed since the previous read; with ``max_steps``, at most that many
        samples (and the events up to the last of them), so a long run is read in blocks
        whose memory does not grow with the run (the report's and the dashboard's reader)."""
        conn = self._conn
        conn.execute("BEGIN")
        try:
            chunk = self._read(conn, max_steps)
        finally:
            conn.execute("COMMIT")
        if len(chunk.steps):
            self._after_step = int(chunk.steps[-1])
        return chunk

    def position(self) -> tuple[int, dict[str, list[StatusValue]]]:
        """Where the next read starts: the last step read and the forward-filled status then
        (a copy), so :meth:`seek` can come back here later (the dashboard's scrubber)."""
        return self._after_step, {k: list(v) for k, v in self._status_state.items()}

    def seek(self, after_step: int, status: dict[str, list[StatusValue]]) -> None:
        """Read on from a :meth:`position` (samples only: events already read are skipped)."""
        self._after_step = after_step
        self._status_state = {k: list(v) for k, v in status.items()}
        self._after_event = MAX_RUN_ID

    def _read(self, conn: sqlite3.Connection, max_steps: int | None = None) -> Chunk:
        rid, after = self.run_id, self._after_step
        metrics_j, kinds_j = conn.execute(
            "SELECT metrics, status_kinds FROM runs WHERE id = ?", (rid,)
        ).fetchone()
        upto = _block_end(conn, rid, after, max_steps)
        steps, pm, battery, group_v, aux = _samples(conn, rid, len(self.names), after, upto)
        kinds = {k: set(v) for k, v in json.loads(kinds_j or "{}").items()}
        status = _forward_fill_status(
            conn.execute(
                "SELECT channel, step, battery, value FROM status_samples WHERE run_id = ?"
                " AND step > ? AND step <= ? ORDER BY channel, step, battery",
                (rid, after, upto),
            ).fetchall(),
            steps,
            kinds,
            self._status_state,
        )
        last_event = MAX_RUN_ID
        if upto < MAX_RUN_ID and len(pm):  # a block: the events up to its last sample's time
            (found,) = conn.execute(
                "SELECT MAX(id) FROM events WHERE run_id = ? AND id > ? AND t_s <= ?",
                (rid, self._after_event, float(pm[-1, 1])),
            ).fetchone()
            last_event = self._after_event if found is None else int(found)
        events = []
        for event_id, t_s, kind, b, message, data in conn.execute(
            "SELECT id, t_s, kind, battery, message, data FROM events WHERE run_id = ?"
            " AND id > ? AND id <= ? ORDER BY id",
            (rid, self._after_event, last_event),
        ):
            self._after_event = event_id
            t = t_s if t_s is not None else math.nan
            events.append(Event(t, kind, b, message, json.loads(data)))
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
        metrics = json.loads(metrics_j) if metrics_j else {}
        build_s = float(metrics.pop("build_time_s", 0.0))  # reported apart from the metrics
        result = Result(list(self.names), trace, events, metrics, run_id=rid, build_time_s=build_s)
        return Chunk(result, steps, _run_status(conn, rid))


def _run_status(conn: sqlite3.Connection, rid: int) -> str:
    """The run's status as shown: a ``running`` run whose writer is gone reads ``aborted``."""
    cols = "writer_pid, writer_host, heartbeat_at" if writer_columns(conn) else "NULL, NULL, NULL"
    status, pid, host, beat = conn.execute(
        f"SELECT status, {cols} FROM runs WHERE id = ?", (rid,)
    ).fetchone()
    return shown_status(status, pid, host, beat)


Samples = tuple[
    NDArray[np.int64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64],
    NDArray[np.float64] | None,
]


def _block_end(conn: sqlite3.Connection, rid: int, after: int, max_steps: int | None) -> int:
    """The last step of a read of at most ``max_steps`` samples after ``after`` (unbounded:
    :data:`MAX_RUN_ID`, also when fewer samples are left)."""
    if max_steps is None:
        return MAX_RUN_ID
    if max_steps < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps}")
    row = conn.execute(
        "SELECT step FROM pack_samples WHERE run_id = ? AND step > ? ORDER BY step"
        " LIMIT 1 OFFSET ?",
        (rid, after, max_steps - 1),
    ).fetchone()
    return MAX_RUN_ID if row is None else int(row[0])


def _samples(
    conn: sqlite3.Connection, rid: int, n_b: int, after: int, upto: int = MAX_RUN_ID
) -> Samples:
    """Steps, pack matrix, battery and group arrays and aux of the samples in (after, upto]."""
    n_c = len(BATTERY_CHANNELS)
    width = 1 + len(PACK_COLUMNS)
    (count,) = conn.execute(
        "SELECT COUNT(*) FROM pack_samples WHERE run_id = ? AND step > ? AND step <= ?",
        (rid, after, upto),
    ).fetchone()  # the same snapshot as the rows below (one read transaction)
    pm = np.empty((count, width), dtype=np.float64)
    cur = conn.execute(
        f"SELECT step, {', '.join(PACK_COLUMNS)} FROM pack_samples WHERE run_id = ?"
        " AND step > ? AND step <= ? ORDER BY step",
        (rid, after, upto),
    )
    n_s = 0
    while pack := cur.fetchmany(ROWS_PER_FETCH):
        if n_s + len(pack) > len(pm):  # not in one snapshot after all: grow
            pm = np.concatenate([pm, np.empty((n_s + len(pack) - len(pm), width))])
        pm[n_s : n_s + len(pack)] = _float_matrix(pack, width)
        n_s += len(pack)
    pm = pm[:n_s]
    steps = pm[:, 0].astype(np.int64)  # step numbers are exact in float64 (< 2^53)

    battery = np.full((n_s, n_b, n_c), np.nan)
    max_groups = (
        conn.execute(
            "SELECT COALESCE(MAX(LENGTH(group_v)), 0) FROM battery_samples"
            " WHERE run_id = ? AND step > ? AND step <= ?",
            (rid, after, upto),
        ).fetchone()[0]
        // 8
    )
    group_v = np.full((n_s, n_b, max_groups), np.nan)
    cur = conn.execute(
        f"SELECT step, battery, {', '.join(BATTERY_CHANNELS)}, group_v FROM battery_samples"
        " WHERE run_id = ? AND step > ? AND step <= ? ORDER BY step, battery",
        (rid, after, upto),
    )
    while bat_rows := cur.fetchmany(ROWS_PER_FETCH):  # blocks: no list of every row at once
        _fill_battery(bat_rows, steps, battery, group_v, max_groups)

    aux_rows = conn.execute(
        f"SELECT step, {', '.join(BATTERY_CHANNELS)} FROM aux_samples WHERE run_id = ?"
        " AND step > ? AND step <= ? ORDER BY step",
        (rid, after, upto),
    ).fetchall()
    aux: NDArray[np.float64] | None = None
    if aux_rows:
        aux = np.full((n_s, n_c), np.nan)
        ai = np.searchsorted(steps, np.array([r[0] for r in aux_rows], dtype=np.int64))
        aux[ai, :] = _float_matrix([r[1:] for r in aux_rows], n_c)
    return steps, pm, battery, group_v, aux


ROWS_PER_FETCH = 20_000
"""Battery rows converted per block: Python tuples of a whole 1-day run (1.7 M rows) took
about 1 GB before the arrays were filled."""


def _fill_battery(
    rows: list[tuple[Any, ...]],
    steps: NDArray[np.int64],
    battery: NDArray[np.float64],
    group_v: NDArray[np.float64],
    max_groups: int,
) -> None:
    """One block of battery rows into the preallocated arrays."""
    n_c = battery.shape[2]
    si = np.searchsorted(steps, np.array([r[0] for r in rows], dtype=np.int64))
    bi = np.array([r[1] for r in rows], dtype=np.int64)
    battery[si, bi, :] = _float_matrix([r[2:-1] for r in rows], n_c)
    blobs = [r[-1] for r in rows]
    if all(len(b) == 8 * max_groups for b in blobs):
        gm = np.frombuffer(b"".join(blobs), dtype="<f8").reshape(len(blobs), max_groups)
        group_v[si, bi, :] = gm
    else:
        for j, blob in enumerate(blobs):
            g = np.frombuffer(blob, dtype="<f8")
            group_v[si[j], bi[j], : len(g)] = g


def samples_committed(path: Path | str) -> int:
    """How many samples of the file's latest run are committed so far: 0 while the file, its
    schema or its first run does not exist yet (a writer still starting up)."""
    try:
        conn = _open_ro(path)
    except InputError:
        return 0
    try:
        row = conn.execute(
            "SELECT COUNT(*) FROM pack_samples WHERE run_id = (SELECT MAX(id) FROM runs)"
        ).fetchone()
    except sqlite3.Error:
        return 0
    finally:
        conn.close()
    return int(row[0])


def list_runs(path: Path | str) -> list[dict[str, Any]]:
    """Every run in the file, oldest first, with its JSON columns decoded and its step count."""
    conn = _open_ro(path)
    try:
        writer = (
            "writer_pid, writer_host, heartbeat_at" if writer_columns(conn) else "NULL, NULL, NULL"
        )
        rows = conn.execute(
            "SELECT id, started_at, finished_at, status, config, versions, battery_names,"
            " metrics, (SELECT COUNT(*) FROM pack_samples p WHERE p.run_id = runs.id),"
            f" {writer} FROM runs ORDER BY id"
        ).fetchall()
    finally:
        conn.close()
    return [
        {
            "id": r[0],
            "started_at": r[1],
            "finished_at": r[2],
            "status": shown_status(r[3], r[9], r[10], r[11]),
            "heartbeat_at": r[11],
            "config": json.loads(r[4]),
            "versions": json.loads(r[5]),
            "battery_names": json.loads(r[6]),
            "metrics": json.loads(r[7]) if r[7] else None,
            "n_steps": r[8],
        }
        for r in rows
    ]
