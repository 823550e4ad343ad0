"""Does a what-if leave the range its fitted cell set was fitted on? (#27 §4)

A cell set written by ``packpilot fit`` records in ``notes.window`` the SOC, cell current and
temperature its logs covered (and ``notes.reference_temp_c``, the temperature its resistances
were fitted at). A run on such a set that takes a battery beyond that range is extrapolating:
the fitted resistances, capacity and OCV were never checked there. Each battery that does gets
one warning row in the run's verdict (kind ``OutsideFit``, category ``extrapolated``, so
``simulate --fail-on extrapolated`` can stop a script), naming the quantity, how far it went,
the fitted range and when it first left it. Shipped sets (no ``window``) are never flagged.

Margins keep a run that merely touches the edge quiet: 2 % of SOC, 5 % of the largest fitted
current (at least 0.5 A), 5 K of temperature; a log without temperature counts as having
covered its reference temperature +-5 K.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.record import BATTERY_CHANNELS

F64 = NDArray[np.float64]
SOC_MARGIN = 0.02
CURRENT_MARGIN_REL = 0.05
CURRENT_MARGIN_MIN_A = 0.5
TEMP_MARGIN_K = 5.0
_CH = {name: k for k, name in enumerate(BATTERY_CHANNELS)}


def fitted_window(cell: str) -> dict[str, Any] | None:
    """The ``notes`` of a fitted cell-set file (``window`` and the reference temperature), or
    None for a shipped set or a file without them."""
    if not cell.endswith(".json"):
        return None
    try:
        notes = json.loads(Path(cell).read_text(encoding="utf-8-sig")).get("notes")
    except (OSError, ValueError, AttributeError):
        return None
    if not isinstance(notes, dict) or not isinstance(notes.get("window"), dict):
        return None
    return notes


def _first(mask: NDArray[np.bool_], t: F64) -> float | None:
    return float(t[int(np.argmax(mask))]) if mask.any() else None


def _logged_temperature(notes: Mapping[str, Any]) -> bool:
    w = notes["window"]
    return w.get("temp_min_c") is not None and w.get("temp_max_c") is not None


def _temperature_range(notes: Mapping[str, Any]) -> tuple[float, float]:
    w = notes["window"]
    if _logged_temperature(notes):
        return float(w["temp_min_c"]), float(w["temp_max_c"])
    ref = float(notes.get("reference_temp_c", 25.0))
    return ref, ref


def battery_excursions(
    notes: Mapping[str, Any], t_s: F64, soc: F64, cell_current_a: F64, temp_c: F64
) -> list[tuple[float, str]]:
    """(first time, what) for every quantity of one battery outside the fitted window."""
    w = notes["window"]
    out: list[tuple[float, str]] = []
    lo, hi = float(w["soc_min"]), float(w["soc_max"])
    for mask, word, x in ((soc < lo - SOC_MARGIN, "down to", soc.min()),
                          (soc > hi + SOC_MARGIN, "up to", soc.max())):  # fmt: skip
        t = _first(mask, t_s)
        if t is not None:
            out.append(
                (t, f"SOC {word} {100 * x:.0f} %, fitted on {100 * lo:.0f}-{100 * hi:.0f} %")
            )
    i_lo, i_hi = float(w["current_min_a"]), float(w["current_max_a"])
    margin = max(CURRENT_MARGIN_REL * max(abs(i_lo), abs(i_hi)), CURRENT_MARGIN_MIN_A)
    for mask, x in ((cell_current_a > i_hi + margin, cell_current_a.max()),
                    (cell_current_a < i_lo - margin, cell_current_a.min())):  # fmt: skip
        t = _first(mask, t_s)
        if t is not None:
            out.append((t, f"cell current {x:.1f} A, fitted on {i_lo:.1f}..{i_hi:.1f} A"))
    t_lo, t_hi = _temperature_range(notes)
    how, rng = "temperature", f"fitted on {t_lo:.1f}..{t_hi:.1f} degC"
    if not _logged_temperature(notes):
        how, rng = "start temperature", f"the logs carry none (fitted as at {t_lo:.1f} degC)"
        # The flight's own temperatures were never logged (its pack warmed, unrecorded): only
        # the start, the ambient the what-if sets, is compared with the reference temperature.
        temp_c = np.where(np.arange(len(temp_c)) == 0, temp_c, np.nan)
    ok = np.isfinite(temp_c)
    low = float(np.nanmin(temp_c)) if ok.any() else 0.0
    high = float(np.nanmax(temp_c)) if ok.any() else 0.0
    cold = ok & (temp_c < t_lo - TEMP_MARGIN_K)
    hot = ok & (temp_c > t_hi + TEMP_MARGIN_K)
    for mask, x in ((cold, low), (hot, high)):
        t = _first(mask, t_s)
        if t is not None:
            out.append((t, f"{how} {x:.1f} degC, {rng}"))
    return sorted(out)


def excursions(
    config: Mapping[str, Any] | None, names: Sequence[str], t_s: F64, battery: F64
) -> dict[str, list[tuple[float, str]]]:
    """Per battery name on a fitted cell set: its excursions (empty lists left out).
    ``battery`` is the trace's (rows, batteries, BATTERY_CHANNELS) array."""
    if not config or not len(t_s):
        return {}
    pack = config.get("pack", {})
    out: dict[str, list[tuple[float, str]]] = {}
    for k, name in enumerate(names):
        bat = next((b for b in pack.get("batteries", []) if b.get("name") == name), None)
        if bat is None or k >= battery.shape[1]:
            continue
        notes = fitted_window(str(bat.get("cell") or pack.get("cell", "")))
        if notes is None:
            continue
        rows = battery[:, k, :]
        found = battery_excursions(
            notes, t_s, rows[:, _CH["soc"]],
            rows[:, _CH["current_a"]] / max(int(bat.get("cells_per_group", 1)), 1),
            rows[:, _CH["temp_c"]],
        )  # fmt: skip
        if found:
            out[name] = found
    return out


__all__ = ["battery_excursions", "excursions", "fitted_window"]
