"""Flight logs turned into what the fit reads: one :class:`~packpilot.model.fit.profile.Profile`
per battery, per cell (the battery's voltage / series cells), with the autopilot's charge
counter as the state when the log has one.

A battery the fit cannot use is refused in one line naming what is missing: no current
measurement, no cell count (give ``--cells``), too few samples.

Lab cycler exports (a Maccor text export, :mod:`packpilot.io.cycler`) are read beside the
logs: one cell on one channel (``--cells N`` when the channel held N cells in series).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from packpilot.errors import InputError
from packpilot.io.cycler import is_cycler_export, read_maccor
from packpilot.io.flightlog import F64, BatterySeries, hold, read_flight_log
from packpilot.model.fit.profile import Profile

MIN_PEAK_A = 0.5
"""A battery whose logged current never reaches this has no usable current sensor."""


def _counter_ah(b: BatterySeries) -> F64 | None:
    """The autopilot's charge counter in Ah when it counts (rises over the log)."""
    d = b.discharged_mah
    if d is None or not np.isfinite(d).any():
        return None
    d = hold(np.asarray(d, dtype=np.float64))[0]
    if float(d[-1] - d[0]) <= 0.0 or np.any(np.diff(d) < -1.0):
        return None
    out: F64 = d / 1000.0
    return out


def battery_profile(path: Path, b: BatterySeries, cells: int | None) -> tuple[Profile, list[str]]:
    """One battery's profile and what was assumed or derived for it."""
    label = f"{path.name}:{b.name}"
    if b.current_a is None:
        raise InputError(f"{path}: battery {b.name}: no current measurement in the log: cannot fit")
    n = b.cell_count or cells
    if not n:
        raise InputError(
            f"{path}: battery {b.name}: the log has no cell count: give --cells N (series cells)"
        )
    notes = []
    if not b.cell_count:
        notes.append(f"{label}: {n} series cells (--cells)")
    if b.time_derived:
        notes.append(f"{label}: time derived: {b.time_derived}")
    if not np.any(np.asarray(b.voltage_v) > 0.0):
        raise InputError(
            f"{path}: battery {b.name}: voltage is 0 throughout (no voltage measurement): "
            "cannot fit"
        )
    cur = hold(np.asarray(b.current_a, dtype=np.float64))[0]
    if float(np.max(np.abs(cur))) < MIN_PEAK_A:
        raise InputError(
            f"{path}: battery {b.name}: current is {float(np.max(np.abs(cur))):g} A at most "
            "(the current sensor reads nothing): cannot fit"
        )
    volt = hold(np.asarray(b.voltage_v, dtype=np.float64))[0] / n
    counter = _counter_ah(b)
    notes.append(
        f"{label}: state of charge from "
        + ("the autopilot's charge counter" if counter is not None else "the sampled current")
    )
    temp = None if b.temp_c is None else hold(np.asarray(b.temp_c, dtype=np.float64))[0]
    try:
        prof = Profile(label, np.asarray(b.t_s, dtype=np.float64), cur, volt, counter, temp, n)
    except ValueError as err:
        raise InputError(f"{path}: battery {b.name}: {err}") from None
    return prof, notes


def cycler_profile(path: Path, cells: int | None) -> tuple[Profile, list[str]]:
    """A cycler channel's profile: one cell unless ``cells`` says how many in series."""
    c = read_maccor(path)
    n = cells or 1
    if float(np.max(np.abs(c.current_a))) <= 0.0:
        raise InputError(f"{path}: the channel's current is 0 throughout: nothing to fit")
    notes = [*c.notes, f"{path.name}: {n} series cell(s)" + ("" if cells else " (no --cells)")]
    try:
        prof = Profile(path.name, c.t_s, c.current_a, c.voltage_v / n, None, c.temp_c, n)
    except ValueError as err:
        raise InputError(f"{path}: {err}") from None
    return prof, notes


def profiles_from_logs(
    paths: list[Path], cells: int | None, battery: str | None
) -> tuple[list[Profile], list[str]]:
    """Every log's battery (``battery`` when a log has several)."""
    out: list[Profile] = []
    notes: list[str] = []
    for path in paths:
        if is_cycler_export(path):
            prof, more = cycler_profile(path, cells)
            out.append(prof)
            notes += more
            continue
        log = read_flight_log(path)
        names = [b.name for b in log.batteries]
        if battery is not None:
            pick = [b for b in log.batteries if b.name == battery]
            if not pick:
                raise InputError(f"{path}: --battery {battery}: the log has {', '.join(names)}")
        elif len(names) > 1:
            raise InputError(
                f"{path}: the log has batteries {', '.join(names)}: give --battery NAME "
                "(batteries of one log are different batteries)"
            )
        else:
            pick = log.batteries
        prof, more = battery_profile(path, pick[0], cells)
        out.append(prof)
        notes += more
    return out, notes


__all__ = ["battery_profile", "cycler_profile", "profiles_from_logs"]
