"""Recording a run into SQLite while it runs: :class:`SQLiteRecorder`.

Why SQLite: one file, no server, safe to read while a run writes (WAL mode), and a crashed run
keeps whatever was flushed. Writes are buffered and sent with ``executemany`` every
``flush_every`` samples so recording costs far less than simulating.
"""

from __future__ import annotations

import datetime as _dt
import functools
import importlib.metadata
import math
import os
import platform
import signal
import sqlite3
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from itertools import chain, repeat
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
from packpilot.contract.events import value as field_value
from packpilot.contract.record import BATTERY_CHANNELS, StatusLayout, StepSample
from packpilot.errors import InputError
from packpilot.io.telemetry.liveness import add_writer_columns, host_name, mark_aborted
from packpilot.io.telemetry.schema import (
    _AUX_INSERT,
    _BAT_INSERT,
    _EVENT_INSERT,
    _PACK_INSERT,
    _SCHEMA,
    _STATUS_INSERT,
    PACK_COLUMNS,
    SCHEMA_VERSION,
    _check_schema,
    _dumps,
)

COMMIT_EVERY_S = 0.5
"""Wall time between commits while a run records (also every ``flush_every`` samples): a killed
writer loses at most the last ~0.5 s of samples (docs/telemetry.md)."""


@contextmanager
def _ctrl_c_after() -> Iterator[None]:
    """Hold a Ctrl-C that arrives inside the block until the block has run, then deliver it.

    A flush is bookkeeping in several statements (status rows derived, rows inserted, the
    buffers cleared after ``COMMIT``). A KeyboardInterrupt between two of them left rows both
    committed and still buffered, and the final flush of the interrupted run then failed with
    "UNIQUE constraint failed: status_samples..." and a traceback instead of exit 130 (seen
    in CI). Only the main thread receives signals; elsewhere the block runs as it is."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[tuple[int, Any]] = []
    before = signal.getsignal(signal.SIGINT)
    if before is None or before == signal.SIG_IGN:  # not set from Python, or ignored
        yield
        return
    signal.signal(signal.SIGINT, lambda signum, frame: held.append((signum, frame)))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)
    if not held:
        return
    if callable(before):
        before(*held[0])  # the default handler raises KeyboardInterrupt here, after the block
    else:  # SIG_DFL: the signal's own action, now that the rows are consistent
        signal.raise_signal(signal.SIGINT)


def _open_for_writing(path: Path) -> sqlite3.Connection:
    """Open (or create) a telemetry file, bring it to the current schema and mark the runs of
    writers that died as ``aborted``. Every failure is one clean :class:`InputError`."""
    if path.is_dir():
        raise InputError(f"{path}: is a directory, not a telemetry database file")
    try:
        conn = sqlite3.connect(path, isolation_level=None)
    except sqlite3.Error as err:
        raise InputError(f"{path}: cannot open telemetry database ({err})") from None
    try:
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=NORMAL")
        conn.executescript(_SCHEMA)
        conn.execute(
            "INSERT OR IGNORE INTO meta VALUES ('schema_version', ?)", (str(SCHEMA_VERSION),)
        )
        _check_schema(conn, path)
        add_writer_columns(conn)
        mark_aborted(conn)
    except sqlite3.DatabaseError as err:
        conn.close()
        raise InputError(f"{path}: {_why(err)}") from None
    except InputError:
        conn.close()
        raise
    return conn


def _why(err: sqlite3.Error) -> str:
    """What a user can act on, for SQLite's errors on opening or writing a file."""
    text = str(err)
    if isinstance(err, sqlite3.OperationalError):
        if "full" in text:
            return f"cannot write telemetry: the disk (or database) is full ({text})"
        if "readonly" in text or "read-only" in text or "unable to open" in text:
            return f"cannot write telemetry: read-only file or directory ({text})"
        return f"cannot write telemetry ({text})"
    return f"not a PackPilot telemetry database ({text})"


def _utc_now() -> str:
    return _dt.datetime.now(_dt.UTC).isoformat(timespec="milliseconds")


def _versions() -> dict[str, str]:
    try:
        pp = importlib.metadata.version("packpilot")
    except importlib.metadata.PackageNotFoundError:
        pp = "unknown"
    return {"packpilot": pp, "numpy": np.__version__, "python": platform.python_version()}


ROWS_PER_INSERT = 64
"""Rows one ``INSERT ... VALUES (...), (...), ...`` statement carries: SQLite then runs one
statement per 64 rows instead of one per row (the status rows of uav_mission: 27.7 -> 16.0 us
of CPU per step, the same rows; benchmarks/RESULTS.md)."""


@functools.cache
def _multi_row(sql: str, n: int) -> str:
    """``sql`` (``INSERT INTO t VALUES (?, ?)``) inserting ``n`` rows at once."""
    head, values = sql.split(" VALUES ")
    return f"{head} VALUES {', '.join([values] * n)}"


def _insert(conn: sqlite3.Connection, sql: str, rows: Sequence[tuple[Any, ...]]) -> None:
    """``conn.executemany(sql, rows)``, in statements of :data:`ROWS_PER_INSERT` rows (the
    same rows, in the same order, in the caller's transaction)."""
    n = ROWS_PER_INSERT
    full = len(rows) // n * n
    if full:
        width = len(rows[0])
        flat = list(chain.from_iterable(rows[:full]))
        step = width * n
        conn.executemany(
            _multi_row(sql, n), [flat[j : j + step] for j in range(0, full * width, step)]
        )
    if full < len(rows):
        conn.executemany(sql, rows[full:])


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


_FLOATLIKE = ("f", "o")
"""Kinds whose value is the number itself (``o``: ``None`` for NaN): a value changed exactly
when the numbers differ and are not both NaN."""


class SQLiteRecorder:
    """The default ``Recorder``: runs, samples and events in one SQLite file (WAL mode).

    Several runs may share one file. A run is inserted with status ``running`` at ``start`` and
    committed at once, so a run that dies without ``finish`` stays visible as ``running`` with
    every flushed sample; ``finish(status="error")`` marks it failed. Leaving a ``with`` block
    on an exception finishes an unfinished run with status ``error``.
    """

    def __init__(
        self,
        path: Path | str,
        *,
        flush_every: int = 500,
        commit_every_s: float = COMMIT_EVERY_S,
    ) -> None:
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        self.path = Path(path)
        self.flush_every = flush_every
        self.commit_every_s = commit_every_s
        self._last_commit = time.monotonic()
        self._conn: sqlite3.Connection | None = _open_for_writing(self.path)
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
        self._num_buf: NDArray[np.float64] | None = None
        self._num_prev: NDArray[np.float64] | None = None
        self._num_layout: StatusLayout | None = None
        self._num_done = 0
        """Leading buffered rows whose status rows are made (the run's first sample's)."""

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
        now = _utc_now()
        try:
            cur = conn.execute(
                "INSERT INTO runs (started_at, status, config, versions, battery_names,"
                " channels, writer_pid, writer_host, heartbeat_at)"
                " VALUES (?, 'running', ?, ?, ?, ?, ?, ?, ?)",
                (
                    now,
                    _dumps(config),
                    _dumps(_versions()),
                    _dumps(list(battery_names)),
                    _dumps(list(BATTERY_CHANNELS)),
                    os.getpid(),
                    host_name(),
                    now,
                ),
            )
        except sqlite3.OperationalError as err:
            raise InputError(f"{self.path}: {_why(err)}") from None
        self._last_commit = time.monotonic()
        run_id = cur.lastrowid
        assert run_id is not None
        self._run_id = run_id
        self._status_kinds = {}
        self._status_prev = {}
        self._status_prev_seq = {}
        self._bat_buf = None  # re-sized from the first sample of the new run
        self._num_buf = self._num_prev = self._num_layout = None
        self._num_done = 0
        return run_id

    def _alloc(self, sample: StepSample) -> None:
        """Size the sample buffers from the first sample of a run (group count is per pack)."""
        self._alloc_shapes(sample.battery.shape, sample.group_v.shape)

    def _alloc_shapes(self, shape_b: tuple[int, ...], shape_g: tuple[int, ...]) -> None:
        n = self.flush_every
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
        if sample.aux is not None:
            self._aux_buf[k] = sample.aux
        # Only now, and together: a mis-shaped sample above leaves no partial row, and a
        # Ctrl-C (KeyboardInterrupt between any two statements) at worst drops this row
        # (_sample_rows reads exactly _pending rows) instead of a traceback at the final flush.
        self._steps.append(step)
        if sample.aux is not None:
            self._aux_steps.append(k)
        self._pending = k + 1
        if sample.status:
            self._record_status(run_id, step, sample.status)
        if (
            self._pending >= self.flush_every
            or time.monotonic() - self._last_commit >= self.commit_every_s
        ):
            self.flush()

    def record_numbers(
        self,
        step: int,
        scalars: NDArray[np.float64],
        battery: NDArray[np.float64],
        group_v: NDArray[np.float64],
        status: NDArray[np.float64],
        layout: StatusLayout,
    ) -> None:
        """:meth:`record` of a sample given as the numbers it is made of (what a run's trace
        holds): ``scalars`` the pack row (:data:`PACK_COLUMNS`), ``battery``/``group_v`` as a
        sample's, ``status`` the status numbers (batteries, slots) read through ``layout``.
        The database receives the same rows as from :meth:`record`; the status values are
        rendered and compared only at the flush, in bulk, and only where a number changed
        (per step this copies four rows: rendering every sample cost more than the BMS)."""
        run_id = self._require_run()
        if self._steps and self._num_layout is None:
            raise RuntimeError("record_numbers cannot follow record() in the same run")
        k = self._pending
        if self._bat_buf is None:
            self._alloc_shapes(battery.shape, group_v.shape)
        if self._num_buf is None:
            self._num_buf = np.empty((self.flush_every, *status.shape))
            self._num_layout = layout
        assert self._pack_buf is not None and self._bat_buf is not None
        assert self._grp_buf is not None
        self._pack_buf[k] = scalars
        self._bat_buf[k] = battery
        self._grp_buf[k] = group_v
        self._num_buf[k] = status
        self._steps.append(int(step))
        self._pending = k + 1
        if self._num_prev is None:  # the run's first sample: every channel, as record() does
            with _ctrl_c_after():  # once per run: all three or none
                self._num_prev = status.copy()
                self._num_done = self._pending
                self._record_status(run_id, int(step), layout.render(status))
        if (
            self._pending >= self.flush_every
            or time.monotonic() - self._last_commit >= self.commit_every_s
        ):
            self.flush()

    def _numbers_to_status(self, run_id: int) -> None:
        """The status rows of the buffered numbers (rows after a run's first sample, which
        :meth:`record_numbers` stored whole): a value is stored when it renders differently
        from the step before (what :meth:`_record_status` decides, value by value, against
        the last value stored: for every kind, that is the previous step's value)."""
        layout, buf, prev, k = self._num_layout, self._num_buf, self._num_prev, self._pending
        start = self._num_done
        if layout is None or buf is None or prev is None or k <= start:
            return
        slots = [slot for _, slot, _, _ in layout.channels]
        cur = buf[start:k][:, :, slots]  # (t, b, c)
        before = np.concatenate([prev[None, :, slots], buf[start : k - 1][:, :, slots]])
        moved = cur.view(np.int64) != before.view(np.int64)
        kinds = [kind for _, _, kind, _ in layout.channels]
        floatlike = np.array([kind in _FLOATLIKE for kind in kinds])
        if floatlike.any():
            same = (cur == before) | (np.isnan(cur) & np.isnan(before))
            moved &= ~(same & floatlike)
        boolean = np.array([kind == "b" for kind in kinds])
        if boolean.any():
            moved &= ((cur != 0.0) != (before != 0.0)) | ~boolean
        t, c, b = np.nonzero(moved.transpose(0, 2, 1))
        if t.size:
            self._store_moved(run_id, layout, t, c, b, cur, before, start)
        self._num_prev = buf[k - 1].copy()
        self._num_done = k

    def _store_moved(
        self, run_id: int, layout: StatusLayout, t: Any, c: Any, b: Any,
        cur: NDArray[np.float64], before: NDArray[np.float64], start: int,
    ) -> None:  # fmt: skip
        """Append the status rows of the entries whose numbers moved (``t``, ``c``, ``b``:
        row, channel, battery). Kinds ``f``/``o`` (every moved entry is a change, the value
        is the number, NaN stored as NULL) in bulk; the others rendered one by one and kept
        only when the value a user reads changed (``i``: 1.2 -> 1.7 is no change)."""
        chans = layout.channels
        kinds = self._status_kinds
        steps = np.asarray(self._steps[start : start + cur.shape[0]], np.int64)
        pos = np.asarray(layout.positions, np.int64)
        floatlike = np.array([kind in _FLOATLIKE for _, _, kind, _ in chans])[c]
        names = np.array([name for name, _, _, _ in chans], dtype=object)
        fl = np.nonzero(floatlike)[0]
        if fl.size:
            tf, cf, bf = t[fl], c[fl], b[fl]
            xs = cur[tf, bf, cf]
            vals = [None if x != x else x for x in xs.tolist()]
            self._status_rows.extend(
                zip(
                    repeat(run_id), steps[tf].tolist(), pos[bf].tolist(),
                    names[cf].tolist(), vals, strict=False,
                )
            )  # fmt: skip
            nan = np.isnan(xs)
            for ci in np.unique(cf).tolist():
                name, _, kind, _ = chans[ci]
                mine = cf == ci
                if kind == "f" or (~nan[mine]).any():
                    kinds[name].add("float")
                if kind == "o" and nan[mine].any():
                    kinds[name].add("none")
        other = np.nonzero(~floatlike)[0]
        if other.size:
            self._store_rendered(run_id, chans, t[other], c[other], b[other], cur, before, steps)

    def _store_rendered(
        self, run_id: int, chans: Sequence[tuple[str, int, str, Any]], t: Any, c: Any, b: Any,
        cur: NDArray[np.float64], before: NDArray[np.float64], steps: NDArray[np.int64],
    ) -> None:  # fmt: skip
        """The moved entries of the kinds a number is not the value of (``i``, ``b``, ``m``,
        ``l:``): stored when the rendered value changed (same rule as :meth:`_record_status`)."""
        assert self._num_layout is not None
        pos = self._num_layout.positions
        rows, kinds = self._status_rows, self._status_kinds
        xs = cur[t, b, c].tolist()
        ps = before[t, b, c].tolist()
        for ti, ci, bi, x, px in zip(t.tolist(), c.tolist(), b.tolist(), xs, ps, strict=True):
            name, _, kind, labels = chans[ci]
            v = field_value(x, kind, labels)
            p = field_value(px, kind, labels)
            if type(v) is type(p) and (v == p or (v != v and p != p)):
                continue
            stored, seen = _status_cell(v)
            kinds[name].add(seen)
            rows.append((run_id, int(steps[ti]), pos[bi], name, stored))

    def _record_status(self, run_id: int, step: int, status: Mapping[str, Sequence[Any]]) -> None:
        """Store a status value only when it differs from the last one stored (same type too).

        Most channels (stage, mode, tripped flags) change a few times per run; writing every
        step made status the bulk of the rows. Readers forward-fill (see docs/telemetry.md).
        A ``status`` with a ``changed`` attribute (the channels whose numbers changed since
        the previous sample) is read only there: rendering every channel of every step cost
        as much as the whole BMS step.
        """
        kinds = self._status_kinds
        prev = self._status_prev
        prev_seq = self._status_prev_seq
        rows = self._status_rows
        # A status that names the channels whose numbers changed since the previous sample
        # (sim/record.py:StatusRow) is read only there: the others would compare equal below.
        changed: Sequence[str] | None = getattr(status, "changed", None)
        items = status.items() if changed is None else ((c, status[c]) for c in changed)
        for channel, seq in items:
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
        steps = self._steps[:k]  # a row interrupted before _pending counted it is dropped
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
        aux = [(run_id, steps[j], *self._aux_buf[j].tolist()) for j in self._aux_steps if j < k]
        return pack, bat, aux

    def flush(self) -> None:
        """Write every buffered row and the run's heartbeat in one transaction; a full disk or
        read-only media is one clean :class:`InputError` naming the file."""
        conn = self._connection()
        self._last_commit = time.monotonic()
        if not (self._pending or self._event_rows):
            return
        try:
            with _ctrl_c_after():
                self._commit(conn)
        except sqlite3.OperationalError as err:
            self._drop_buffers()  # they cannot be written; closing must not fail again
            raise InputError(f"{self.path}: {_why(err)}") from None

    def _commit(self, conn: sqlite3.Connection) -> None:
        run_id = self._run_id
        if run_id is not None and self._num_layout is not None:
            self._numbers_to_status(run_id)
        pack, bat, aux = self._sample_rows(run_id) if run_id is not None else ([], [], [])
        conn.execute("BEGIN")
        try:
            if run_id is not None:
                conn.execute("UPDATE runs SET heartbeat_at = ? WHERE id = ?", (_utc_now(), run_id))
            _insert(conn, _PACK_INSERT, pack)
            _insert(conn, _BAT_INSERT, bat)
            if aux:
                conn.executemany(_AUX_INSERT, aux)
            if self._status_rows:
                _insert(conn, _STATUS_INSERT, self._status_rows)
            if self._event_rows:
                conn.executemany(_EVENT_INSERT, self._event_rows)
            if run_id is not None and self._status_kinds:
                conn.execute(
                    "UPDATE runs SET status_kinds = ? WHERE id = ?",
                    (_dumps({k: sorted(v) for k, v in self._status_kinds.items()}), run_id),
                )
        except BaseException:
            if conn.in_transaction:  # SQLITE_FULL has rolled it back already
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
        self._num_done = 0

    def finish(self, metrics: Mapping[str, Any], status: str = "ok") -> None:
        """Flush, then stamp the run with its end time, status and metrics."""
        conn = self._connection()
        run_id = self._require_run()
        try:
            self.flush()
        finally:
            self._run_id = None
            try:
                conn.execute(
                    "UPDATE runs SET finished_at = ?, status = ?, metrics = ? WHERE id = ?",
                    (_utc_now(), status, _dumps(dict(metrics)), run_id),
                )
            except sqlite3.OperationalError as err:
                raise InputError(f"{self.path}: {_why(err)}") from None

    def close(self) -> None:
        """Flush what is buffered and close; an unfinished run stays ``running``."""
        if self._conn is None:
            return
        try:
            self.flush()
        finally:
            self._conn.close()
            self._conn = None

    def _drop_buffers(self) -> None:
        """Forget the buffered rows of a failed flush (a full disk): they cannot be written."""
        self._pending = 0
        self._num_done = 0
        self._steps.clear()
        self._aux_steps.clear()
        self._status_rows.clear()
        self._event_rows.clear()

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
