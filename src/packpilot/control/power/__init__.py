"""State of power and join planning (``docs/power.md``): the compiled prediction of
:mod:`packpilot.control.power.rules` and its Python face.

Not a method of the fused step: it answers questions about the present state (how much can
the pack hold for 2 / 10 / 30 s; what will closing this switch cause) when a publisher, the
dashboard, a report or a designer asks, from one input structure, :class:`PowerInputs`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from packpilot.control.power import rules
from packpilot.control.power.rules import (
    WHY_CURRENT,
    WHY_CUTOFF,
    WHY_NAMES,
    WHY_NONE,
    WHY_SUPPLY,
    WHY_TEMP,
    PowerInputs,
    PowerOut,
    PowerParams,
    PowerWork,
)
from packpilot.errors import ConfigError

HORIZONS_S = (2.0, 10.0, 30.0)
"""The horizons the issue asks for."""


def make_params(
    *,
    ocv_soc: ArrayLike,
    ocv_v: ArrayLike,
    series: Sequence[float],
    relay: Sequence[bool],
    on_ohm: Sequence[float],
    diode_drop_v: Sequence[float],
    diode_ohm: Sequence[float],
    series_ohm: Sequence[float] | None = None,
    cell_v_min: Sequence[float],
    cell_v_max: Sequence[float],
    temp_max_dsg_c: Sequence[float],
    temp_max_chg_c: Sequence[float],
    temp_min_dsg_c: Sequence[float] | None = None,
    temp_min_chg_c: Sequence[float] | None = None,
    heat_j_per_k: Sequence[float],
    cool_w_per_k: Sequence[float] | None = None,
    horizons_s: Sequence[float] = HORIZONS_S,
    n_sub: int = 30,
    iters: int = 16,
    margin: float = 0.0,
) -> PowerParams:
    """The static facts, checked (a bad value raises :class:`ConfigError` naming it)."""
    xs = np.asarray(ocv_soc, np.float64)
    ys = np.asarray(ocv_v, np.float64)
    if xs.size < 2 or xs.shape != ys.shape or not np.all(np.diff(xs) > 0):
        raise ConfigError("power: the OCV table needs >= 2 points with strictly increasing SOC")
    n = len(series)
    cold = [-math.inf] * n
    temp_min_dsg_c = cold if temp_min_dsg_c is None else temp_min_dsg_c
    temp_min_chg_c = cold if temp_min_chg_c is None else temp_min_chg_c
    cool_w_per_k = [0.0] * n if cool_w_per_k is None else cool_w_per_k
    series_ohm = [0.0] * n if series_ohm is None else series_ohm
    per = {
        "series": series, "relay": relay, "on_ohm": on_ohm, "diode_drop_v": diode_drop_v,
        "diode_ohm": diode_ohm, "series_ohm": series_ohm, "cell_v_min": cell_v_min,
        "cell_v_max": cell_v_max,
        "temp_max_dsg_c": temp_max_dsg_c,
        "temp_max_chg_c": temp_max_chg_c, "temp_min_dsg_c": temp_min_dsg_c,
        "temp_min_chg_c": temp_min_chg_c, "heat_j_per_k": heat_j_per_k,
        "cool_w_per_k": cool_w_per_k,
    }  # fmt: skip
    for name, v in per.items():
        if len(v) != n:
            raise ConfigError(f"power: {name} has {len(v)} entries, need {n}")
    if not all(s > 0 for s in series):
        raise ConfigError("power: series must be > 0 for every battery")
    if not all(math.isfinite(r) and r >= 0 for r in series_ohm):
        raise ConfigError(f"power: series_ohm must be finite and >= 0, got {list(series_ohm)}")
    if not (horizons_s and all(math.isfinite(h) and h > 0 for h in horizons_s)):
        raise ConfigError(f"power: horizons_s must be positive, got {tuple(horizons_s)}")
    if n_sub < 1 or iters < 1:
        raise ConfigError("power: n_sub and iters must be >= 1")
    if not 0.0 <= margin < 1.0:
        raise ConfigError(f"power: margin must be in 0..1, got {margin}")

    def f(v: ArrayLike) -> np.ndarray:
        return np.asarray(v, np.float64)

    return PowerParams(
        ocv_soc=xs, ocv_v=ys, series=f(series), relay=np.asarray(relay, np.bool_),
        on_ohm=f(on_ohm), diode_drop_v=f(diode_drop_v), diode_ohm=f(diode_ohm),
        series_ohm=f(series_ohm), cell_v_min=f(cell_v_min), cell_v_max=f(cell_v_max),
        temp_max_dsg_c=f(temp_max_dsg_c), temp_max_chg_c=f(temp_max_chg_c),
        temp_min_dsg_c=f(temp_min_dsg_c), temp_min_chg_c=f(temp_min_chg_c),
        heat_j_per_k=f(heat_j_per_k), cool_w_per_k=f(cool_w_per_k), horizons_s=f(horizons_s),
        n_sub=int(n_sub), margin=float(margin),
        iters=int(iters),
    )  # fmt: skip


def new_inputs(n_packs: int, n_batteries: int) -> PowerInputs:
    """Inputs with every battery present, both paths on, no polarisation, no limits; the
    caller writes the state (SOC, capacity, temperature, resistances) before asking."""
    shape = (n_packs, n_batteries)

    def full(x: float) -> np.ndarray:
        return np.full(shape, x, np.float64)

    return PowerInputs(
        present=np.ones(shape, np.bool_), chg_on=np.ones(shape, np.bool_),
        dsg_on=np.ones(shape, np.bool_), soc=full(math.nan), capacity_ah=full(math.nan),
        temp_c=full(25.0), r0_ohm=full(math.nan), r1_ohm=full(0.0), tau1_s=full(0.0),
        v1_v=full(0.0), r2_ohm=full(0.0), tau2_s=full(0.0), v2_v=full(0.0), emf_offset_v=full(0.0),
        surround_c=full(math.nan), dudt_v_per_k=full(0.0), r_per_k=full(0.0),
        r_per_soc=full(0.0), r_per_a=full(0.0),
        low_cell_v=full(0.0), high_cell_v=full(0.0), limit_dsg_a=full(math.inf),
        limit_chg_a=full(math.inf),
    )  # fmt: skip


def new_work(n_packs: int, n_batteries: int) -> PowerWork:
    shape = (n_packs, n_batteries)

    def z() -> np.ndarray:
        return np.zeros(shape, np.float64)

    def b() -> np.ndarray:
        return np.zeros(shape, np.bool_)

    return PowerWork(
        soc=z(), v1=z(), v2=z(), temp=z(), r0=z(), e=z(), eoff=z(), cur=z(), peak_pos=z(),
        peak_neg=z(), dok=b(), ddrop=z(), dohm=z(), cok=b(), cdrop=z(), cohm=z(),
        bus_lo=np.zeros(n_packs), bus_hi=np.zeros(n_packs),
        why=np.zeros(n_packs, np.int64), who=np.zeros(n_packs, np.int64),
        only=np.full(n_packs, -1, np.int64),
    )  # fmt: skip


def new_out(n_packs: int, n_batteries: int, n_horizons: int) -> PowerOut:
    ph = (n_packs, n_horizons)
    pbh = (n_packs, n_batteries, n_horizons)
    return PowerOut(
        pack_dsg_a=np.zeros(ph), pack_chg_a=np.zeros(ph), pack_dsg_w=np.zeros(ph),
        pack_chg_w=np.zeros(ph), share_dsg_a=np.zeros(pbh), share_chg_a=np.zeros(pbh),
        alone_dsg_a=np.zeros(pbh), alone_chg_a=np.zeros(pbh),
        why_dsg=np.zeros(ph, np.int64), who_dsg=np.zeros(ph, np.int64),
        why_chg=np.zeros(ph, np.int64), who_chg=np.zeros(ph, np.int64),
    )  # fmt: skip


def _check(prm: PowerParams, inp: PowerInputs) -> None:
    n = prm.series.shape[0]
    if inp.soc.ndim != 2 or inp.soc.shape[1] != n:
        raise ConfigError(f"power: inputs are shaped {inp.soc.shape}, need (packs, {n})")
    bad = inp.present & ~((inp.r0_ohm > 0) & (inp.capacity_ah > 0) & np.isfinite(inp.soc))
    if bad.any():
        p, i = (int(x) for x in np.argwhere(bad)[0])
        raise ConfigError(
            f"power: battery {i} of pack {p} needs r0_ohm > 0, capacity_ah > 0 and a SOC "
            f"(got {inp.r0_ohm[p, i]}, {inp.capacity_ah[p, i]}, {inp.soc[p, i]})"
        )


def state_of_power(prm: PowerParams, inp: PowerInputs, *,
                   alone: bool | float = True) -> PowerOut:  # fmt: skip
    """The state of power of every pack of ``inp`` (one compiled call for P packs).

    ``alone``: each battery's own limits (``alone_*``) at every horizon (True), at none
    (False: the runtime publishes only the pack's) or at the one horizon of that many
    seconds (the report shows the 10 s one); NaN elsewhere. They are 2B of the 2B + 2
    searches per horizon: 80 % of the CPU at 4 batteries."""
    _check(prm, inp)
    P, B = inp.soc.shape
    out = new_out(P, B, prm.horizons_s.shape[0])
    rules.sop_packs(prm, inp, new_work(P, B), out, _alone_k(prm, alone))
    return out


def _alone_k(prm: PowerParams, alone: bool | float) -> int:
    if alone is True:
        return rules.ALONE_ALL
    if alone is False:
        return rules.ALONE_NONE
    hits = np.nonzero(np.isclose(prm.horizons_s, float(alone)))[0]
    if hits.size == 0:
        raise ConfigError(f"power: no horizon of {alone} s (horizons_s {prm.horizons_s.tolist()})")
    return int(hits[0])


def held_bus_v(prm: PowerParams, inp: PowerInputs, current_a: float, horizon_s: float, *,
               pack: int = 0, only: int = -1) -> tuple[float, float]:  # fmt: skip
    """The lowest and highest bus voltage while pack ``pack`` (or battery ``only`` alone)
    holds ``current_a`` (positive discharging) for ``horizon_s``, as :func:`state_of_power`
    judges it (NaN, NaN where it cannot be held to the end): the voltage a limit's power is
    that current times."""
    _check(prm, inp)
    P, B = inp.soc.shape
    wk = new_work(P, B)
    why = rules.hold(prm, inp, wk, pack, only, float(current_a), float(horizon_s))
    if why != rules.WHY_NONE:
        return math.nan, math.nan
    return float(wk.bus_lo[pack]), float(wk.bus_hi[pack])


@dataclass(frozen=True)
class JoinPlan:
    """What closing battery ``j``'s switch onto the bus is predicted to cause."""

    bus_v: float
    """Bus voltage just before (the other batteries carrying the load)."""
    peak_a: float
    """Peak current through the switch, signed (positive: the joining battery discharges)."""
    over_s: float
    """Time the current stays above the limit it was judged against."""
    half_s: float
    """Time until the current has fallen to half its peak (NaN: not within the horizon)."""
    end_a: float
    """The current at the end of the horizon."""


def plan_join(
    prm: PowerParams, inp: PowerInputs, j: int, dv: float, *, pack: int = 0,
    load_a: float = 0.0, horizon_s: float = 30.0, n_steps: int = 600,
    limit_a: float = math.inf,
) -> JoinPlan:  # fmt: skip
    """Battery ``j`` joins pack ``pack`` with its source ``dv`` volts above the bus voltage
    (NaN: at its own state's voltage; its switch state once closed is
    ``inp.chg_on``/``inp.dsg_on``)."""
    _check(prm, inp)
    P, B = inp.soc.shape
    if not (0 <= j < B and 0 <= pack < P):
        raise ConfigError(f"power: no battery {j} in pack {pack}")
    wk = new_work(P, B)
    v0 = float(rules.join_bus_v(prm, inp, wk, pack, j, load_a))
    pk, over, half, end = rules.join(prm, inp, wk, pack, j, load_a, dv, horizon_s, n_steps,
                                     limit_a)  # fmt: skip
    return JoinPlan(v0, float(pk), float(over), float(half), float(end))


def admissible_dv(
    prm: PowerParams, inp: PowerInputs, j: int, limit_a: float, *, sign: float = 1.0,
    pack: int = 0, load_a: float = 0.0, dv_max: float = 50.0, iters: int = 40,
) -> float:  # fmt: skip
    """The largest ``|dV|`` at which battery ``j`` may join (above the bus for ``sign`` = 1,
    below for -1) without its switch current exceeding ``limit_a``: the join planner's
    admissible voltage difference, derived for this pack and state instead of fixed."""
    _check(prm, inp)
    P, B = inp.soc.shape
    wk = new_work(P, B)
    return float(rules.admissible_dv(prm, inp, wk, pack, j, load_a, sign, limit_a, dv_max, 2,
                                     iters))  # fmt: skip


__all__ = [
    "HORIZONS_S",
    "WHY_CURRENT",
    "WHY_CUTOFF",
    "WHY_NAMES",
    "WHY_NONE",
    "WHY_SUPPLY",
    "WHY_TEMP",
    "JoinPlan",
    "PowerInputs",
    "PowerOut",
    "PowerParams",
    "PowerWork",
    "admissible_dv",
    "held_bus_v",
    "make_params",
    "new_inputs",
    "new_out",
    "new_work",
    "plan_join",
    "state_of_power",
]
