"""Is the writer of a ``running`` run still alive? A killed ``simulate --db`` leaves its run
``running`` forever; a later reader must be able to say ``aborted`` instead.

The writer stamps its run with its process id, host name and a heartbeat (UTC, refreshed with
every commit, at least once a second while it records). A later process decides:

* same host: the writer is gone when no process has that id any more;
* another host (a shared or copied file): gone when the heartbeat is older than
  :data:`STALE_AFTER_S` (a live writer refreshes it every second).
"""

from __future__ import annotations

import datetime as _dt
import os
import socket
import sqlite3

STALE_AFTER_S = 600.0
"""A heartbeat this old means the writer on another host is gone (it commits every second)."""

WRITER_COLUMNS: tuple[tuple[str, str], ...] = (
    ("writer_pid", "INTEGER"),
    ("writer_host", "TEXT"),
    ("heartbeat_at", "TEXT"),
)
"""Columns a writer adds to ``runs`` of a file written before they existed (ALTER TABLE)."""


def host_name() -> str:
    return socket.gethostname()


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def writer_gone(pid: int | None, host: str | None, heartbeat_at: str | None) -> bool:
    """True when the process that wrote a ``running`` run cannot still be writing it."""
    if pid is None or host is None:
        return False  # written before writers were stamped: nothing to decide on
    if host == host_name():
        return pid != os.getpid() and not _pid_alive(pid)
    if heartbeat_at is None:
        return False
    beat = _dt.datetime.fromisoformat(heartbeat_at)
    age = (_dt.datetime.now(_dt.UTC) - beat).total_seconds()
    return age > STALE_AFTER_S


def shown_status(status: str, pid: int | None, host: str | None, beat: str | None) -> str:
    """The status a reader reports: ``aborted`` for a ``running`` run whose writer is gone."""
    if status == "running" and writer_gone(pid, host, beat):
        return "aborted"
    return status


def writer_columns(conn: sqlite3.Connection) -> bool:
    """Whether ``runs`` has the writer columns (files from older versions do not)."""
    names = {r[1] for r in conn.execute("PRAGMA table_info(runs)").fetchall()}
    return all(name in names for name, _ in WRITER_COLUMNS)


def add_writer_columns(conn: sqlite3.Connection) -> None:
    """Add the writer columns to an older file's ``runs`` (additive: old readers ignore them)."""
    names = {r[1] for r in conn.execute("PRAGMA table_info(runs)").fetchall()}
    for name, kind in WRITER_COLUMNS:
        if name not in names:
            conn.execute(f"ALTER TABLE runs ADD COLUMN {name} {kind}")


def mark_aborted(conn: sqlite3.Connection) -> list[int]:
    """Store ``aborted`` (ended at its last heartbeat) on every ``running`` run whose writer
    is gone; returns their ids. Called by a writer when it opens a file."""
    rows = conn.execute(
        "SELECT id, writer_pid, writer_host, heartbeat_at FROM runs WHERE status = 'running'"
    ).fetchall()
    gone = [int(r[0]) for r in rows if writer_gone(r[1], r[2], r[3])]
    for run_id in gone:
        conn.execute(
            "UPDATE runs SET status = 'aborted', finished_at = heartbeat_at WHERE id = ?",
            (run_id,),
        )
    return gone


__all__ = [
    "STALE_AFTER_S",
    "add_writer_columns",
    "host_name",
    "mark_aborted",
    "shown_status",
    "writer_columns",
    "writer_gone",
]
