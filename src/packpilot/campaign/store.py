"""Result storage: one Parquet row per run, written batch by batch, consolidated at the end.

Each finished batch is written at once as a part file in ``<out>.parts/`` (atomic rename), so
an interrupted campaign keeps what it computed; the parts are consolidated into ``<out>`` at
the end. The file's metadata records the campaign's identity (:func:`campaign_meta`), so
``resume`` can skip every run index already recorded (ok or error) and refuse a file made with
another seed, spreads or configuration.
"""

from __future__ import annotations

import hashlib
import json
import os
import uuid
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from packpilot.campaign.spreads import PARAM_COLUMNS, Spread, _spreads_canonical
from packpilot.config import ScenarioConfig
from packpilot.errors import InputError

if TYPE_CHECKING:
    import pyarrow as pa

META_KEY = b"packpilot.campaign"
ID_COLUMNS: tuple[str, ...] = ("run", "seed", *PARAM_COLUMNS, "status", "error", "wall_time_s")


def campaign_meta(cfg: ScenarioConfig, spreads: Mapping[str, Spread], seed: int) -> dict[str, Any]:
    return {
        "version": 1,
        "seed": seed,
        "spreads": _spreads_canonical(spreads),
        "config_sha256": hashlib.sha256(cfg.model_dump_json().encode()).hexdigest(),
        "battery_names": [b.name for b in cfg.pack.batteries],
    }


def _table_from_rows(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> pa.Table:
    import pyarrow as pa

    cols: list[str] = list(ID_COLUMNS)
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    table = pa.Table.from_pylist([{c: r.get(c) for c in cols} for r in rows])
    return table.replace_schema_metadata({META_KEY: json.dumps(meta).encode()})


VERDICT_COLUMNS: tuple[str, ...] = ("verdict", "alarms", "overdischarged_at_end")
"""Each ok run's verdict (see :mod:`packpilot.campaign.execute`), right after the ids."""


def _order_columns(names: Sequence[str]) -> list[str]:
    ids = [c for c in (*ID_COLUMNS, *VERDICT_COLUMNS) if c in names]
    rest = [c for c in names if c not in ids and not c.startswith("events_")]
    events = sorted(c for c in names if c.startswith("events_"))
    return ids + rest + events


@dataclass
class ResultStore:
    """``<out>`` (consolidated) plus ``<out>.parts/`` (one part file per finished batch)."""

    out: Path
    meta: dict[str, Any]

    @property
    def parts_dir(self) -> Path:
        return self.out.with_name(self.out.name + ".parts")

    def clear(self) -> None:
        """Start afresh (no resume): remove the previous result and its parts."""
        if self.parts_dir.exists():
            for p in self.parts_dir.iterdir():
                p.unlink()
            self.parts_dir.rmdir()
        if self.out.exists():
            self.out.unlink()

    def _files(self) -> list[Path]:
        files = [self.out] if self.out.exists() else []
        if self.parts_dir.exists():
            files += sorted(self.parts_dir.glob("part-*.parquet"))
        return files

    def _check_meta(self, path: Path, table: pa.Table) -> None:
        raw = (table.schema.metadata or {}).get(META_KEY)
        if raw is None:
            raise InputError(f"{path}: not a PackPilot campaign result (no campaign metadata)")
        theirs = json.loads(raw)
        for key in ("seed", "spreads", "config_sha256"):
            if theirs.get(key) != self.meta.get(key):
                raise InputError(
                    f"{path}: cannot resume: it was made with a different {key} "
                    f"({theirs.get(key)!r}, now {self.meta.get(key)!r})"
                )

    def read(self) -> pa.Table | None:
        """Everything recorded so far (final file + parts), one row per run, sorted by run."""
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq

        tables = []
        for path in self._files():
            try:
                t = pq.read_table(path)
            except (OSError, pa.ArrowInvalid) as err:
                raise InputError(f"{path}: unreadable campaign result ({err})") from None
            self._check_meta(path, t)
            tables.append(t.replace_schema_metadata(None))
        if not tables:
            return None
        table = pa.concat_tables(tables, promote_options="permissive")
        # First occurrence of each run wins (the consolidated file comes first).
        runs = table.column("run").to_numpy()
        _, first = np.unique(runs, return_index=True)
        table = table.take(pa.array(np.sort(first)))
        table = table.take(pc.sort_indices(table, sort_keys=[("run", "ascending")]))
        table = table.select(_order_columns(table.column_names))
        return self._fill_event_counts(table)

    @staticmethod
    def _fill_event_counts(table: pa.Table) -> pa.Table:
        """An ok run without an ``events_X`` column had zero X events (not an unknown count)."""
        import pyarrow as pa
        import pyarrow.compute as pc

        ok = pc.equal(table.column("status"), "ok")
        for i, name in enumerate(table.column_names):
            if name.startswith("events_"):
                col = pc.cast(table.column(name), pa.int64())
                filled = pc.if_else(pc.and_(ok, pc.is_null(col)), 0, col)
                table = table.set_column(i, name, filled)
        return table

    def done_runs(self) -> set[int]:
        table = self.read()
        return set() if table is None else {int(x) for x in table.column("run").to_pylist()}

    def write_part(self, rows: Sequence[Mapping[str, Any]]) -> Path:
        """Write one finished batch atomically (tmp + rename): a crash never leaves half a part."""
        import pyarrow.parquet as pq

        self.parts_dir.mkdir(parents=True, exist_ok=True)
        first = min(int(r["run"]) for r in rows)
        path = self.parts_dir / f"part-{first:08d}-{uuid.uuid4().hex[:8]}.parquet"
        tmp = path.with_suffix(".tmp")
        pq.write_table(_table_from_rows(rows, self.meta), tmp)
        os.replace(tmp, path)
        return path

    def consolidate(self) -> pa.Table:
        """Merge final file + parts into ``out`` (atomic), then drop the parts."""
        import pyarrow.parquet as pq

        table = self.read()
        if table is None:
            table = _table_from_rows([], self.meta)
        table = table.replace_schema_metadata({META_KEY: json.dumps(self.meta).encode()})
        self.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.out.with_name(self.out.name + ".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, self.out)
        if self.parts_dir.exists():
            for p in self.parts_dir.glob("part-*.parquet"):
                p.unlink()
            for p in self.parts_dir.glob("*.tmp"):
                p.unlink()
            self.parts_dir.rmdir()
        return table
