"""What a pilot wants from a replayed flight, beside PackPilot's verdicts (#27 §6): the charge
used against the autopilot's own counter, the autopilot's remaining and warnings next to what
PackPilot would have done, the flight modes on the time axis, and how far the voltage sagged
under current.

- **Charge used, PackPilot's count**: the logged discharge current integrated over the log's
  rows (trapezoid; charge flowing back counts negative), the same samples the replay read. The
  autopilot's counter (PX4 ``discharged_mah``, ArduPilot ``CurrTot``, MAVLink
  ``current_consumed``) integrates at its sensor rate, so the two differ by what the logging
  rate misses; both are shown with the difference.
- **Voltage sag**: a straight line ``V = V0 - R I`` through the samples that draw current
  (above 0.5 A): ``R`` is the log's apparent pack resistance (cells, wiring, connectors,
  the sensor's shunt) and ``R x peak current`` the sag at the peak. A cold pack that warms in
  flight sags less as it goes; one line is the flight's average.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.io.flightlog import WARNING_NAMES
from packpilot.replay.common import LogTable

F64 = NDArray[np.float64]
SAG_MIN_A = 0.5
"""Samples at or below this current are rest, not sag."""
SAG_MIN_SAMPLES = 10


def charge_mah(t_s: F64, current_a: F64) -> float:
    """Trapezoidal charge of the logged current in mAh (discharge positive)."""
    if len(t_s) < 2:
        return 0.0
    return float(np.sum(0.5 * (current_a[1:] + current_a[:-1]) * np.diff(t_s))) / 3.6


def sag(voltage_v: F64, current_a: F64) -> dict[str, float] | None:
    """The straight line V = V0 - R I through the loaded samples, or None when the log does not
    move its current enough to draw one."""
    m = np.isfinite(voltage_v) & np.isfinite(current_a) & (current_a > SAG_MIN_A)
    if m.sum() < SAG_MIN_SAMPLES or np.ptp(current_a[m]) < 2.0:
        return None
    slope, v0 = np.polyfit(current_a[m], voltage_v[m], 1)
    peak = float(np.max(current_a[m]))
    return {
        "resistance_ohm": float(-slope), "v0_v": float(v0), "peak_a": peak,
        "sag_at_peak_v": float(-slope * peak), "samples": int(m.sum()),
    }  # fmt: skip


def _series(log: LogTable, name: str) -> Any:
    flight = log.flight
    if flight is None:
        return None
    return next((b for b in flight.batteries if b.name == name), None)


def battery_account(log: LogTable, name: str) -> dict[str, object]:
    """One battery: PackPilot's charge count and the autopilot's, its remaining and warnings."""
    t = log.columns["t_s"]
    cur = log.columns.get(f"{name}_current_a")
    out: dict[str, object] = {
        "packpilot_mah": None if cur is None else charge_mah(t, cur),
        "autopilot_mah": None, "remaining_start": None, "remaining_end": None,
        "remaining_lowest": None, "warning_first_t_s": None, "warning_worst": None,
    }  # fmt: skip
    b = _series(log, name)
    if b is None:
        return out
    d = b.discharged_mah
    if d is not None and np.isfinite(d).any() and np.nanmax(d) > 0:
        out["autopilot_mah"] = float(np.nanmax(d) - np.nanmin(d[np.isfinite(d)][:1]))
    if b.soc is not None and np.isfinite(b.soc).any():
        ok = b.soc[np.isfinite(b.soc)]
        out.update(remaining_start=float(ok[0]), remaining_end=float(ok[-1]),
                   remaining_lowest=float(ok.min()))  # fmt: skip
    if b.warning is not None and np.any(b.warning > 0):
        worst = int(np.max(b.warning))
        out["warning_worst"] = WARNING_NAMES[worst] if worst < len(WARNING_NAMES) else str(worst)
        out["warning_first_t_s"] = float(b.t_s[int(np.argmax(b.warning > 0))])
    return out


def modes(log: LogTable) -> list[list[object]]:
    """The flight modes as [t_s, name] on the log's time axis (empty when the log has none)."""
    flight = log.flight
    if flight is None:
        return []
    return [[float(t), str(m)] for t, m in flight.modes]


def pilot_summary(log: LogTable, names: list[str]) -> dict[str, object]:
    """The pilot's section of ``replay flight``'s summary."""
    accounts = {n: battery_account(log, n) for n in names if n}
    sags: dict[str, object] = {}
    for n in names:
        prefix = f"{n}_" if n else ""
        v = log.columns.get(f"{prefix}voltage_v")
        i = log.columns.get(f"{prefix}current_a")
        if v is not None and i is not None:
            sags[n or "battery"] = sag(v, i)
    texts = [] if log.flight is None else [[float(t), str(m)] for t, m in log.flight.texts]
    return {"charge": accounts, "flight_modes": modes(log), "sag": sags, "texts": texts}


def charge_lines(summary: dict[str, object]) -> list[str]:
    """Short sentences: charge used by both counts, remaining, warnings."""
    lines = []
    charge = summary.get("charge")
    assert isinstance(charge, dict)
    for name, a in charge.items():
        mine, theirs = a["packpilot_mah"], a["autopilot_mah"]
        if mine is None:
            continue
        text = f"{name}: {mine:.0f} mAh used by PackPilot's count of the logged current"
        if theirs is not None:
            diff = mine - theirs
            rel = f" ({100 * diff / theirs:+.1f} %)" if theirs > 0 else ""
            text += f"; the autopilot counted {theirs:.0f} mAh, {diff:+.0f} mAh{rel}"
        else:
            text += "; the log has no charge counter of the autopilot's"
        if a["remaining_start"] is not None:
            text += (
                f"; the autopilot's remaining {100 * a['remaining_start']:.0f} % -> "
                f"{100 * a['remaining_end']:.0f} %"
            )
        lines.append(text)
    return lines


__all__ = ["battery_account", "charge_lines", "charge_mah", "modes", "pilot_summary", "sag"]
