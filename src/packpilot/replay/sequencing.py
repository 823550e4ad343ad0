"""Replay a logged parallel-battery discharge through the sequencing controller.

Input columns, per battery ``<name>_voltage_v, <name>_current_a`` (battery-side terminal
voltage and current, positive = discharge; what ``simulate --trace-csv`` writes and
``packpilot import`` produces), optional ``<name>_present`` (1 = inserted, 0 = not) and
``docked`` (1 = a charger is connected); the older numbered form ``v_0..v_{N-1},
i_0..i_{N-1}, present_k`` is still read. Every cell read must be a finite number. The output
has one row per input row with, per battery k (in the log's order), the commanded state and
FETs (``state_k, chg_k, dsg_k``), plus the pack-level ``mode``.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.sequencing import (
    SequencingConfig,
    SequencingController,
    battery_measurement,
)
from packpilot.errors import InputError
from packpilot.replay.common import (
    AUX,
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
    "Replay t_s and each battery's <name>_voltage_v, <name>_current_a (as simulate --trace-"
    "csv and packpilot import write them; older v_k, i_k too; or a flight log) through "
    "parallel discharge sequencing."
)
"""The command's help: the column vocabulary it reads."""

F64 = NDArray[np.float64]


def _flag_column(log: LogTable, name: str) -> NDArray[np.bool_]:
    """A 0/1 column as booleans; anything else is an input error naming the row."""
    col = log.columns[name]
    bad = np.nonzero((col != 0.0) & (col != 1.0))[0]
    if bad.size:
        row = int(bad[0]) + 2
        raise InputError(f"{log.path}: row {row}, column {name}: {col[bad[0]]:g} is not 0 or 1")
    flags: NDArray[np.bool_] = np.asarray(col == 1.0, dtype=bool)
    return flags


def _check_columns(log: LogTable) -> int:
    """Number of batteries; every ``v_k`` needs an ``i_k`` (and ``present_k`` if any)."""
    v_cols = log.indexed("v")
    n = len(v_cols)
    i_cols = [c for c in log.columns if c.startswith("i_") and c[2:].isdigit()]
    for k in range(n):
        if f"i_{k}" not in log.columns:
            raise InputError(f"{log.path}: column i_{k} is missing (battery {k} has v_{k})")
    for name in i_cols:
        if int(name[2:]) >= n:
            raise InputError(
                f"{log.path}: column {name} has no matching voltage column v_{name[2:]}"
            )
    present = [c for c in log.columns if c.startswith("present_")]
    if present:
        for k in range(n):
            if f"present_{k}" not in log.columns:
                raise InputError(
                    f"{log.path}: column present_{k} is missing "
                    f"(present_* columns must cover all {n} batteries)"
                )
        for name in present:
            idx = name.removeprefix("present_")
            if not idx.isdigit() or int(idx) >= n:
                raise InputError(f"{log.path}: column {name} matches no battery (0..{n - 1})")
    return n


def _named_inputs(log: LogTable) -> tuple[list[str], list[F64], list[F64], list[NDArray[np.bool_]]]:
    """Names, voltages, currents and presence of the batteries named in the log."""
    names = [b for b in log.batteries() if b and b != AUX]
    if not names:
        log.require(["A_voltage_v", "A_current_a"])  # names the vocabulary in the error
    log.require(["t_s", *(f"{b}_{c}" for b in names for c in ("voltage_v", "current_a"))])
    volts = [log.columns[f"{b}_voltage_v"] for b in names]
    currs = [log.columns[f"{b}_current_a"] for b in names]
    present = [
        _flag_column(log, f"{b}_present")
        if f"{b}_present" in log.columns
        else np.ones(len(log), dtype=bool)
        for b in names
    ]
    return names, volts, currs, present


def _numbered_inputs(
    log: LogTable,
) -> tuple[list[str], list[F64], list[F64], list[NDArray[np.bool_]]]:
    """The older ``v_k, i_k, present_k`` form."""
    log.require(["t_s"])
    n = _check_columns(log)
    volts = [log.columns[f"v_{k}"] for k in range(n)]
    currs = [log.columns[f"i_{k}"] for k in range(n)]
    present = (
        [_flag_column(log, f"present_{k}") for k in range(n)]
        if "present_0" in log.columns
        else [np.ones(len(log), dtype=bool) for _ in range(n)]
    )
    return [str(k) for k in range(n)], volts, currs, present


def replay(
    log_path: Path | LogTable, config: SequencingConfig, options: LogOptions | None = None
) -> ReplayResult:
    """Run :class:`SequencingController` over a log; one output row per input row."""
    options = options or LogOptions()
    path = log_path.path if isinstance(log_path, LogTable) else log_path
    refuse_options(path, options, "sequencing", "battery", "assume_temp_c")
    log = log_path if isinstance(log_path, LogTable) else open_log(log_path, options)
    numbered = "v_0" in log.columns or "i_0" in log.columns
    names, volts, currs, present = (_numbered_inputs if numbered else _named_inputs)(log)
    n = len(names)
    t = log.columns["t_s"]
    dts = row_durations(t)
    docked = _flag_column(log, "docked") if "docked" in log.columns else np.zeros(len(log), bool)

    # The log carries no cell count or capacity: one "cell" per battery; the charge limit uses
    # the config's default_capacity_ah.
    pack = PackInfo(
        n_batteries=n,
        groups_per_battery=(1,) * n,
        cells_per_group=(1,) * n,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
    )
    ctrl = SequencingController(config, pack)
    columns = ["t_s", "mode"]
    for k in range(n):
        columns += [f"state_{k}", f"chg_{k}", f"dsg_{k}"]
    rows: list[list[CellValue]] = []
    kinds: Counter[str] = Counter()
    joins: list[dict[str, object]] = []
    reverse: list[dict[str, object]] = []
    risk: list[dict[str, object]] = []
    max_diode_s = 0.0
    for r in range(len(log)):
        meas = Measurements(
            t_s=float(t[r]),
            batteries=tuple(
                battery_measurement(float(volts[k][r]), float(currs[k][r]), bool(present[k][r]))
                for k in range(n)
            ),
            bus_v=float("nan"),
            docked=bool(docked[r]),
        )
        out = ctrl.step(meas, float(dts[r]))
        row: list[CellValue] = [float(t[r]), ctrl.mode.value]
        for state, chg, dsg in zip(ctrl.states, ctrl.chg_on, ctrl.dsg_on, strict=True):
            row += [state.value, int(chg), int(dsg)]
        rows.append(row)
        for ev in out.events:
            kinds[ev.kind] += 1
            # the battery by its name in the log, as the headlines name it (index alongside)
            who = {"battery": _name(names, ev.battery), "index": ev.battery}
            if ev.kind == "BatteryJoined":
                joins.append({"t_s": ev.t_s, **who, "rule": ev.data.get("reason")})
            elif ev.kind == "ReverseCurrent":
                reverse.append({"t_s": ev.t_s, **who, "current_a": ev.data.get("current_a")})
            elif ev.kind == "CrossCurrentRisk":
                risk.append({"t_s": ev.t_s, **who, "predicted_a": ev.data.get("predicted_a")})
            elif ev.kind == "DiodeBypassed":
                c = ev.data.get("conduction_s")
                if isinstance(c, float):
                    max_diode_s = max(max_diode_s, c)
    summary: dict[str, object] = {
        "method": "sequencing",
        **log_summary(log),
        "batteries": names,
        "n_batteries": n,
        "transitions": dict(sorted(kinds.items())),
        "joins": joins,
        "reverse_current": reverse,
        "cross_current_risk": risk,
        "max_diode_conduction_s": max_diode_s,
        "final_states": [s.value for s in ctrl.states],
        "final_mode": ctrl.mode.value,
        "config": config.model_dump(mode="json"),
    }
    return ReplayResult(columns=columns, rows=rows, summary=summary)


def _name(names: list[str], k: int | None) -> str | None:
    """Battery ``k`` as the log names it (``A``, ``B``; a numbered log's ``0``, ``1``)."""
    if k is None or not 0 <= k < len(names):
        return None
    return names[k]


__all__ = ["replay"]
