"""Replay a logged discharge through the condition-dependent discharge protection.

Input: ``t_s`` and one battery's ``current_a, temp_c, min_cell_v`` (current positive =
discharge), unprefixed or as ``<battery>_current_a, …`` — what ``simulate --trace-csv`` writes
and ``packpilot import`` produces; or a flight log read directly. Each row holds from its
``t_s`` until the next row's; the last row lasts as long as the previous step. The log is fed,
row by row, to the same :class:`ProtectionController` the closed loop uses (one battery), so a
replay answers "when would this log have tripped, and under which parameter?" without any plant
model. A log without temperature replays only at a temperature the user states
(``--assume-temp-c``), and the summary says it was assumed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.protection import ProtectionConfig, ProtectionController
from packpilot.errors import InputError
from packpilot.replay.common import (
    CellValue,
    LogOptions,
    LogTable,
    ReplayResult,
    log_summary,
    open_log,
    row_durations,
)

HELP = (
    "Replay t_s and one battery's current_a, temp_c, min_cell_v (or <battery>_current_a, "
    "... as simulate --trace-csv and packpilot import write them; or a .ulg/.bin/.log "
    "flight log) through discharge protection."
)
"""The command's help: the column vocabulary it reads."""

REQUIRED_COLUMNS = ("t_s", "current_a", "temp_c", "min_cell_v")
OUTPUT_COLUMNS = ["t_s", "param", "cutoff_v", "weighted_s", "tripped"]

ONE_CELL = PackInfo(
    n_batteries=1,
    groups_per_battery=(1,),
    cells_per_group=(1,),
    switch_kind=(SwitchKind.MOSFET_PAIR,),
)


def _inputs(
    log: LogTable, options: LogOptions
) -> tuple[str, dict[str, NDArray[np.float64]], list[str]]:
    """(battery name, the four input columns, assumptions made) of the replayed battery."""
    prefix, name = log.battery_prefix(options.battery)
    cols = {c: f"{prefix}{c}" for c in REQUIRED_COLUMNS[1:]}
    assumed: list[str] = []
    missing = [cols["current_a"]]
    if cols["temp_c"] not in log.columns and options.assume_temp_c is None:
        missing.append(cols["temp_c"])
    if cols["min_cell_v"] not in log.columns and (
        options.cells is None or f"{prefix}voltage_v" not in log.columns
    ):
        missing.append(cols["min_cell_v"])
    log.require(
        ["t_s", *missing],
        {
            cols["temp_c"]: "no temperature: give --assume-temp-c T to replay at a stated "
            "constant temperature",
            cols["min_cell_v"]: "no cell voltage: give --cells N to use voltage_v / N",
        },
    )
    n = len(log)
    out = {"t_s": log.columns["t_s"], "current_a": log.columns[cols["current_a"]]}
    unused = [
        f"{flag} not used: the log has {col}"
        for flag, given, col in (
            ("--assume-temp-c", options.assume_temp_c, cols["temp_c"]),
            ("--cells", options.cells, cols["min_cell_v"]),
        )
        if given is not None and col in log.columns and log.source == "CSV"
    ]
    assumed += unused
    if cols["temp_c"] in log.columns:
        out["temp_c"] = log.columns[cols["temp_c"]]
    else:
        t = _assumed_temp(log, options)
        out["temp_c"] = np.full(n, t)
        assumed.append(f"temp_c = {t:g} degC throughout (--assume-temp-c): the log has none")
    if cols["min_cell_v"] in log.columns:
        out["min_cell_v"] = log.columns[cols["min_cell_v"]]
    else:
        cells = options.cells
        assert cells is not None
        if not 1 <= cells <= 1000:
            raise InputError(f"{log.path}: --cells {cells}: must be 1..1000")
        out["min_cell_v"] = log.columns[f"{prefix}voltage_v"] / cells
        assumed.append(
            f"min_cell_v = voltage_v / {cells} (--cells): the average cell; the log has no cell "
            "voltages, a weak cell would sit lower and trip earlier"
        )
    held = _pre_switch(log, prefix, out)
    if held:
        assumed.append(
            f"{held} row(s) where the recorded run's own BMS switched the battery ({prefix}dsg_on "
            "or chg_on changed) show the state after the switch; there the replay reads the "
            "previous row, the state that BMS decided on"
        )
    return name, out, assumed


def _pre_switch(log: LogTable, prefix: str, cols: dict[str, NDArray[np.float64]]) -> int:
    """A trace row at which the recorded BMS switched a FET holds the plant *after* the switch
    (current 0 once the discharge path opened), while that BMS measured the state before it:
    such rows take the previous row's current, temperature and cell voltage, so that a run's
    own trace replays to its own decisions. Returns the number of rows so treated."""
    gates = [log.columns[c] for c in (f"{prefix}dsg_on", f"{prefix}chg_on") if c in log.columns]
    if not gates or len(log) < 2:
        return 0
    switched = np.zeros(len(log), dtype=bool)
    for g in gates:
        switched[1:] |= g[1:] != g[:-1]
    rows = np.nonzero(switched)[0]
    for name in ("current_a", "temp_c", "min_cell_v"):
        col = cols[name].copy()
        col[rows] = col[rows - 1]
        cols[name] = col
    return int(rows.size)


def _assumed_temp(log: LogTable, options: LogOptions) -> float:
    t = options.assume_temp_c
    assert t is not None
    if not (math.isfinite(t) and -60.0 <= t <= 100.0):
        raise InputError(f"{log.path}: --assume-temp-c {t:g}: must be a temperature in -60..100")
    return t


def replay(
    log_path: Path | LogTable, config: ProtectionConfig, options: LogOptions | None = None
) -> ReplayResult:
    """Run the protection over a log; one output row per input row plus a summary.

    ``trip_time_s`` is the end of the row in which the weighted sum reaches m (row ``t_s`` plus
    its duration): five 1 s rows under P3 starting at t = 0 trip at 5.0 s.
    """
    options = options or LogOptions()
    log = log_path if isinstance(log_path, LogTable) else open_log(log_path, options)
    battery, cols, assumed = _inputs(log, options)
    t, cur, temp, vmin = cols["t_s"], cols["current_a"], cols["temp_c"], cols["min_cell_v"]
    dur = row_durations(t)
    ctl = ProtectionController(config, ONE_CELL)
    rows: list[list[CellValue]] = []
    trip_time: float | None = None
    param_at_trip: str | None = None
    cutoff_at_trip: float | None = None
    peak = 0.0
    for k in range(len(log)):
        v = float(vmin[k])
        bm = BatteryMeasurement(
            voltage_v=v,
            current_a=float(cur[k]),
            temp_c=float(temp[k]),
            min_cell_v=v,
            max_cell_v=v,
            soc=math.nan,
            full_capacity_ah=math.nan,
            remaining_capacity_ah=math.nan,
        )
        out = ctl.step(Measurements(t_s=float(t[k]), batteries=(bm,), bus_v=v), float(dur[k]))
        p = ctl.parameter(0)
        if trip_time is None and any(ev.kind == "ProtectionTripped" for ev in out.events):
            trip_time = round(float(t[k] + dur[k]), 9)
            param_at_trip = None if p is None else p.name
            cutoff_at_trip = None if p is None else p.cutoff_v
        st = ctl.battery(0)
        peak = max(peak, ctl.fraction(0))
        rows.append(
            [
                float(t[k]),
                None if p is None else p.name,
                None if p is None else p.cutoff_v,
                round(float(st.acc_wms) / 1000.0, 9),
                st.tripped,
            ]
        )
    summary: dict[str, object] = {
        "method": "protection",
        "battery": battery,
        "tripped": trip_time is not None,
        "trip_time_s": trip_time,
        "param_at_trip": param_at_trip,
        "cutoff_at_trip_v": cutoff_at_trip,
        "m_s": ctl.m_s,
        "weights": ctl.weights(),
        "final_fraction": ctl.fraction(0),
        "peak_fraction": peak,
        **log_summary(log, assumed=assumed),
        "config": config.model_dump(mode="json"),
    }
    return ReplayResult(columns=list(OUTPUT_COLUMNS), rows=rows, summary=summary)


__all__ = ["ONE_CELL", "OUTPUT_COLUMNS", "REQUIRED_COLUMNS", "replay"]
