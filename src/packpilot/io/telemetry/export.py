"""Exporting a run as a wide table (one row per step): CSV or Parquet."""

from __future__ import annotations

import csv
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import StatusValue
from packpilot.contract.record import BATTERY_CHANNELS, Result
from packpilot.errors import InputError
from packpilot.io.telemetry.reader import RunTail
from packpilot.io.telemetry.schema import _dumps


def _status_column(seqs: list[Sequence[StatusValue]], b: int) -> list[StatusValue]:
    return [s[b] if b < len(s) else None for s in seqs]


WideColumn = NDArray[np.float64] | NDArray[np.int64] | list[StatusValue]


def _aligned_status(
    status: Mapping[str, list[Sequence[StatusValue]]], n_s: int, runs_to_end: bool
) -> dict[str, list[Sequence[StatusValue]]]:
    """The status channels with one sample per step (see :func:`wide_columns`)."""
    aligned: dict[str, list[Sequence[StatusValue]]] = {}
    for channel, seqs in status.items():
        if len(seqs) == n_s:
            aligned[channel] = seqs
        elif runs_to_end and len(seqs) < n_s:
            aligned[channel] = [*([()] * (n_s - len(seqs))), *seqs]
        else:
            warnings.warn(
                f"status channel {channel!r} has {len(seqs)} samples for {n_s} steps;"
                " left out of the wide export",
                stacklevel=4,  # the caller of wide_columns' caller, as before this helper
            )
    return aligned


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

    aligned = _aligned_status(tr.status, n_s, status_runs_to_end)
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


def _whole(db_path: Path | str, run_id: int | None) -> tuple[Result, NDArray[np.int64]]:
    """A run and its recorded step numbers (the Trace has no step column)."""
    tail = RunTail(db_path, run_id)
    try:
        chunk = tail.read()
    finally:
        tail.close()
    return chunk.result, chunk.steps


def export_csv(db_path: Path | str, out_path: Path | str, run_id: int | None = None) -> None:
    """Export one run (latest by default) as a wide CSV."""
    result, steps = _whole(db_path, run_id)
    _write_csv(wide_columns(result, steps, status_runs_to_end=True), out_path)


def export_parquet(db_path: Path | str, out_path: Path | str, run_id: int | None = None) -> None:
    """Export one run (latest by default) as a wide Parquet table (NaN kept as NaN)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    result, steps = _whole(db_path, run_id)
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
