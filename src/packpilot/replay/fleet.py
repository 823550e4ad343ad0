"""Battery health across flights: one SQLite record per flight per battery (fitted R0 and
capacity with their uncertainty, energy, charge, lowest cell, peak current, temperature, the
autopilot's warnings), and a report with one row per battery, its trend and its flags.

Identity: the log's serial number (PX4 ``serial_number``), else the label the user gives
(``--label``); a battery with neither is refused (two packs must not be merged by accident).
A flight is keyed by (battery, the log file's SHA-256 and the battery's name in it): adding the
same log twice keeps one record.

Flags (``fleet report``): R0 up by more than ``r0_rise`` (20 %) — the median of the last
:data:`RECENT` flights against the median of the first :data:`FIRST` — ; capacity down by more
than ``fade`` (10 %) on the same comparison, counted only over flights whose capacity was
identifiable; the cell spread (highest minus lowest measured cell, 95th percentile over a
flight; logs with real cells only) growing by more than ``spread_rise_v`` (20 mV) and by half
again, first flights against recent ones; an outlier — a battery whose recent R0 is more than
:data:`OUTLIER_MADS` robust deviations from the fleet's median of recent R0s (with three or
more batteries).
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import BatterySeries, read_flight_log
from packpilot.model.cell import load_parameter_set
from packpilot.model.fit.profile import Profile
from packpilot.model.fit.validate import fit_and_validate
from packpilot.replay.fitlogs import battery_profile

FIRST = 10
RECENT = 5
OUTLIER_MADS = 5.0
SCHEMA = """
CREATE TABLE IF NOT EXISTS flights (
  id INTEGER PRIMARY KEY,
  battery TEXT NOT NULL,
  log TEXT NOT NULL,
  log_sha256 TEXT NOT NULL,
  log_battery TEXT NOT NULL,
  r0_ohm REAL, r0_rel REAL, capacity_ah REAL, capacity_rel REAL, capacity_ok INTEGER,
  energy_wh REAL, charge_ah REAL, lowest_cell_v REAL, peak_current_a REAL, max_temp_c REAL,
  warnings TEXT, verdict TEXT, heldout_rmse_v REAL, cell_spread_v REAL,
  UNIQUE (battery, log_sha256, log_battery)
)
"""
SPREAD_QUANTILE = 0.95
"""A flight's cell spread: this quantile over its samples of (highest - lowest cell), so one
glitched sample does not set it."""
SPREAD_RISE_V = 0.020
"""Flag a battery whose recent cell spread exceeds its first flights' by more than this
(and by half again): cells drifting apart, a weak cell or a balancing problem."""


@dataclass(frozen=True)
class FlightRecord:
    battery: str
    log: str
    log_sha256: str
    log_battery: str
    r0_ohm: float
    r0_rel: float
    capacity_ah: float
    capacity_rel: float
    capacity_ok: bool
    energy_wh: float
    charge_ah: float
    lowest_cell_v: float
    peak_current_a: float
    max_temp_c: float | None
    warnings: str
    verdict: str
    heldout_rmse_v: float
    cell_spread_v: float | None = None
    """Highest minus lowest cell (95th percentile over the flight); None without real cells."""


def connect(db: Path) -> sqlite3.Connection:
    con = sqlite3.connect(db)
    con.execute(SCHEMA)
    have = {row[1] for row in con.execute("PRAGMA table_info(flights)")}
    if "cell_spread_v" not in have:  # a fleet recorded before the cell spread was kept
        con.execute("ALTER TABLE flights ADD COLUMN cell_spread_v REAL")
        con.commit()
    return con


def cell_spread(cells_v: np.ndarray | None) -> float | None:
    """A flight's cell spread from its measured cell voltages (samples, cells), or None when
    the log has fewer than two real cells."""
    if cells_v is None:
        return None
    real = cells_v[:, np.isfinite(cells_v).any(axis=0)]
    if real.shape[1] < 2:
        return None
    rows = real[np.isfinite(real).all(axis=1)]
    if not len(rows):
        return None
    return float(np.quantile(rows.max(axis=1) - rows.min(axis=1), SPREAD_QUANTILE))


def flight_record(battery: str, log: str, sha: str, name: str, prof: Profile,
                  series: int, warnings: str = "",
                  cells_v: np.ndarray | None = None) -> FlightRecord:  # fmt: skip
    """Fit one flight of one battery and summarise it."""
    cell = load_parameter_set("uav_5ah")
    v = fit_and_validate([prof], cell.ocv_soc, cell.ocv_table_v)
    p = v.result.params
    dt = np.diff(prof.t_s, prepend=prof.t_s[0])
    return FlightRecord(
        battery=battery, log=log, log_sha256=sha, log_battery=name,
        r0_ohm=p["r0_ohm"].value, r0_rel=p["r0_ohm"].rel_uncertainty,
        capacity_ah=p["capacity_ah"].value, capacity_rel=p["capacity_ah"].rel_uncertainty,
        capacity_ok=p["capacity_ah"].identifiable,
        energy_wh=float(np.sum(prof.voltage_v * series * prof.current_a * dt) / 3600.0),
        charge_ah=float(prof.drawn_ah[-1]), lowest_cell_v=float(np.min(prof.voltage_v)),
        peak_current_a=float(np.max(prof.current_a)),
        max_temp_c=None if prof.temp_c is None else float(np.max(prof.temp_c)),
        warnings=warnings, verdict=v.verdict, heldout_rmse_v=v.checks[0].rmse_v,
        cell_spread_v=cell_spread(cells_v),
    )  # fmt: skip


def store(con: sqlite3.Connection, rec: FlightRecord) -> bool:
    """Insert; False when that flight of that battery is already recorded."""
    cols = list(rec.__dataclass_fields__)
    cur = con.execute(
        f"INSERT OR IGNORE INTO flights ({', '.join(cols)}) VALUES "
        f"({', '.join('?' for _ in cols)})",
        [getattr(rec, c) for c in cols],
    )
    con.commit()
    return cur.rowcount == 1


def _warnings(b: BatterySeries) -> str:
    if b.warning is None or not np.any(b.warning > 0):
        return ""
    return f"worst level {int(np.max(b.warning))} in {int(np.sum(b.warning > 0))} samples"


def add_logs(db: Path, logs: Sequence[Path], label: str | None, cells: int | None,
             battery: str | None) -> list[str]:  # fmt: skip
    """``fleet add``: one record per flight per battery; returns one line per log."""
    con = connect(db)
    lines = []
    try:
        for path in logs:
            log = read_flight_log(path)
            sha = hashlib.sha256(path.read_bytes()).hexdigest()
            picks = [b for b in log.batteries if battery is None or b.name == battery]
            if not picks:
                raise InputError(f"{path}: --battery {battery}: not in the log")
            for b in picks:
                ident = b.serial_number or label
                if ident is None:
                    raise InputError(
                        f"{path}: battery {b.name} has no serial number in the log: give "
                        "--label NAME (the battery's own label)"
                    )
                if b.serial_number is None and len(picks) > 1:
                    ident = f"{label}-{b.name}"
                prof, _ = battery_profile(path, b, cells)
                series = b.cell_count or cells or 1
                rec = flight_record(ident, str(path), sha, b.name, prof, series, _warnings(b),
                                    b.cells_v)  # fmt: skip
                new = store(con, rec)
                lines.append(
                    f"{path.name}:{b.name} -> {ident}: R0 {1000 * rec.r0_ohm:.2f} mOhm "
                    f"(±{100 * rec.r0_rel:.0f} %), {rec.verdict}"
                    + ("" if new else " (already recorded: kept once)")
                )
    finally:
        con.close()
    return lines


def _median(x: Sequence[float]) -> float:
    return float(np.median(np.asarray(x))) if len(x) else float("nan")


def report(db: Path, r0_rise: float = 0.20, fade: float = 0.10,
           spread_rise_v: float = SPREAD_RISE_V) -> list[dict[str, object]]:  # fmt: skip
    """One row per battery: flights, R0, capacity and cell-spread trend, the flags."""
    if not db.exists():
        raise InputError(f"{db}: no such fleet database")
    con = connect(db)
    try:
        rows = con.execute(
            "SELECT battery, r0_ohm, capacity_ah, capacity_ok, lowest_cell_v, warnings, "
            "cell_spread_v FROM flights ORDER BY battery, id"
        ).fetchall()
    finally:
        con.close()
    by: dict[str, list[tuple[float, float, int, float, str, float | None]]] = {}
    for bat, *rest in rows:
        by.setdefault(bat, []).append(tuple(rest))
    out: list[dict[str, object]] = []
    for bat, fl in by.items():
        r0 = [f[0] for f in fl]
        caps = [f[1] for f in fl if f[2]]
        first, recent = _median(r0[:FIRST]), _median(r0[-RECENT:])
        row: dict[str, object] = {
            "battery": bat, "flights": len(fl), "r0_first_mohm": 1000 * first,
            "r0_recent_mohm": 1000 * recent, "r0_change_pct": 100 * (recent / first - 1),
            "lowest_cell_v": min(f[3] for f in fl),
            "warned_flights": sum(1 for f in fl if f[4]), "flags": [],
        }  # fmt: skip
        flags: list[str] = []
        if len(fl) > FIRST and recent > first * (1 + r0_rise):
            flags.append(f"R0 up {100 * (recent / first - 1):.0f} % (> {100 * r0_rise:.0f} %)")
        if len(caps) > FIRST:
            c0, c1 = _median(caps[:FIRST]), _median(caps[-RECENT:])
            row["capacity_change_pct"] = 100 * (c1 / c0 - 1)
            if c1 < c0 * (1 - fade):
                flags.append(f"capacity down {100 * (1 - c1 / c0):.0f} %")
        flags += _spread_trend(row, [f[5] for f in fl if f[5] is not None], spread_rise_v)
        row["flags"] = flags
        out.append(row)
    _outliers(out)
    return out


def _spread_trend(row: dict[str, object], spreads: list[float], rise_v: float) -> list[str]:
    """The cell-spread trend over the flights that measured cells: first flights against
    recent ones, as R0's; a flag when it grew by more than ``rise_v`` and by half again."""
    if not spreads:
        row["cell_spread_flights"] = 0
        return []
    first, recent = _median(spreads[:FIRST]), _median(spreads[-RECENT:])
    row.update(cell_spread_flights=len(spreads), cell_spread_first_mv=1000 * first,
               cell_spread_recent_mv=1000 * recent)  # fmt: skip
    if len(spreads) > FIRST and recent > first + rise_v and recent > 1.5 * first:
        return [f"cell spread growing: {1000 * first:.0f} -> {1000 * recent:.0f} mV"]
    return []


def _outliers(rows: list[dict[str, object]]) -> None:
    if len(rows) < 3:
        return
    rec = np.array([float(r["r0_recent_mohm"]) for r in rows])  # type: ignore[arg-type]
    med = float(np.median(rec))
    mad = float(np.median(np.abs(rec - med))) * 1.4826 or 1e-9
    for r, x in zip(rows, rec, strict=True):
        if abs(x - med) > OUTLIER_MADS * mad and abs(x - med) > 0.1 * med:
            flags = r["flags"]
            assert isinstance(flags, list)
            flags.append(f"outlier: recent R0 {x:.2f} mOhm vs fleet median {med:.2f} mOhm")


def flights(db: Path) -> dict[str, list[dict[str, object]]]:
    """Every battery's flights in the order they were added (the fleet view's trend lines)."""
    if not db.exists():
        raise InputError(f"{db}: no such fleet database")
    con = connect(db)
    try:
        cur = con.execute(
            "SELECT battery, log, r0_ohm, r0_rel, capacity_ah, capacity_ok, lowest_cell_v, "
            "cell_spread_v, verdict, warnings FROM flights ORDER BY battery, id"
        )
        names = [d[0] for d in cur.description]
        out: dict[str, list[dict[str, object]]] = {}
        for row in cur.fetchall():
            rec = dict(zip(names, row, strict=True))
            out.setdefault(str(rec.pop("battery")), []).append(rec)
    finally:
        con.close()
    return out


def report_json(rows: list[dict[str, object]]) -> str:
    return json.dumps(rows)


__all__ = [
    "FlightRecord", "add_logs", "cell_spread", "connect", "flight_record", "flights", "report",
    "store",
]  # fmt: skip
