"""Reading recorded runs back: a run as a ``Result`` (:func:`load_run`), the list of runs.

Status is stored on change; reading forward-fills it to one value per step again.
"""

from __future__ import annotations

import json
import math
import sqlite3
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
from packpilot.contract.record import BATTERY_CHANNELS, Result, Trace
from packpilot.errors import InputError
from packpilot.io.telemetry.liveness import shown_status, writer_columns
from packpilot.io.telemetry.schema import PACK_COLUMNS, _check_schema


def _open_ro(path: Path | str) -> sqlite3.Connection:
    """Open a telemetry file for reading only. A WAL file needs its ``-shm`` beside it, which
    read-only media cannot hold: then the file is opened ``immutable`` (no locks, no WAL), which
    reads every committed row of a run that finished (its WAL was checkpointed on close)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: telemetry database not found")
    try:
        return _connect_checked(p, "mode=ro")
    except sqlite3.OperationalError:
        pass  # read-only media: no -shm can be created next to the file
    except sqlite3.DatabaseError as err:
        raise InputError(f"{p}: not a PackPilot telemetry database ({err})") from None
    try:
        return _connect_checked(p, "immutable=1")
    except sqlite3.DatabaseError as err:
        raise InputError(f"{p}: not a PackPilot telemetry database ({err})") from None


def _connect_checked(p: Path, query: str) -> sqlite3.Connection:
    """A connection by URI (``query``) whose file holds a readable PackPilot schema."""
    conn = sqlite3.connect(f"{p.resolve().as_uri()}?{query}", uri=True)
    try:
        conn.execute("SELECT 1 FROM runs LIMIT 1").fetchall()
        _check_schema(conn, p)
    except (sqlite3.DatabaseError, InputError):
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
