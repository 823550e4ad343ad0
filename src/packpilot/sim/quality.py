"""The quality figures of each method, computed from a finished run.

One implementation for the two readers of these numbers: the benchmarks (``benchmarks/bench_*.py``,
which judge them against issue #15's goals over many runs) and the HTML report (which shows them
for the one run it describes). Everything here reads the recorded trace, events and metrics, the
plant's truth, never the plant object itself, so a run loaded back from SQLite gives the same
figures as the in-memory one.

* sequencing: :func:`sequencing_figures` (co-discharge share, switch changes per minute, peak
  load share, cross-charge, energy and heat), goals in :data:`SEQUENCING_GOALS`;
* staged charging: :func:`time_to_full` and :func:`stage_breakdown` (time, batteries and charge
  per stage);
* equalization: :func:`spread_mv` and :func:`group_spread_mv` (the spread the method works on);
* protection: :func:`protection_figures` (trip, parameter at the trip, allowance used, margin to
  the active cut-off, predicted time to trip).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.contract.record import Result, Trace
from packpilot.model.cell.model import ocv_v
from packpilot.model.cell.params import load_parameter_set

F64 = NDArray[np.float64]
B1 = NDArray[np.bool_]

# --------------------------------------------------------------------------- sequencing

SHARE_MIN_LOAD_A = 5.0
"""Load sharing is judged where the load draws at least 1C of a 5 Ah battery: at a landing's
1.5 A a circulating current of a few hundred mA would make any ratio meaningless."""

SEQUENCING_GOALS: dict[str, Callable[[float], bool]] = {
    "co_share": lambda x: x >= 0.90,
    "sw_per_min": lambda x: x <= 1.0,
    "peak_share_held": lambda x: x <= 0.6,
    "rev_1a_s": lambda x: x <= 0.1 + 1e-9,
    "cross_mah_h": lambda x: x <= 1.0,
    "energy_to_brownout_ratio": lambda x: x >= 0.99,
    "heat_ratio": lambda x: x < 1.0,
}
"""Issue #15 §1's goals, per figure (the bench, its headlines and the report use this table).
Energy is judged against direct parallel **up to the first load brown-out** (issue #15's
decision, recorded in issue #24): after the load's lock-out the flight is over, and pulsing a
locked-out load is not energy delivered."""

SEQUENCING_GOAL_TEXT: dict[str, str] = {
    "co_share": ">= 0.90",
    "sw_per_min": "<= 1",
    "peak_share_held": "<= 0.6",
    "rev_1a_s": "<= 0.1 s",
    "cross_mah_h": "<= 1",
    "energy_to_brownout_ratio": ">= 0.99",
    "heat_ratio": "< 1",
}
"""The same goals as text, for tables."""


def _ocv(cfg: ScenarioConfig, res: Result) -> F64:
    """(steps, batteries) open-circuit voltage of each battery from its SOC and temperature."""
    tr = res.trace
    soc = tr.channel("soc")
    temp = tr.channel("temp_c")
    out = np.empty_like(soc)
    for k, b in enumerate(cfg.pack.batteries[: soc.shape[1]]):
        params = load_parameter_set(b.cell or cfg.pack.cell)
        out[:, k] = ocv_v(params, soc[:, k], temp[:, k]) * b.series_groups * b.cells_per_group
    return out


def longest_run_s(mask: B1, dt: float) -> float:
    """Longest run of True (s), per column, the largest over columns."""
    best = 0
    for col in mask.reshape(len(mask), -1).T:
        run = 0
        for x in col:
            run = run + 1 if x else 0
            best = max(best, run)
    return best * dt


def _meet(cfg: ScenarioConfig, res: Result, present: B1) -> int | None:
    """First step at which the present batteries' OCVs are within v_co (plus the spread their
    resistance differences sustain at the present load), or None."""
    tr = res.trace
    ocv = _ocv(cfg, res)
    r = [b.resistance_ohm for b in cfg.pack.batteries[: ocv.shape[1]]]
    dr = max(r) - min(r) if all(x is not None for x in r) else 0.0  # type: ignore[type-var,operator]
    n_pres = present.sum(axis=1)
    hi = np.where(present, ocv, -np.inf).max(axis=1)
    lo = np.where(present, ocv, np.inf).min(axis=1)
    v_co = cfg.sequencing.v_co if cfg.sequencing is not None else 0.0
    allow = v_co + np.maximum(tr.load_a, 0.0) / np.maximum(n_pres, 1) * dr
    met = (hi - lo < allow) & (n_pres >= 2)
    return int(np.argmax(met)) if met.any() else None


def _switching(tr: Trace, chg: B1, dsg: B1, loaded: B1, k_bo: int, dt: float) -> tuple[F64, B1]:
    """FET gate changes per step, and the steps of steady hover."""
    # Steady hover: the loaded time from 10 s after the load starts to the first brown-out
    # (the hover profiles' gusts included; four_spread's whole mission, bursts and landing).
    dem = tr.load_demand_a
    steady = (dem > 1.0) & loaded
    k0 = int(np.argmax(dem > 1.0)) + max(1, round(10.0 / dt)) if (dem > 1.0).any() else 0
    steady[:k0] = False
    steady[k_bo:] = False
    flips = np.zeros(len(dem))
    flips[1:] = (chg[1:] != chg[:-1]).sum(axis=1) + (dsg[1:] != dsg[:-1]).sum(axis=1)
    return flips, steady


def _opt(x: Any) -> float | None:
    return None if x is None else float(x)


def sequencing_figures(cfg: ScenarioConfig, res: Result) -> dict[str, Any]:
    """Issue #15 §1's figures of one finished run (definitions: ``benchmarks/bench_sequencing``
    and docs/parallel_discharge.md). ``None`` where a figure has no data (never met, no load)."""
    tr = res.trace
    dt = cfg.sim.dt_s
    cur = tr.channel("current_a")
    volt = tr.channel("voltage_v")
    chg = tr.channel("chg_on") > 0.5
    dsg = tr.channel("dsg_on") > 0.5
    present = np.isfinite(volt) & (volt > 1.0)
    n_pres = present.sum(axis=1)
    no_charger = ~(tr.charger_a > 1e-6)
    into = np.where(present, np.maximum(-cur, 0.0), 0.0)
    into[~no_charger] = 0.0
    loaded = tr.load_a > 1.0
    unsupplied = (tr.load_demand_a > 1e-9) & (tr.load_a < tr.load_demand_a - 1e-6)
    k_bo = int(np.argmax(unsupplied)) if unsupplied.any() else len(unsupplied)
    budget_s = cfg.sim.stop_when_unsupplied_s
    k_budget = len(unsupplied)
    over = np.nonzero(np.cumsum(unsupplied) * dt >= (budget_s or np.inf) - 1e-9)[0]
    k_budget = int(over[0]) + 1 if over.size else k_budget
    power_w = tr.bus_v * tr.load_a
    energy_budget_wh = float(np.sum(power_w[:k_budget]) * dt / 3600.0)
    k_meet = _meet(cfg, res, present)
    both = np.all(~present | (chg & dsg & (cur > 0.0)), axis=1) & (n_pres >= 2)
    after = np.zeros(len(cur), bool)
    if k_meet is not None:
        after[k_meet:k_bo] = True
    sel = after & loaded
    co_share = float(both[sel].mean()) if sel.any() else None
    flying = tr.load_a > SHARE_MIN_LOAD_A
    share = np.where(flying[:, None], cur / np.maximum(tr.load_a[:, None], 1e-9), 0.0)
    share_max = np.where(present, share, 0.0).max(axis=1)
    sel_f = sel & flying
    peak_share = float(share_max[sel_f].max()) if sel_f.any() else None
    # The share the controller is answerable for: at steps after the meet where some present
    # battery was held out (not discharging with both FETs on). With every battery engaged the
    # split is the plant's alone (issue #24 item 8: direct parallel gives the demo 0.695, the
    # method 0.698, after the same meet). 0 when the controller never held one out.
    held = sel_f & ~both
    peak_share_held = float(share_max[held].max()) if held.any() else 0.0
    k_join = int(np.argmax(both)) if both.any() else None
    since_join = np.zeros(len(cur), bool)
    if k_join is not None:
        since_join[k_join:k_bo] = True
    sel_j = since_join & flying
    peak_share_join = float(share_max[sel_j].max()) if sel_j.any() else None
    both_present = flying & (n_pres >= 2)
    peak_share_all = float(share_max[both_present].max()) if both_present.any() else None
    flips, steady = _switching(tr, chg, dsg, loaded, k_bo, dt)
    steady_min = steady.sum() * dt / 60.0
    run_h = len(cur) * dt / 3600.0
    m = res.metrics
    events = m.get("events") or {}
    return {
        "meet_s": float(tr.t_s[k_meet]) if k_meet is not None else None,
        "co_share": co_share,
        "sw_per_min": float(flips[steady].sum() / steady_min) if steady_min > 0 else None,
        "steady_min": steady_min,
        "peak_share": peak_share,
        "peak_share_held": peak_share_held if sel_f.any() else None,
        "peak_share_join": peak_share_join,
        "join_s": float(tr.t_s[k_join]) if k_join is not None else None,
        "peak_share_all": peak_share_all,
        "rev_peak_a": float(into.max()),
        "rev_1a_s": longest_run_s(into > 1.0, dt),
        "rev_0.5a_s": longest_run_s(into > 0.5, dt),
        "cross_mah_h": float(into.sum() * dt / 3.6 / run_h),
        "unsupplied_s": _opt(m.get("load_unsupplied_s")),
        "first_brownout_s": float(tr.t_s[k_bo]) if k_bo < len(unsupplied) else None,
        "energy_wh": _opt(m.get("energy_out_wh")),
        "energy_to_brownout_wh": float(np.sum(power_w[:k_bo]) * dt / 3600.0),
        "energy_budget_wh": energy_budget_wh,
        "heat_j": _opt(m.get("joule_heat_j")),
        "diode_j": float(
            sum(m.get("chg_diode_energy_j", [])) + sum(m.get("dsg_diode_energy_j", []))
        ),
        "joins": int(events.get("BatteryJoined", 0)),
        "reverse_events": int(events.get("ReverseCurrent", 0)),
        "risk_events": int(events.get("CrossCurrentRisk", 0)),
        "sim_s": _opt(m.get("sim_time_s")),
    }


def sequencing_verdicts(row: dict[str, Any]) -> dict[str, str]:
    """Goal -> 'met' / 'MISSED' / '-' for one row of sequencing figures."""
    out: dict[str, str] = {}
    for key, ok in SEQUENCING_GOALS.items():
        x = row.get(key)
        out[key] = "-" if x is None else ("met" if ok(x) else "MISSED")
    return out


# --------------------------------------------------------------------------- staged charging

FULL_BAND_V = 0.5
"""'At V_sat' band: the charging controller's default reach_tol_v."""


def time_to_full(
    res: Result,
    v_sat_v: float | Sequence[float] | F64,
    term_a: float,
    traction: Sequence[int],
    band_v: float | Sequence[float] | F64 = FULL_BAND_V,
) -> float:
    """First time by which every traction battery has been within ``band_v`` of V_sat with its
    charge current down to ``term_a`` (the criterion the method stops on); NaN if never.
    ``v_sat_v`` and ``band_v`` may be one value per traction battery (a per-cell basis scaled
    by each battery's series count)."""
    cols = list(traction)
    v = res.trace.channel("voltage_v")[:, cols]
    i_chg = -res.trace.channel("current_a")[:, cols]
    full = (v >= np.asarray(v_sat_v) - np.asarray(band_v)) & (i_chg <= term_a)
    t = res.trace.t_s
    step = float(t[1] - t[0]) if len(t) > 1 else 0.0
    t_full = []
    for b in range(full.shape[1]):
        hits = np.flatnonzero(full[:, b])
        if hits.size == 0:
            return float("nan")
        t_full.append(float(t[hits[0]] + step))
    return max(t_full)


def stage_breakdown(
    res: Result, traction: Sequence[int], heat_steps_j: F64 | None = None
) -> list[dict[str, Any]]:
    """Consecutive periods of one ``chg_stage`` (the whole run when the run has no staging),
    each with its start, duration, batteries connected, charge delivered and mean charger
    current; with ``heat_steps_j`` (the traction batteries' I²R heat per step, which only the
    plant knows) also the heat and the effective resistance heat / (q·I/n) it implies (NaN
    without). Periods that moved less than 0.05 Ah and 0.05 kJ are left out."""
    t = res.trace.t_s
    n_steps = len(t) if heat_steps_j is None else min(len(t), len(heat_steps_j))
    dt = float(t[1] - t[0]) if len(t) > 1 else 0.0
    cols = list(traction)
    i_chg = np.maximum(-res.trace.channel("current_a")[:n_steps, cols], 0.0)
    stages = res.trace.status.get("chg_stage")
    relays = res.trace.status.get("chg_relay")
    label = [str(s[0]) for s in stages] if stages else ["all relays closed"] * n_steps
    label = ["–"] * (n_steps - len(label)) + label[len(label) - n_steps :]
    rows: list[dict[str, Any]] = []
    k0 = 0
    for k in range(1, n_steps + 1):
        if k < n_steps and label[k] == label[k0]:
            continue
        sl = slice(k0, k)
        q_c = float(i_chg[sl].sum()) * dt
        heat = float(heat_steps_j[sl].sum()) if heat_steps_j is not None else math.nan
        i_mean = float(i_chg[sl].sum(axis=1).mean())
        n = _connected(relays, cols, k0, k, n_steps)
        r_eff = heat / (q_c * i_mean / n) if q_c > 0.0 and i_mean > 0.0 and n > 0 else math.nan
        rows.append(
            {
                "stage": label[k0],
                "t0_s": float(t[k0]),
                "duration_s": (k - k0) * dt,
                "n": n,
                "charge_ah": q_c / 3600.0,
                "mean_a": i_mean,
                "heat_kj": heat / 1e3,
                "r_eff_mohm": r_eff * 1e3,
            }
        )
        k0 = k
    return [r for r in rows if r["charge_ah"] > 0.05 or r["heat_kj"] > 0.05]


def _connected(relays: Any, cols: list[int], k0: int, k1: int, n_steps: int) -> int:
    """Most traction batteries whose relay was closed at once in steps ``k0 .. k1 - 1``."""
    if not relays:
        return len(cols)
    off = n_steps - len(relays)  # a channel recorded from a later step on covers the end
    rows = [relays[j - off] for j in range(max(k0, off), k1)]
    return max((sum(1 for i in cols if r[i]) for r in rows), default=0)


def stage_times(res: Result) -> dict[str, float]:
    """Total time (s) in each ``chg_stage`` value of the first battery carrying one, in order
    of first appearance; empty when the run has no staging."""
    stages = res.trace.status.get("chg_stage")
    t = res.trace.t_s
    if not stages or len(t) == 0:
        return {}
    dt = np.diff(t, append=t[-1] + (t[-1] - t[-2] if len(t) > 1 else 0.0))[len(t) - len(stages) :]
    out: dict[str, float] = {}
    for s, d in zip(stages, dt, strict=True):
        key = str(next((v for v in s if v is not None), "–"))
        out[key] = out.get(key, 0.0) + float(d)
    return out


# --------------------------------------------------------------------------- equalization


def spread_mv(values_v: Sequence[float] | F64) -> float:
    """Highest minus lowest of a set of voltages (V), in mV; NaN readings ignored (NaN if all
    are). The figure equalization is judged on: the bench applies it to the groups' rest
    voltages, the report to each battery's group voltages."""
    v = np.asarray(values_v, dtype=np.float64)
    v = v[np.isfinite(v)]
    return float(v.max() - v.min()) * 1000.0 if v.size else math.nan


def group_spread_mv(trace: Trace, battery: int) -> F64:
    """Per step, the spread (mV) of one battery's series-group voltages (NaN columns of a
    battery with fewer groups than the widest are ignored)."""
    g = trace.group_v[:, battery, :]
    ok = np.isfinite(g)
    hi = np.where(ok, g, -np.inf).max(axis=1)
    lo = np.where(ok, g, np.inf).min(axis=1)
    out: F64 = (hi - lo) * 1000.0
    out[~ok.any(axis=1)] = math.nan
    return out


# --------------------------------------------------------------------------- protection


def protection_figures(res: Result, battery: int, event_battery: int) -> dict[str, Any]:
    """One protected battery: whether and when it tripped and on which parameter, the most of
    its allowance sum(t_k / t_max_k) it used, the least margin (V) between its lowest cell and
    the active cut-off while discharging, and the shortest predicted time to trip (s).

    ``battery`` indexes the trace, ``event_battery`` the events (which count traction batteries
    only). A figure is None when the run did not record what it needs."""
    trips = [e for e in res.events if e.kind == "ProtectionTripped" and e.battery == event_battery]
    trip = trips[0] if trips else None
    st = res.trace.status
    frac = _status_column(st.get("protection_fraction"), battery)
    cut = _status_column(st.get("protection_cutoff_v"), battery)
    ttt = _status_column(st.get("protection_time_to_trip_s"), battery)
    n = len(res.trace.t_s)
    margin = None
    if cut is not None:
        cell = res.trace.channel("min_cell_v")[n - len(cut) :, battery]
        cur = res.trace.channel("current_a")[n - len(cut) :, battery]
        m = np.where(cur > 0.0, cell - cut, np.nan)
        margin = float(np.nanmin(m)) if np.isfinite(m).any() else None
    return {
        "tripped": trip is not None,
        "trip_s": None if trip is None else float(trip.t_s),
        "param_at_trip": None if trip is None else trip.data.get("param"),
        "temp_at_trip_c": None if trip is None else _opt(trip.data.get("temp_c")),
        "max_fraction": _nanmax(frac),
        "min_margin_v": margin,
        "min_time_to_trip_s": None if ttt is None else _nanmin(ttt),
    }


def _status_column(seqs: Any, b: int) -> F64 | None:
    """One battery's column of a numeric status channel (None -> NaN), None if not recorded."""
    if not seqs or len(seqs[0]) <= b:
        return None
    return np.array([math.nan if s[b] is None else float(s[b]) for s in seqs], dtype=np.float64)


def _nanmax(x: F64 | None) -> float | None:
    return float(np.nanmax(x)) if x is not None and np.isfinite(x).any() else None


def _nanmin(x: F64 | None) -> float | None:
    return float(np.nanmin(x)) if x is not None and np.isfinite(x).any() else None


__all__ = [
    "FULL_BAND_V",
    "SEQUENCING_GOALS",
    "SEQUENCING_GOAL_TEXT",
    "SHARE_MIN_LOAD_A",
    "group_spread_mv",
    "longest_run_s",
    "protection_figures",
    "sequencing_figures",
    "sequencing_verdicts",
    "spread_mv",
    "stage_breakdown",
    "stage_times",
    "time_to_full",
]
