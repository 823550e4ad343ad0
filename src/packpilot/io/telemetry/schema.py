"""The telemetry database's schema: tables and columns, its version, the insert statements.

The schema is documented in ``docs/telemetry.md``; bump ``SCHEMA_VERSION`` when it changes.
Both the writer and the reader check the version of a file (:func:`_check_schema`); JSON
columns are written with :func:`_dumps`.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.contract.record import BATTERY_CHANNELS
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


def _check_schema(conn: sqlite3.Connection, path: Path | str) -> None:
    row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
    if row is None or row[0] != str(SCHEMA_VERSION):
        found = "none" if row is None else row[0]
        raise InputError(
            f"{path}: telemetry schema version {found}, this PackPilot reads {SCHEMA_VERSION}"
        )
