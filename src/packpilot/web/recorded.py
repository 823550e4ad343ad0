"""A recorded run (a SQLite telemetry file) on the dashboard: the whole run at once, plus the
full-rate sample at any moment for the page's time scrubber.

The run is replayed into a :class:`LiveRun` in one go, so the page, the verdict and the API are
the ones of a live run that has ended; only ``kind`` says ``recorded``. The chart history is
the LiveRun's bounded overview; the scrubber reads the full-rate trace kept here.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.contract.record import Result, StepSample
from packpilot.errors import InputError
from packpilot.web.live import LiveRun, headline, jsonable_dict, sample_summary

SQLITE_MAGIC = b"SQLite format 3\x00"

_STATES = {"ok": "finished", "stopped": "stopped", "interrupted": "stopped"}


def is_sqlite(path: Path) -> bool:
    """The file starts with SQLite's header (what ``dashboard FILE`` takes for a recording)."""
    try:
        with path.open("rb") as f:
            return f.read(len(SQLITE_MAGIC)) == SQLITE_MAGIC
    except OSError:
        return False


def _section(config: dict[str, Any], name: str) -> dict[str, Any]:
    got = config.get(name)
    return got if isinstance(got, dict) else {}


class Recording:
    """One recorded run, loaded: ``live`` for the page, :meth:`at` for the scrubber."""

    def __init__(self, path: Path, run_id: int | None = None, max_points: int = 2000) -> None:
        from packpilot.io.telemetry import list_runs, load_run

        try:
            self.result: Result = load_run(path, run_id)
            row = next(r for r in list_runs(path) if r["id"] == self.result.run_id)
        except sqlite3.Error as err:  # a file changed under us, a locked or damaged page
            raise InputError(f"{path}: cannot read ({err})") from None
        trace = self.result.trace
        if len(trace.t_s) == 0:
            raise InputError(f"{path}: run {self.result.run_id} has no samples")
        self.path = path
        self.run_id = self.result.run_id
        config = row["config"] if isinstance(row["config"], dict) else {}
        names = list(self.result.battery_names)
        pack = _section(config, "pack")
        sim = _section(config, "sim")
        dt_s = float(sim.get("dt_s") or (trace.t_s[1] - trace.t_s[0] if len(trace.t_s) > 1 else 0))
        self.live = LiveRun(
            scenario=str(pack.get("name") or path.stem),
            duration_s=float(trace.t_s[-1]) + dt_s,
            dt_s=dt_s,
            speed=0.0,
            max_points=max_points,
            battery_names=names,
            kind="recorded",
            source=f"{path.name}, run {self.run_id}",
            db=str(path),
        )
        self.live.run_id = self.run_id
        self._fill(config, names, str(row["status"]))

    def _fill(self, config: dict[str, Any], names: list[str], status: str) -> None:
        live = self.live
        live.on_start(names, config)
        for k in range(len(self.result.trace.t_s)):
            live.on_sample(self.sample(k))
        live.on_events(self.result.events)
        state = _STATES.get(status, "error")
        live.on_finish(self.result.metrics, state)
        if state != "finished":
            live.error = f"the recording's status is {status!r}"

    def sample(self, k: int) -> StepSample:
        """Row ``k`` of the trace as the StepSample it was recorded from."""
        tr = self.result.trace
        return StepSample(
            step=int(tr.step[k]) if tr.step is not None else k,
            t_s=float(tr.t_s[k]),
            bus_v=float(tr.bus_v[k]),
            load_demand_a=float(tr.load_demand_a[k]),
            load_a=float(tr.load_a[k]),
            charger_v=float(tr.charger_v[k]),
            charger_a=float(tr.charger_a[k]),
            battery=tr.battery[k],
            group_v=tr.group_v[k],
            status={ch: seq[k] for ch, seq in tr.status.items() if k < len(seq)},
            aux=tr.aux[k] if tr.aux is not None else None,
        )

    def at(self, t_s: float) -> dict[str, Any]:
        """The full-rate sample at or just before ``t_s`` (clamped to the run), with the
        headline numbers then and how many events had happened by then."""
        tr = self.result.trace
        # 1 µs of slack: a step's time accumulated in floating point (4.999999 for 5.0)
        found = int(np.searchsorted(tr.t_s, t_s + 1e-6, side="right"))
        k = max(0, min(len(tr.t_s) - 1, found - 1))
        s = self.sample(k)
        names = list(self.result.battery_names)
        summary = sample_summary(s, names)
        t = float(tr.t_s[k])
        n_events = sum(1 for e in self.result.events if not e.t_s > t)
        return jsonable_dict(
            {
                "index": k,
                "t_s": t,
                "latest": summary,
                "headline": headline(summary, self.live.topology.roles),
                "n_events": n_events,
            }
        )
