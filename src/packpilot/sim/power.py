"""Where state of power and join planning get their numbers: the static facts of a pack from
its config and cell sets, and the batteries' present state (:class:`PowerInputs`).

The prediction itself is the core's (:mod:`packpilot.control.power`); this module sits above
the plant's cell model because the resistances and RC branches come from the cell set.

**The one place the state comes from.** :func:`inputs_from_core` fills
:class:`~packpilot.control.power.PowerInputs` from what the core has today: the SOC method's
estimate (else the battery's reported SOC), the cell set's R0 / R1 / C1 (/ R2 / C2) at the
battery's temperature, SOC and current, scaled like the plant scales a battery's stated
``resistance_ohm``, and **no polarisation** (``v1_v = v2_v = 0``: nothing estimates it yet).
A model-based observer replaces exactly this function: it writes its SOC, R0, RC
polarisation voltages (and their resistances and time constants) into the same fields.
:func:`inputs_from_plant` fills them from the simulated plant's truth (tests, benchmarks).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import interpn

from packpilot.config import ScenarioConfig
from packpilot.config.limits import LimitsConfig
from packpilot.config.scenario import BatteryConfig
from packpilot.config.supervisor import SupervisorConfig
from packpilot.control.power import (
    HORIZONS_S,
    PowerInputs,
    PowerParams,
    admissible_dv,
    make_params,
    new_inputs,
    plan_join,
)
from packpilot.errors import ConfigError
from packpilot.model.cell import model as cellmod
from packpilot.model.cell.params import CellParams
from packpilot.model.pack import Pack, _load_cell_set, battery_base_soc, battery_series_ohm

F64 = NDArray[np.float64]


def traction(cfg: ScenarioConfig) -> list[BatteryConfig]:
    """The traction batteries, in the core's battery order."""
    return [b for b in cfg.pack.batteries if b.role != "aux"]


@functools.lru_cache(maxsize=16)
def _cells(name: str) -> CellParams:
    return _load_cell_set(name)


def cell_set(cfg: ScenarioConfig, b: BatteryConfig) -> CellParams:
    """The battery's cell set (loaded once per process: the publisher asks every second)."""
    return _cells(b.cell or cfg.pack.cell)


@dataclass(frozen=True)
class CellRc:
    """One cell's equivalent circuit at a state: R0, R1, tau1 (R2, tau2 zero for one RC)."""

    r0_ohm: float
    r1_ohm: float
    tau1_s: float
    r2_ohm: float
    tau2_s: float
    r_per_k: float
    """d ln R0 / dT about this state (1/K) ..."""
    r_per_soc: float
    """... d ln R0 / d SOC ..."""
    r_per_a: float
    """... d ln R0 / d|I| (1/A), between 0 A and this state's current (or 30 A)."""


def cell_rc(params: CellParams, soc: float, temp_c: float, current_a: float = 0.0) -> CellRc:
    """The cell set's tables at (temperature, zero current, SOC), held at their edges, and
    how R0 moves with temperature, SOC and current there (the prediction follows them).

    One interpolation of the five tables stacked, at the four points the chords need: the
    runtime builds this for every battery at every publication, and eight separate
    ``interpn`` calls were 1.2 ms of a 4-battery pack's 8 ms state of power."""
    axes = (params.rc_temp_c, params.rc_current_a, params.rc_soc)
    shape = params.r0_ohm.shape
    tables = [params.r0_ohm, params.r1_ohm, params.c1_f, params.r2_ohm, params.c2_f]
    stacked = np.stack([np.zeros(shape) if t is None else t for t in tables], axis=-1)
    # the chord over the next 10 K a battery warms under load (R falls convexly with
    # temperature, so the chord keeps the predicted R at or above the table's on the way);
    # the chord towards empty, where a discharging battery goes (R rises steeply there);
    # the chord between 0 A and this state's current (or 30 A)
    ds = -0.05 if soc >= 0.05 else 0.05
    di = max(abs(current_a), 30.0)
    pts = np.array([[temp_c, 0.0, soc], [temp_c + 10.0, 0.0, soc], [temp_c, 0.0, soc + ds],
                    [temp_c, di, soc]], np.float64)  # fmt: skip
    for k, ax in enumerate(axes):
        np.clip(pts[:, k], ax[0], ax[-1], out=pts[:, k])
    at = interpn(axes, stacked, pts)  # (point, table)
    r0 = float(at[0, 0])
    r1, c1, r2, c2 = (float(x) for x in at[0, 1:])
    r_t = math.log(float(at[1, 0]) / r0) / 10.0
    r_s = math.log(float(at[2, 0]) / r0) / ds
    r_a = math.log(float(at[3, 0]) / r0) / di
    return CellRc(r0, r1, r1 * c1, r2, r2 * c2, r_t, r_s, r_a)


def resistance_scale(cfg: ScenarioConfig, b: BatteryConfig) -> float:
    """The factor the plant puts on this battery's cell resistances (``model/pack.py``): its
    stated ``resistance_ohm`` over the cell set's R0 at ``resistance_temp_c`` (a datasheet's or
    an ohmmeter's temperature, 25 degC by default) and its initial SOC (``soc0``, or its
    ``ocv0_v`` read through the OCV at the ambient), no current. Until 2026-11-29 this took the
    R0 at the battery's ambient instead, so away from 25 degC the core's inputs had the stated
    resistance at the ambient while the plant's cells followed their temperature law from
    25 degC: at 5 degC uav_5ah's R0 is 1.8 x its 25 degC value, and the cell-set inputs
    (``inputs_from_core`` without a trusted observer R0) had R0 1.8 x too low."""
    if b.resistance_ohm is None:
        return 1.0
    prm = cell_set(cfg, b)
    soc = battery_base_soc(b, prm, cfg.pack.ambient_c)
    r0 = cell_rc(prm, min(max(soc, 0.0), 1.0), b.resistance_temp_c, 0.0).r0_ohm
    return b.resistance_ohm / (b.n_cells * r0)


def _limit_rows(cfg: ScenarioConfig, quantity: str, path: str | None = None) -> list[float]:
    """Trip thresholds of a quantity (of one path's rows, if given)."""
    if cfg.limits is None:
        return []
    return [
        r.threshold for r in cfg.limits.rows
        if r.quantity == quantity and r.tier == "trip" and path in (None, r.path)
    ]  # fmt: skip


MARGIN = 0.02
"""Taken off every state of power published: the prediction's worst error against the plant
measured by ``benchmarks/bench_power.py`` (1.2 %, after a 60 s preload), rounded up."""


def params_of(
    cfg: ScenarioConfig,
    horizons_s: tuple[float, ...] = HORIZONS_S,
    n_sub: int = 30,
    margin: float = MARGIN,
) -> PowerParams:
    """The static facts of the pack's traction batteries: the pack cell set's OCV curve,
    series counts, switches, each battery's leads, connectors and shunt (its ``series_ohm``,
    :func:`~packpilot.model.pack.battery_series_ohm`, as the plant's branch has it: the one
    place it enters the prediction), and the limits a battery must not cross: the cut-off is the
    highest of the cell set's minimum voltage and the limits table's ``cell_v_min`` trips,
    the maximum the lowest of its maximum and the ``cell_v_max`` trips, the temperature limits
    the lowest ``temp_max_c`` trip of each path and the highest ``temp_min_c`` trip (none without
    one); the heat capacity is the cells', cooled
    through their conductance to the jig (held at the start temperature)."""
    bats = traction(cfg)
    pack_cells = _cells(cfg.pack.cell)
    sw = [b.switch or cfg.pack.switch for b in bats]
    lo, hi = _limit_rows(cfg, "cell_v_min"), _limit_rows(cfg, "cell_v_max")
    hot_d = _limit_rows(cfg, "temp_max_c", "discharge")
    hot_c = _limit_rows(cfg, "temp_max_c", "charge")
    cold_d = _limit_rows(cfg, "temp_min_c", "discharge")
    cold_c = _limit_rows(cfg, "temp_min_c", "charge")
    sets = [cell_set(cfg, b) for b in bats]
    return make_params(
        ocv_soc=pack_cells.ocv_soc, ocv_v=pack_cells.ocv_table_v,
        series=[float(b.n_cells) for b in bats],
        relay=[s.kind == "relay" for s in sw], on_ohm=[s.on_ohm for s in sw],
        diode_drop_v=[s.diode_drop_v for s in sw], diode_ohm=[s.diode_ohm for s in sw],
        series_ohm=[battery_series_ohm(b, c) for b, c in zip(bats, sets, strict=True)],
        cell_v_min=[max([c.v_min_v, *lo]) for c in sets],
        cell_v_max=[min([c.v_max_v, *hi]) for c in sets],
        temp_max_dsg_c=[min(hot_d, default=math.inf) for _ in bats],
        temp_max_chg_c=[min(hot_c, default=math.inf) for _ in bats],
        temp_min_dsg_c=[max(cold_d, default=-math.inf) for _ in bats],
        temp_min_chg_c=[max(cold_c, default=-math.inf) for _ in bats],
        heat_j_per_k=[c.thermal.cell_heat_capacity_j_per_k * b.n_cells
                      for c, b in zip(sets, bats, strict=True)],
        cool_w_per_k=[_conductance(c) * b.n_cells for c, b in zip(sets, bats, strict=True)],
        horizons_s=horizons_s, n_sub=n_sub, margin=margin,
    )  # fmt: skip


def _conductance(c: CellParams) -> float:
    """A cell's conductance to what surrounds it: to its jig (two-node model), or to the air
    through the jig (one node)."""
    th = c.thermal
    if th.nodes == 2:
        return float(th.cell_jig_w_per_k)
    a, b = th.cell_jig_w_per_k, th.jig_air_w_per_k
    return float(a * b / (a + b))


def current_limits(cfg: ScenarioConfig, capacity_ah: F64) -> tuple[F64, F64]:
    """(discharge, charge) current limits per battery from the limits table's C-rate trips
    (the lowest trip × capacity), inf without one."""
    d = _limit_rows(cfg, "dsg_c_rate")
    c = _limit_rows(cfg, "chg_c_rate")
    inf = np.full_like(capacity_ah, math.inf)
    return (
        capacity_ah * min(d) if d else inf,
        capacity_ah * min(c) if c else inf,
    )


def _fill_rc(inp: PowerInputs, p: int, i: int, b: BatteryConfig, rc: CellRc, rs: float) -> None:
    """Battery-level resistances from one cell's (every cell of a battery is in series)."""
    k = b.n_cells * rs
    inp.r0_ohm[p, i] = rc.r0_ohm * k
    inp.r1_ohm[p, i] = rc.r1_ohm * k
    inp.tau1_s[p, i] = rc.tau1_s
    inp.r2_ohm[p, i] = rc.r2_ohm * k
    inp.tau2_s[p, i] = rc.tau2_s
    inp.r_per_k[p, i] = rc.r_per_k
    inp.r_per_soc[p, i] = rc.r_per_soc
    inp.r_per_a[p, i] = rc.r_per_a


def inputs_from_core(
    cfg: ScenarioConfig,
    *,
    soc: F64,
    temp_c: F64,
    current_a: F64,
    voltage_v: F64,
    min_cell_v: F64,
    max_cell_v: F64,
    present: NDArray[np.bool_],
    chg_on: NDArray[np.bool_],
    dsg_on: NDArray[np.bool_],
    limit_dsg_a: F64 | None = None,
    limit_chg_a: F64 | None = None,
    prm: PowerParams | None = None,
    polarisation_v: F64 | None = None,
    r0_ohm: F64 | None = None,
) -> PowerInputs:
    """The batteries' state as the core knows it (one pack; arrays over traction
    batteries). SOC is what the caller passes (the SOC method's estimate: the observer's
    where it runs). ``polarisation_v`` and ``r0_ohm`` are the observer's estimates (battery
    units; NaN where it does not run or is not trusted): where finite, the RC polarisation
    stands in the first branch (the observer has one) and the estimated R0 replaces the cell
    set's, with no current dependence (the observer's R0 is fitted at the currents seen).
    Elsewhere the cell set's resistances and zero polarisation.

    ``limit_*_a`` (the limits layer's published per-battery limits) tighten the C-rate trips;
    a NaN there means unknown and leaves the trip."""
    bats = traction(cfg)
    n = len(bats)
    prm = params_of(cfg) if prm is None else prm
    inp = new_inputs(1, n)
    cap = np.array([b.capacity_ah or cell_set(cfg, b).capacity_ah for b in bats])
    dsg, chg = current_limits(cfg, cap)
    for i, b in enumerate(bats):
        s = float(soc[i]) if math.isfinite(soc[i]) else 0.5
        t = float(temp_c[i]) if math.isfinite(temp_c[i]) else cfg.pack.ambient_c
        cur = float(current_a[i]) if math.isfinite(current_a[i]) else 0.0
        _fill_rc(inp, 0, i, b, cell_rc(cell_set(cfg, b), s, t, cur), resistance_scale(cfg, b))
        inp.soc[0, i] = s
        inp.emf_offset_v[0, i] = b.n_cells * entropic_v(cell_set(cfg, b), prm, s, t)
        inp.dudt_v_per_k[0, i] = b.n_cells * dudt_v_per_k(cell_set(cfg, b), s, t)
        inp.temp_c[0, i] = t
        inp.capacity_ah[0, i] = cap[i]
        avg = float(voltage_v[i]) / b.n_cells
        inp.low_cell_v[0, i] = _gap(avg - float(min_cell_v[i]))
        inp.high_cell_v[0, i] = _gap(float(max_cell_v[i]) - avg)
        inp.present[0, i] = bool(present[i])
        inp.chg_on[0, i] = bool(chg_on[i])
        inp.dsg_on[0, i] = bool(dsg_on[i])
        inp.v1_v[0, i] = 0.0  # no polarisation estimate yet (the observer's)
        inp.v2_v[0, i] = 0.0
        inp.limit_dsg_a[0, i] = _tighter(dsg[i], limit_dsg_a, i)
        inp.limit_chg_a[0, i] = _tighter(chg[i], limit_chg_a, i)
        _observed(inp, i, polarisation_v, r0_ohm)
    return inp


def _observed(inp: PowerInputs, i: int, pol: F64 | None, r0: F64 | None) -> None:
    """The observer's polarisation and R0 of battery ``i``, where it has them (#28 §1 -> §3)."""
    if pol is not None and math.isfinite(pol[i]):
        inp.v1_v[0, i] = float(pol[i])
        inp.v2_v[0, i] = 0.0
    if r0 is not None and math.isfinite(r0[i]) and r0[i] > 0.0:
        inp.r0_ohm[0, i] = float(r0[i])
        inp.r_per_a[0, i] = 0.0


def entropic_v(params: CellParams, prm: PowerParams, soc: float, temp_c: float) -> float:
    """How far the cell's OCV at ``temp_c`` sits from the OCV table the prediction reads."""
    at_t = float(cellmod.ocv_v(params, np.array([soc]), np.array([temp_c]))[0])
    return at_t - float(np.interp(soc, prm.ocv_soc, prm.ocv_v))


def dudt_v_per_k(params: CellParams, soc: float, temp_c: float) -> float:
    """The cell's entropic coefficient dOCV/dT at this state (V/K)."""
    lo, hi = cellmod.ocv_v(params, np.array([soc, soc]), np.array([temp_c - 1.0, temp_c + 1.0]))
    return float(hi - lo) / 2.0


def _gap(x: float) -> float:
    return max(x, 0.0) if math.isfinite(x) else 0.0


def _tighter(trip: float, published: F64 | None, i: int) -> float:
    if published is None or not math.isfinite(published[i]):
        return float(trip)
    return min(float(trip), max(float(published[i]), 0.0))


def inputs_from_plant(cfg: ScenarioConfig, pack: Pack) -> PowerInputs:
    """The batteries' true state in the simulated plant (every pack of ``pack``): SOC and
    polarisation averaged over each battery's cells, its hottest cell, its R0 from the plant's
    present Thevenin resistances, R1 / tau from the cell set at that state; the lowest and
    highest cell's distance from the average."""
    bats = traction(cfg)
    strings = [k for k, b in enumerate(cfg.pack.batteries) if b.role != "aux"]
    P = pack.n_packs
    pp = params_of(cfg)
    inp = new_inputs(P, len(bats))
    soc, temp = pack.cell_states()
    jig = np.empty_like(temp)
    for bank in pack.banks:
        jig.ravel()[bank.idx] = bank.state.jig_temp_c
    eta = np.zeros((2, *soc.shape))
    for bank in pack.banks:
        for r in range(bank.state.eta_v.shape[1]):
            eta[r].ravel()[bank.idx] = bank.state.eta_v[:, r]
    v_cell = pack.e_cell  # at rest under no current: the source voltage
    present = pack.present()
    chg, dsg = pack.effective_gates()
    for i, (b, k) in enumerate(zip(bats, strings, strict=True)):
        sl = slice(pack.string_cell_starts[k], pack.string_cell_starts[k] + b.n_cells)
        prm = cell_set(cfg, b)
        for p in range(P):
            s = float(soc[p, sl].mean())
            t = float(temp[p, sl].max())
            cur = float(pack.string_a[p, k])
            # the RC branches at the cells' mean temperature; the limits at the hottest
            rc = cell_rc(prm, s, float(temp[p, sl].mean()), cur)
            _fill_rc(inp, p, i, b, rc, float(pack.cell_r_scale[p, sl].mean()))
            # the plant's own R0 (every cell's state), brought back to zero current
            at_cur = math.exp(rc.r_per_a * abs(cur))
            inp.r0_ohm[p, i] = float(pack.r_cell[p, sl].sum()) / at_cur
            inp.v1_v[p, i] = float(eta[0, p, sl].sum())
            inp.v2_v[p, i] = float(eta[1, p, sl].sum())
            inp.soc[p, i] = s
            emf = float(pack.e_cell[p, sl].sum() + eta[:, p, sl].sum())
            inp.emf_offset_v[p, i] = emf - b.n_cells * float(np.interp(s, pp.ocv_soc, pp.ocv_v))
            inp.dudt_v_per_k[p, i] = b.n_cells * dudt_v_per_k(prm, s, t)
            inp.temp_c[p, i] = t
            inp.surround_c[p, i] = float(jig[p, sl].mean())
            inp.capacity_ah[p, i] = float(pack.capacity_ah[p, sl].mean())
            avg = float(v_cell[p, sl].mean())
            inp.low_cell_v[p, i] = _gap(avg - float(v_cell[p, sl].min()))
            inp.high_cell_v[p, i] = _gap(float(v_cell[p, sl].max()) - avg)
            inp.present[p, i] = bool(present[p, k])
            inp.chg_on[p, i] = bool(chg[p, k])
            inp.dsg_on[p, i] = bool(dsg[p, k])
        dl, cl = current_limits(cfg, inp.capacity_ah[:, i])
        inp.limit_dsg_a[:, i] = dl
        inp.limit_chg_a[:, i] = cl
    return inp


def rest_inputs(cfg: ScenarioConfig, prm: PowerParams, soc: float, temp_c: float) -> PowerInputs:
    """Every traction battery at rest at ``soc`` and ``temp_c``, switches closed: the state
    a designer asks about."""
    n = prm.series.shape[0]
    ocv = float(np.interp(soc, prm.ocv_soc, prm.ocv_v))
    return inputs_from_core(
        cfg, soc=np.full(n, soc), temp_c=np.full(n, temp_c), current_a=np.zeros(n),
        voltage_v=prm.series * ocv, min_cell_v=np.full(n, ocv), max_cell_v=np.full(n, ocv),
        present=np.ones(n, bool), chg_on=np.ones(n, bool), dsg_on=np.ones(n, bool),
    )  # fmt: skip


def join_table(
    cfg: ScenarioConfig,
    socs: tuple[float, ...] = (0.2, 0.5, 0.8),
    temps_c: tuple[float, ...] | None = None,
    switch_a: float = math.inf,
    load_a: float = 0.0,
) -> list[dict[str, float | str]]:
    """The join planner as a designer's table: for each traction battery joining the others
    (all at rest at one SOC and temperature, the others holding ``load_a``), the admissible
    dV above and below the bus (its switch within ``switch_a`` and its own current limits,
    every other battery within its own), and the predicted peak at the supervisor's fixed
    ``join_limit_v``. Without a ``[limits]`` section the default limits table's trips
    stand for the batteries' current limits; a dV of ``dv_max`` (an empty battery against a
    full one) means any difference is admissible."""
    if cfg.limits is None:  # a designer's question: the default limits table's trips
        cfg = cfg.model_copy(update={"limits": LimitsConfig()})
    prm = params_of(cfg)
    bats = traction(cfg)
    if len(bats) < 2:
        raise ConfigError("plan-join: the pack needs at least two traction batteries to join")
    fixed = (cfg.supervisor or SupervisorConfig()).join_limit_v
    temps = temps_c if temps_c is not None else (0.0, cfg.pack.ambient_c)
    # the largest difference two of these batteries can have: empty against full
    dv_max = float(max(prm.series) * (prm.ocv_v[-1] - prm.ocv_v[0]))
    rows: list[dict[str, float | str]] = []
    for j, b in enumerate(bats):
        for soc in socs:
            for t in temps:
                inp = rest_inputs(cfg, prm, soc, t)
                up_a = min(switch_a, float(inp.limit_dsg_a[0, j]))
                down_a = min(switch_a, float(inp.limit_chg_a[0, j]))
                plan = plan_join(prm, inp, j, fixed, load_a=load_a, horizon_s=60.0,
                                 n_steps=1200, limit_a=up_a)  # fmt: skip
                rows.append({
                    "battery": b.name, "soc": soc, "temp_c": t,
                    "r_loop_ohm": _loop_ohm(prm, inp, j),
                    "dv_up_v": admissible_dv(prm, inp, j, up_a, sign=1.0, load_a=load_a,
                                             dv_max=dv_max),
                    "dv_down_v": admissible_dv(prm, inp, j, down_a, sign=-1.0, load_a=load_a,
                                               dv_max=dv_max),
                    "fixed_dv_v": fixed, "peak_at_fixed_a": plan.peak_a,
                    "half_s": plan.half_s, "limit_up_a": up_a, "limit_down_a": down_a,
                })  # fmt: skip
    return rows


def _loop_ohm(prm: PowerParams, inp: PowerInputs, j: int) -> float:
    """Battery ``j`` with its leads and switch, in series with the others in parallel (both
    FETs / the relay closed): the resistance a dV drives the first instant's current
    through."""

    def arm(s: int) -> float:
        sw = prm.on_ohm[s] if prm.relay[s] else 2.0 * prm.on_ohm[s]
        return float(inp.r0_ohm[0, s] + prm.series_ohm[s] + sw)

    others = sum(1.0 / arm(s) for s in range(prm.series.shape[0]) if s != j)
    return arm(j) + (1.0 / others if others > 0 else math.inf)


__all__ = [
    "CellRc",
    "cell_rc",
    "current_limits",
    "inputs_from_core",
    "inputs_from_plant",
    "join_table",
    "params_of",
    "resistance_scale",
    "traction",
]
