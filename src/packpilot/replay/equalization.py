"""Replay a logged string (time, current, group voltages) through the equalization controller.

Input: ``t_s`` and one battery's ``current_a, g0_v, …, g{M-1}_v`` (group voltages in V, current
positive = discharge), unprefixed or as ``<battery>_current_a, <battery>_g0_v, …`` (what
``simulate --trace-csv`` writes); the older ``current_a, v_0, …, v_{M-1}`` is still read.
Each row is held for its duration (until the next row), exactly as the closed loop would step
the controller. Output per row and group: ΔV (mV), AH, remaining balancing time, commanded
equalizer current. The summary gives the final AH, the number of updates of each kind and the
charge the equalizers were commanded to move.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.equalization import EqualizationConfig, EqualizationController
from packpilot.errors import InputError
from packpilot.replay.common import (
    CellValue,
    LogOptions,
    LogTable,
    ReplayResult,
    log_summary,
    open_log,
    refuse_options,
    row_durations,
)

HELP = (
    "Replay t_s and one battery's current_a, g0_v..g{M-1}_v (or <battery>_current_a, "
    "<battery>_g<k>_v; older v_k too) through Newton-iterated equalization."
)
"""The command's help: the column vocabulary it reads."""

MAX_UPDATES_PER_ROW = 100_000
"""Most times one row may apply formula 1 or 2 (its duration / min(T1, T2)). A row held for
a 1e308 s gap looped that many times; a day's gap at T2 = 60 s is 1,440."""


def _check_gaps(path: Path, durations: NDArray[np.float64], config: EqualizationConfig) -> None:
    """Refuse a log whose time gaps would apply the formulas more than the bound allows."""
    per_row = durations / min(config.t1_s, config.t2_s)
    k = int(np.argmax(per_row))
    if per_row[k] > MAX_UPDATES_PER_ROW:
        raise InputError(
            f"{path}: row {k + 2}, column t_s: a gap of {durations[k]:g} s would apply the "
            f"balancing formulas {per_row[k]:.3g} times (at most {MAX_UPDATES_PER_ROW:,}); "
            "split the log at the gap"
        )


def _columns(log: LogTable, options: LogOptions) -> tuple[str, str, list[str]]:
    """(battery, current column, group-voltage columns) in either vocabulary."""
    if "v_0" in log.columns:
        log.require(["t_s", "current_a"])
        return "", "current_a", log.indexed("v")
    prefix, name = log.battery_prefix(options.battery)
    groups = log.indexed(f"{prefix}g", "_v")
    log.require(
        ["t_s", f"{prefix}current_a", *([] if groups else [f"{prefix}g0_v"])],
        {f"{prefix}g0_v": "no group voltages: the log does not carry them one by one"},
    )
    return name, f"{prefix}current_a", groups


def replay(
    log_path: Path | LogTable, config: EqualizationConfig, options: LogOptions | None = None
) -> ReplayResult:
    """Run :class:`EqualizationController` over a group-voltage log of one string."""
    options = options or LogOptions()
    path = log_path.path if isinstance(log_path, LogTable) else log_path
    refuse_options(path, options, "equalization", "assume_temp_c", "cells")
    log = log_path if isinstance(log_path, LogTable) else open_log(log_path, options)
    battery, cur_col, v_cols = _columns(log, options)
    m = len(v_cols)
    t = log.columns["t_s"]
    cur = log.columns[cur_col]
    volts = [log.columns[c] for c in v_cols]
    durations = row_durations(t)
    _check_gaps(log.path, durations, config)
    pack = PackInfo(
        n_batteries=1,
        groups_per_battery=(m,),
        cells_per_group=(1,),
        switch_kind=(SwitchKind.RELAY,),
        has_balancers=True,
    )
    ctrl = EqualizationController(config, pack)
    columns = ["t_s", "current_a"]
    for k in range(m):
        columns += [f"dv_mv_g{k}", f"ah_g{k}", f"time_s_g{k}", f"i_eq_a_g{k}", f"owed_ah_g{k}"]
    rows: list[list[CellValue]] = []
    n_events = 0
    for i in range(len(log)):
        gv = tuple(float(v[i]) for v in volts)
        bm = BatteryMeasurement(
            voltage_v=sum(gv),
            current_a=float(cur[i]),
            temp_c=25.0,
            min_cell_v=min(gv),
            max_cell_v=max(gv),
            soc=0.5,
            full_capacity_ah=0.0,
            remaining_capacity_ah=0.0,
            group_voltages_v=gv,
        )
        out = ctrl.step(
            Measurements(t_s=float(t[i]), batteries=(bm,), bus_v=bm.voltage_v),
            float(durations[i]),
        )
        n_events += sum(1 for e in out.events if e.kind == "BalancingUpdated")
        row: list[CellValue] = [float(t[i]), float(cur[i])]
        for k in range(m):
            row += [
                out.status[f"eq_dv_mv_g{k}"][0],
                out.status[f"eq_ah_g{k}"][0],
                out.status[f"eq_time_s_g{k}"][0],
                out.status[f"eq_i_a_g{k}"][0],
                out.status[f"eq_owed_ah_g{k}"][0],
            ]
        rows.append(row)
    st = ctrl.strings[0]
    summary: dict[str, object] = {
        "method": "equalization",
        "battery": battery,
        **log_summary(log),
        "groups": m,
        "final_ah": list(st.ah),
        "updates": dict(st.counts),
        "balancing_events": n_events,
        "charge_granted_ah": list(st.ledger_granted_ah),
        "charge_owed_ah": list(st.owed_ah),
        "charge_commanded_ah": list(st.ledger_net_ah),
        "balancing_time_s": list(st.ledger_time_s),
        "config": config.model_dump(mode="json"),
    }
    return ReplayResult(columns=columns, rows=rows, summary=summary)


__all__ = ["replay"]
