"""SQLite telemetry: record a run while it runs, read it back as a ``Result``, export it.

One job per module:

- :mod:`~packpilot.io.telemetry.schema` — the tables, ``SCHEMA_VERSION``, the version check;
- :mod:`~packpilot.io.telemetry.writer` — :class:`SQLiteRecorder`, recording a run as it runs;
- :mod:`~packpilot.io.telemetry.reader` — :func:`load_run`, :func:`list_runs`;
- :mod:`~packpilot.io.telemetry.export` — a run as a wide CSV or Parquet table.

The schema is documented in ``docs/telemetry.md``.
"""

from __future__ import annotations

from packpilot.io.telemetry.export import export_csv, export_parquet, trace_to_csv, wide_columns
from packpilot.io.telemetry.reader import list_runs, load_run, samples_committed
from packpilot.io.telemetry.schema import PACK_COLUMNS, SCHEMA_VERSION
from packpilot.io.telemetry.writer import SQLiteRecorder

__all__ = [
    "PACK_COLUMNS",
    "SCHEMA_VERSION",
    "SQLiteRecorder",
    "export_csv",
    "export_parquet",
    "list_runs",
    "load_run",
    "samples_committed",
    "trace_to_csv",
    "wide_columns",
]
