"""Replay a logged discharge through the condition-dependent discharge protection.

Input CSV columns: ``t_s,current_a,temp_c,min_cell_v`` (current positive = discharge). Each row
holds from its ``t_s`` until the next row's; the last row lasts as long as the previous step.
The log is fed, row by row, to the same :class:`ProtectionController` the closed loop uses
(one battery), so a replay answers "when would this log have tripped, and under which
parameter?" without any plant model.
"""

from __future__ import annotations

import math
from pathlib import Path

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.protection import ProtectionConfig, ProtectionController
from packpilot.replay.common import CellValue, ReplayResult, read_log, row_durations

REQUIRED_COLUMNS = ("t_s", "current_a", "temp_c", "min_cell_v")
OUTPUT_COLUMNS = ["t_s", "param", "cutoff_v", "weighted_s", "tripped"]

_ONE_CELL = PackInfo(
    n_batteries=1,
    groups_per_battery=(1,),
    cells_per_group=(1,),
    switch_kind=(SwitchKind.MOSFET_PAIR,),
)


def replay(log_path: Path, config: ProtectionConfig) -> ReplayResult:
    """Run the protection over a log; one output row per input row plus a summary.

    ``trip_time_s`` is the end of the row in which the weighted sum reaches m (row ``t_s`` plus
    its duration): five 1 s rows under P3 starting at t = 0 trip at 5.0 s.
    """
    log = read_log(log_path, REQUIRED_COLUMNS)
    t = log.columns["t_s"]
    cur = log.columns["current_a"]
    temp = log.columns["temp_c"]
    vmin = log.columns["min_cell_v"]
    dur = row_durations(t)
    ctl = ProtectionController(config, _ONE_CELL)
    rows: list[list[CellValue]] = []
    trip_time: float | None = None
    param_at_trip: str | None = None
    cutoff_at_trip: float | None = None
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
        "tripped": trip_time is not None,
        "trip_time_s": trip_time,
        "param_at_trip": param_at_trip,
        "cutoff_at_trip_v": cutoff_at_trip,
        "m_s": ctl.m_s,
        "weights": ctl.weights(),
        "final_fraction": ctl.fraction(0),
        "rows": len(log),
    }
    return ReplayResult(columns=list(OUTPUT_COLUMNS), rows=rows, summary=summary)


__all__ = ["OUTPUT_COLUMNS", "REQUIRED_COLUMNS", "replay"]
