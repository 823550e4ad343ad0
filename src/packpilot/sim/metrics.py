"""The metrics of a run, defined once and accumulated step by step for P packs.

A single run and every pack of a campaign batch get their summary from the same accumulator,
so a pack's metrics are identical (bit for bit) whether it ran alone or among 255 others.
Per pack:

* ``energy_out_wh`` / ``energy_in_wh``: Σ bus_v·load_a·dt and Σ charger_v·charger_a·dt;
* ``min_cell_v`` / ``max_cell_v`` / ``max_temp_c``: extremes over the run, NaN readings
  skipped (NaN only if every reading was);
* ``final_soc``: each battery's SOC (weakest cell) after the last step;
* ``peak_string_current_a``: each battery's current at its largest magnitude (the first such
  step; a NaN current is the peak and stays it, as ``argmax`` has it);
* ``peak_cross_current_a``: the largest battery-to-battery current at one traction battery's
  terminals, whatever the load and the charger do (:func:`cross_current`; issue #24: it
  counted only while no charger delivered, and said 0 while a battery discharged into its
  siblings at 30 A during a staged charge);
* ``load_unsupplied_s``: time the load got less than it asked for;
* ``joule_heat_j`` and the diode ledgers: the plant's own integrals at the pack's last step;
* ``events``: counts by kind.

A pack stops accumulating when it stops (``stop_when_unsupplied_s``); the others go on.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.jit import kernel
from packpilot.model.pack import Interval, Pack

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]


@kernel
def _nanmin(a: float, b: float) -> float:
    if math.isnan(a):
        return b
    if math.isnan(b):
        return a
    return min(a, b)


@kernel
def _nanmax(a: float, b: float) -> float:
    if math.isnan(a):
        return b
    if math.isnan(b):
        return a
    return max(a, b)


@kernel
def cross_current(string_a: F64, traction: I64, charger_a: float) -> float:
    """The largest battery-to-battery current at one traction battery's terminals (A, ≥ 0).

    On the bus, the current into the charging batteries (C, their sum) comes from the charger
    and from the discharging ones (D); the part the charger does not cover, B = max(0, C − I),
    is battery to battery (the node then gives B ≤ D: the rest of D feeds the load). B is
    shared pro rata: a charging battery takes c_k·B/C of it, a discharging one gives
    d_k·B/D. Without a charger this is each charging battery's own current, the definition
    before issue #24, which counted only while no charger delivered. NaN if a current is.
    """
    into = 0.0
    out = 0.0
    big_c = 0.0
    big_d = 0.0
    for k in range(traction.shape[0]):
        x = string_a[traction[k]]
        if math.isnan(x):
            return math.nan
        if x < 0.0:
            big_c -= x
            into = max(into, -x)
        else:
            big_d += x
            out = max(out, x)
    flow = big_c - (charger_a if charger_a > 0.0 else 0.0)
    if flow <= 0.0 or big_c <= 0.0:
        return 0.0
    share_in = into * flow / big_c
    share_out = out * flow / big_d if big_d > 0.0 else 0.0
    return max(share_in, share_out)


@kernel
def accumulate(
    live: B1, starts: I64, traction: I64, cell_v: F64, temp_c: F64, soc: F64, cap: F64,
    bus_v: F64, load_a: F64, demand_a: F64, charger_v: F64, charger_a: F64, string_a: F64,
    steps: I64, energy_out: F64, energy_in: F64, min_cell_v: F64, max_cell_v: F64,
    max_temp_c: F64, final_soc: F64, peak_abs: F64, peak_val: F64, peak_cross: F64,
    unsupplied_steps: I64,
) -> None:  # fmt: skip
    """Fold one step of every live pack into the running metrics."""
    P, C = cell_v.shape
    S = starts.shape[0]
    for p in range(P):
        if not live[p]:
            continue
        steps[p] += 1
        energy_out[p] += bus_v[p] * load_a[p]
        energy_in[p] += charger_v[p] * charger_a[p]
        for s in range(S):
            lo = starts[s]
            hi = starts[s + 1] if s + 1 < S else C
            vmin, vmax, tmax = cell_v[p, lo], cell_v[p, lo], temp_c[p, lo]
            rem, full = soc[p, lo] * cap[p, lo], cap[p, lo]
            for c in range(lo + 1, hi):  # np.minimum / np.maximum: NaN propagates
                v = cell_v[p, c]
                if v < vmin or math.isnan(v):
                    vmin = v if not math.isnan(vmin) else vmin
                if v > vmax or math.isnan(v):
                    vmax = v if not math.isnan(vmax) else vmax
                t = temp_c[p, c]
                if t > tmax or math.isnan(t):
                    tmax = t if not math.isnan(tmax) else tmax
                r = soc[p, c] * cap[p, c]
                if r < rem or math.isnan(r):
                    rem = r if not math.isnan(rem) else rem
                if cap[p, c] < full or math.isnan(cap[p, c]):
                    full = cap[p, c] if not math.isnan(full) else full
            min_cell_v[p] = _nanmin(min_cell_v[p], vmin)
            max_cell_v[p] = _nanmax(max_cell_v[p], vmax)
            max_temp_c[p] = _nanmax(max_temp_c[p], tmax)
            final_soc[p, s] = rem / full
            cur = string_a[p, s]
            a = abs(cur)
            if not math.isnan(peak_abs[p, s]) and (a > peak_abs[p, s] or math.isnan(a)):
                peak_abs[p, s] = a
                peak_val[p, s] = cur
        into = cross_current(string_a[p], traction, charger_a[p])
        if into > peak_cross[p] or math.isnan(into):
            peak_cross[p] = into if not math.isnan(peak_cross[p]) else peak_cross[p]
        d = demand_a[p]
        if d > 1e-9 and load_a[p] < d - 1e-6:
            unsupplied_steps[p] += 1


@dataclass
class Metrics:
    """Running metrics of P packs (see the module docstring for the definitions)."""

    n_packs: int
    n_strings: int
    dt_s: float
    steps: I64 = field(init=False)
    energy_out: F64 = field(init=False)
    energy_in: F64 = field(init=False)
    min_cell_v: F64 = field(init=False)
    max_cell_v: F64 = field(init=False)
    max_temp_c: F64 = field(init=False)
    final_soc: F64 = field(init=False)
    peak_abs: F64 = field(init=False)
    peak_val: F64 = field(init=False)
    peak_cross: F64 = field(init=False)
    unsupplied_steps: I64 = field(init=False)
    live: B1 = field(init=False)
    events: list[Counter[str]] = field(init=False)
    joule: F64 = field(init=False)
    chg_diode: F64 = field(init=False)
    dsg_diode: F64 = field(init=False)

    def __post_init__(self) -> None:
        P, S = self.n_packs, self.n_strings
        self.steps = np.zeros(P, np.int64)
        self.energy_out = np.zeros(P)
        self.energy_in = np.zeros(P)
        self.min_cell_v = np.full(P, np.nan)
        self.max_cell_v = np.full(P, np.nan)
        self.max_temp_c = np.full(P, np.nan)
        self.final_soc = np.full((P, S), np.nan)
        self.peak_abs = np.full((P, S), -1.0)
        self.peak_val = np.zeros((P, S))
        self.peak_cross = np.zeros(P)
        self.unsupplied_steps = np.zeros(P, np.int64)
        self.live = np.ones(P, np.bool_)
        self.events = [Counter() for _ in range(P)]
        self.joule = np.zeros(P)
        self.chg_diode = np.zeros((P, S))
        self.dsg_diode = np.zeros((P, S))

    def add(
        self, pack: Pack, iv: Interval, traction: I64, kinds: Sequence[Sequence[str]] | None
    ) -> None:
        """Fold the step just taken (``iv``, the plant after it, its event kinds per pack)."""
        soc, temp = pack.cell_states()
        accumulate(
            self.live, pack.string_cell_starts, traction, iv.cell_v, temp, soc, pack.capacity_ah,
            iv.bus_v, iv.load_a, iv.load_demand_a, iv.charger_v, iv.charger_a, iv.string_a,
            self.steps, self.energy_out, self.energy_in, self.min_cell_v, self.max_cell_v,
            self.max_temp_c, self.final_soc, self.peak_abs, self.peak_val, self.peak_cross,
            self.unsupplied_steps,
        )  # fmt: skip
        if kinds is not None:
            for p, ks in enumerate(kinds):
                if ks and self.live[p]:
                    self.events[p].update(ks)
        self.pack = pack

    def _ledgers(self, pack: Pack, mask: B1) -> None:
        """The plant's integrals of the packs in ``mask``, as they are now."""
        self.joule[mask] = pack.joule_j[mask].sum(axis=1)
        self.chg_diode[mask] = pack.chg_diode_j[mask]
        self.dsg_diode[mask] = pack.dsg_diode_j[mask]

    def stop(self, mask: B1, pack: Pack | None = None) -> None:
        """Packs in ``mask`` stop here: their metrics freeze (ledgers as they are now)."""
        mask = mask & self.live
        if pack is not None and mask.any():
            self._ledgers(pack, mask)
        self.live &= ~mask

    def of(self, p: int, wall_s: float, names: Sequence[str]) -> dict[str, Any]:
        """Pack ``p``'s metrics, JSON-able (a live pack's ledgers as the plant has them)."""
        pack: Pack | None = getattr(self, "pack", None)
        if pack is not None and self.live[p]:
            mask = np.zeros(self.n_packs, np.bool_)
            mask[p] = True
            self._ledgers(pack, mask)
        n = int(self.steps[p])
        dt = self.dt_s
        return {
            "sim_time_s": float(n * dt),
            "wall_time_s": float(wall_s),
            "steps": n,
            "energy_out_wh": float(self.energy_out[p] * dt / 3600.0),
            "energy_in_wh": float(self.energy_in[p] * dt / 3600.0),
            "min_cell_v": float(self.min_cell_v[p]),
            "max_cell_v": float(self.max_cell_v[p]),
            "max_temp_c": float(self.max_temp_c[p]),
            "final_soc": [float(x) for x in self.final_soc[p]],
            "peak_string_current_a": [float(x) for x in self.peak_val[p]],
            "peak_cross_current_a": float(self.peak_cross[p]),
            "joule_heat_j": float(self.joule[p]),
            "load_unsupplied_s": float(self.unsupplied_steps[p] * dt),
            "chg_diode_energy_j": [float(x) for x in self.chg_diode[p]],
            "dsg_diode_energy_j": [float(x) for x in self.dsg_diode[p]],
            "events": dict(self.events[p]),
            "battery_names": list(names),
        }


__all__ = ["Metrics", "accumulate", "cross_current"]
