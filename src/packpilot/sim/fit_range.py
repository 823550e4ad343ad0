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


class Excursions:
    """One battery's excursions beyond its fitted window, folded block by block: the live
    dashboard's verdict feeds it as the run goes, a finished run's whole trace is one block,
    and both end with the same rows (first time of each quantity, how far the run went)."""

    def __init__(self, notes: Mapping[str, Any]) -> None:
        w = notes["window"]
        self.soc_lo, self.soc_hi = float(w["soc_min"]), float(w["soc_max"])
        self.i_lo, self.i_hi = float(w["current_min_a"]), float(w["current_max_a"])
        self.i_margin = max(CURRENT_MARGIN_REL * max(abs(self.i_lo), abs(self.i_hi)),
                            CURRENT_MARGIN_MIN_A)  # fmt: skip
        self.t_lo, self.t_hi = _temperature_range(notes)
        self.logged = _logged_temperature(notes)
        ocv = notes.get("ocv")
        win = ocv.get("window_soc") if isinstance(ocv, dict) else None
        self.ocv_note = (
            f"; its OCV was corrected from the data on {100 * float(win[0]):.0f}-"
            f"{100 * float(win[1]):.0f} % and that correction is held at its edge value "
            "beyond (not fitted there)"
            if isinstance(win, list) and len(win) == 2 else ""
        )  # fmt: skip
        self.first: dict[str, float] = {}
        self.ext = {"soc_min": np.inf, "soc_max": -np.inf, "i_min": np.inf, "i_max": -np.inf,
                    "t_min": np.inf, "t_max": -np.inf}  # fmt: skip
        self.n = 0

    def _mark(self, key: str, mask: NDArray[np.bool_], t_s: F64) -> None:
        t = _first(mask, t_s)
        if t is not None and key not in self.first:
            self.first[key] = t

    def _fold(self, key: str, x: F64, fn: Any) -> None:
        ok = np.isfinite(x)
        if ok.any():
            kind = "min" if fn is np.fmin else "max"
            pick = float(x[ok].min() if kind == "min" else x[ok].max())
            self.ext[key] = float(fn(self.ext[key], pick))

    def feed(self, t_s: F64, soc: F64, cell_current_a: F64, temp_c: F64) -> None:
        """The next block of samples of this battery, in order."""
        if not len(t_s):
            return
        with np.errstate(invalid="ignore"):
            self._mark("soc_low", soc < self.soc_lo - SOC_MARGIN, t_s)
            self._mark("soc_high", soc > self.soc_hi + SOC_MARGIN, t_s)
            self._mark("i_high", cell_current_a > self.i_hi + self.i_margin, t_s)
            self._mark("i_low", cell_current_a < self.i_lo - self.i_margin, t_s)
            if not self.logged:
                # The flight's own temperatures were never logged (its pack warmed,
                # unrecorded): only the start, the ambient the what-if sets, is compared with
                # the reference temperature.
                temp_c = np.where(np.arange(len(temp_c)) + self.n == 0, temp_c, np.nan)
            self._mark("cold", temp_c < self.t_lo - TEMP_MARGIN_K, t_s)
            self._mark("hot", temp_c > self.t_hi + TEMP_MARGIN_K, t_s)
        for key, x, fn in (("soc_min", soc, np.fmin), ("soc_max", soc, np.fmax),
                           ("i_min", cell_current_a, np.fmin), ("i_max", cell_current_a, np.fmax),
                           ("t_min", temp_c, np.fmin), ("t_max", temp_c, np.fmax)):  # fmt: skip
            self._fold(key, np.asarray(x, np.float64), fn)
        self.n += len(t_s)

    def rows(self) -> list[tuple[float, str]]:
        """(first time, what) for every quantity outside the fitted window so far."""
        e, f = self.ext, self.first
        lo, hi = self.soc_lo, self.soc_hi
        out: list[tuple[float, str]] = []
        for key, word, x in (("soc_low", "down to", e["soc_min"]),
                             ("soc_high", "up to", e["soc_max"])):  # fmt: skip
            if key in f:
                out.append((f[key], f"SOC {word} {100 * x:.0f} %, fitted on "
                                    f"{100 * lo:.0f}-{100 * hi:.0f} %{self.ocv_note}"))  # fmt: skip
        for key, x in (("i_high", e["i_max"]), ("i_low", e["i_min"])):
            if key in f:
                out.append((f[key], f"cell current {x:.1f} A, fitted on "
                                    f"{self.i_lo:.1f}..{self.i_hi:.1f} A"))  # fmt: skip
        how, rng = "temperature", f"fitted on {self.t_lo:.1f}..{self.t_hi:.1f} degC"
        if not self.logged:
            how = "start temperature"
            rng = f"the logs carry none (fitted as at {self.t_lo:.1f} degC)"
        for key, x in (("cold", e["t_min"]), ("hot", e["t_max"])):
            if key in f:
                out.append((f[key], f"{how} {x:.1f} degC, {rng}"))
        return sorted(out)


def battery_excursions(
    notes: Mapping[str, Any], t_s: F64, soc: F64, cell_current_a: F64, temp_c: F64
) -> list[tuple[float, str]]:
    """(first time, what) for every quantity of one battery outside the fitted window."""
    acc = Excursions(notes)
    acc.feed(t_s, soc, cell_current_a, temp_c)
    return acc.rows()


class FitWatch:
    """Every battery of a run on a fitted cell set, folded block by block (``RunWatch``'s,
    so the CLI, the report and the live dashboard show the same ``OutsideFit`` rows)."""

    def __init__(self, config: Mapping[str, Any] | None, names: Sequence[str]) -> None:
        self.watch: list[tuple[int, str, int, Excursions]] = []
        pack = (config or {}).get("pack") or {}
        for k, name in enumerate(names):
            bat = next((b for b in pack.get("batteries", []) if b.get("name") == name), None)
            if bat is None:
                continue
            notes = fitted_window(str(bat.get("cell") or pack.get("cell", "")))
            if notes is not None:
                cells = max(int(bat.get("cells_per_group", 1)), 1)
                self.watch.append((k, name, cells, Excursions(notes)))

    def feed(self, t_s: F64, battery: F64) -> None:
        """The next block: ``battery`` is the trace's (rows, batteries, BATTERY_CHANNELS)."""
        for k, _, cells, acc in self.watch:
            if k >= battery.shape[1]:
                continue
            rows = battery[:, k, :]
            acc.feed(t_s, rows[:, _CH["soc"]], rows[:, _CH["current_a"]] / cells,
                     rows[:, _CH["temp_c"]])  # fmt: skip

    def found(self) -> dict[str, list[tuple[float, str]]]:
        """Per battery name: its excursions so far (empty lists left out)."""
        out = {name: acc.rows() for _, name, _, acc in self.watch}
        return {name: rows for name, rows in out.items() if rows}


def excursions(
    config: Mapping[str, Any] | None, names: Sequence[str], t_s: F64, battery: F64
) -> dict[str, list[tuple[float, str]]]:
    """Per battery name on a fitted cell set: its excursions (empty lists left out).
    ``battery`` is the trace's (rows, batteries, BATTERY_CHANNELS) array."""
    if not config or not len(t_s):
        return {}
    watch = FitWatch(config, names)
    watch.feed(t_s, battery)
    return watch.found()


__all__ = ["Excursions", "FitWatch", "battery_excursions", "excursions", "fitted_window"]
