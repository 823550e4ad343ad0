"""The state of power and the join plans of a pack *now*, from what the core knows: one function
for the runtime's publisher (CCL/DCL, 0x231, DroneCAN), the live dashboard and the run report
(issue #28 §3, §4), so the three can never show different figures for the same state.

:class:`CoreView` is that state, one pack, arrays over the traction batteries: the SOC the core
uses (``contract/soc_source.py``: the observer's estimate where trusted, the coulomb counter as
fallback, the battery's own report without an estimator), the observer's polarisation and R0
where it is trusted, the measurements, the switch states, the limits layer's per-battery
limits, and whether the supervisor has opened every path. The publisher fills it from the
core's arrays (:func:`view_of_core` there), the dashboard and the report from a recorded step
(:func:`view_of_status`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.contract.soc_source import shown_soc
from packpilot.control.power import (
    HORIZONS_S,
    WHY_NAMES,
    PowerInputs,
    PowerOut,
    PowerParams,
    admissible_dv,
    held_bus_v,
    plan_join,
    state_of_power,
)
from packpilot.sim.power import inputs_from_core

F64 = NDArray[np.float64]
B = NDArray[np.bool_]
TRIPPED_MODES = ("fault", "shutdown")
"""Supervisor modes that open every path: no power, no join."""


@dataclass
class CoreView:
    """What the core knows of one pack now (arrays over the traction batteries)."""

    soc_est: F64
    """``soc_est`` (NaN: no estimator)."""
    observer_ok: B
    soc_sigma: F64
    reported_soc: F64
    """The battery's own SOC, shown only where the core has no estimate."""
    v_rc_v: F64
    r0_ohm: F64
    temp_c: F64
    current_a: F64
    voltage_v: F64
    min_cell_v: F64
    max_cell_v: F64
    present: B
    chg_on: B
    dsg_on: B
    limit_dsg_a: F64
    limit_chg_a: F64
    tripped: bool = False
    bus_v: float = math.nan
    load_a: float = 0.0

    def soc(self) -> tuple[F64, list[str]]:
        """The SOC the core uses per battery, and its source (``contract/soc_source.py``)."""
        pairs = [
            shown_soc(float(e), bool(ok), float(s), float(r))
            for e, ok, s, r in zip(self.soc_est, self.observer_ok, self.soc_sigma,
                                   self.reported_soc, strict=True)
        ]  # fmt: skip
        return np.array([p[0] for p in pairs], np.float64), [p[1] for p in pairs]


def sop_inputs(cfg: ScenarioConfig, prm: PowerParams, view: CoreView) -> PowerInputs | None:
    """The prediction's inputs from the view: a battery not reporting, or without a SOC,
    counts as absent (the others carry everything); the observer's polarisation and R0 only
    where it is trusted; every battery absent when the supervisor has opened every path.
    None when no battery can be predicted."""
    if prm.series.shape[0] != len(view.soc_est):
        return None
    soc, _ = view.soc()
    here = view.present & np.isfinite(soc)
    if not here.any():
        return None
    ok = view.observer_ok
    inp = inputs_from_core(
        cfg, soc=soc, temp_c=view.temp_c, current_a=view.current_a, voltage_v=view.voltage_v,
        min_cell_v=view.min_cell_v, max_cell_v=view.max_cell_v, present=here,
        chg_on=view.chg_on, dsg_on=view.dsg_on, limit_dsg_a=view.limit_dsg_a,
        limit_chg_a=view.limit_chg_a, prm=prm,
        polarisation_v=np.where(ok, view.v_rc_v, math.nan),
        r0_ohm=np.where(ok, view.r0_ohm, math.nan),
    )  # fmt: skip
    if view.tripped:
        inp.present[0, :] = False
    return inp


def state_of_power_now(cfg: ScenarioConfig, prm: PowerParams, view: CoreView, *,
                       alone: bool | float = True) -> PowerOut | None:  # fmt: skip
    """The pack's state of power from the view (None: nothing can be predicted); ``alone``
    as :func:`~packpilot.control.power.state_of_power`'s."""
    inp = sop_inputs(cfg, prm, view)
    return None if inp is None else state_of_power(prm, inp, alone=alone)


def _dv_max(prm: PowerParams) -> float:
    """The largest difference two of these batteries can have: empty against full."""
    return float(max(prm.series) * (prm.ocv_v[-1] - prm.ocv_v[0]))


def joining(view: CoreView, here: B) -> list[int]:
    """Batteries about to join: present, their path not fully closed (a relay open, or a
    MOSFET pair with a FET off: sequencing's STANDBY, a battery held out), while another
    battery holds the bus; none while the supervisor has every path open."""
    closed = view.chg_on & view.dsg_on
    out = []
    for j in range(len(closed)):
        others = here & (view.chg_on | view.dsg_on)
        others[j] = False
        if here[j] and not closed[j] and others.any() and not view.tripped:
            out.append(j)
    return out


def join_plans(
    cfg: ScenarioConfig, prm: PowerParams, view: CoreView, inp: PowerInputs
) -> list[dict[str, Any]]:
    """For each battery about to join (:func:`joining`): the join planner's predicted peak
    current through its switch once both paths close, at the voltage difference measured now
    (its terminal voltage against the bus), judged against the battery's limit in that
    direction (its discharge limit when it sits above the bus, its charge limit below), and
    the admissible difference above and below the bus (``docs/power.md``, Join planning)."""
    out: list[dict[str, Any]] = []
    for j in joining(view, inp.present[0].copy()):
        closing = inp._replace(chg_on=inp.chg_on.copy(), dsg_on=inp.dsg_on.copy())
        closing.chg_on[0, j] = closing.dsg_on[0, j] = True
        dv = float(view.voltage_v[j] - view.bus_v)
        dv = dv if math.isfinite(dv) else math.nan
        up_a, down_a = float(inp.limit_dsg_a[0, j]), float(inp.limit_chg_a[0, j])
        limit = up_a if not (dv < 0.0) else down_a
        load = view.load_a if math.isfinite(view.load_a) else 0.0
        plan = plan_join(prm, closing, j, dv, load_a=load, limit_a=limit, horizon_s=30.0,
                         n_steps=300)  # fmt: skip
        out.append({
            "battery": j, "dv_v": dv, "peak_a": plan.peak_a, "limit_a": limit,
            "over_s": plan.over_s, "half_s": plan.half_s,
            "dv_up_v": admissible_dv(prm, closing, j, up_a, sign=1.0, load_a=load,
                                     dv_max=_dv_max(prm)),
            "dv_down_v": admissible_dv(prm, closing, j, down_a, sign=-1.0, load_a=load,
                                       dv_max=_dv_max(prm)),
            "within": bool(abs(plan.peak_a) <= limit),
        })  # fmt: skip
    return out


def battery_watts(prm: PowerParams, inp: PowerInputs, out: PowerOut) -> dict[str, F64]:
    """Each battery's power at its limits, (B, H) W per direction: its share of the pack's
    limit times the bus voltage the pack's power is taken at (the lowest on the way
    discharging, the highest charging: ``pack_dsg_w / pack_dsg_a``), and its own limit alone
    on the bus times the bus voltage while it alone holds that limit for the horizon
    (:func:`~packpilot.control.power.held_bus_v`). Power delivered to (taken from) the bus;
    0 where the limit is 0. Why here and not in the page: one function serves every view."""
    n, hs = inp.soc.shape[1], prm.horizons_s.tolist()
    res = {k: np.zeros((n, len(hs))) for k in ("share_dsg_w", "share_chg_w", "alone_dsg_w",
                                               "alone_chg_w")}  # fmt: skip
    for h, secs in enumerate(hs):
        for d, sign in (("dsg", 1.0), ("chg", -1.0)):
            pack_a = float(getattr(out, f"pack_{d}_a")[0, h])
            bus = float(getattr(out, f"pack_{d}_w")[0, h]) / pack_a if pack_a > 0.0 else 0.0
            res[f"share_{d}_w"][:, h] = getattr(out, f"share_{d}_a")[0, :, h] * bus + 0.0  # no -0
            for i in range(n):
                a = float(getattr(out, f"alone_{d}_a")[0, i, h])
                if not (a > 0.0 and inp.present[0, i]):
                    continue
                lo, hi = held_bus_v(prm, inp, sign * a, secs, only=i)
                res[f"alone_{d}_w"][i, h] = a * (lo if sign > 0.0 else hi)
    return res


def power_summary(
    cfg: ScenarioConfig, prm: PowerParams, view: CoreView, names: Sequence[str]
) -> dict[str, Any] | None:
    """Everything a page shows of the pack's power now (JSON-able; NaN stays NaN for the
    caller's encoder): per horizon the pack's discharge and charge limit (A, W) with what
    stops more and in which battery, per battery its share of the pack's limit and its limit
    alone, each in W too (:func:`battery_watts`), the join plans, and the SOC source each
    battery's prediction started from."""
    inp = sop_inputs(cfg, prm, view)
    if inp is None:
        return None
    out = state_of_power(prm, inp)
    _, sources = view.soc()

    def who(k: int) -> str | None:
        return names[k] if 0 <= k < len(names) else None

    horizons = []
    for h, secs in enumerate(prm.horizons_s.tolist()):
        horizons.append({
            "horizon_s": secs,
            "dsg_a": float(out.pack_dsg_a[0, h]), "chg_a": float(out.pack_chg_a[0, h]),
            "dsg_w": float(out.pack_dsg_w[0, h]), "chg_w": float(out.pack_chg_w[0, h]),
            "why_dsg": WHY_NAMES[int(out.why_dsg[0, h])], "who_dsg": who(int(out.who_dsg[0, h])),
            "why_chg": WHY_NAMES[int(out.why_chg[0, h])], "who_chg": who(int(out.who_chg[0, h])),
        })  # fmt: skip
    watts = battery_watts(prm, inp, out)
    batteries = [
        {
            "name": names[i] if i < len(names) else str(i),
            "present": bool(inp.present[0, i]),
            "soc_source": sources[i],
            "share_dsg_a": out.share_dsg_a[0, i].tolist(),
            "share_chg_a": out.share_chg_a[0, i].tolist(),
            "alone_dsg_a": out.alone_dsg_a[0, i].tolist(),
            "alone_chg_a": out.alone_chg_a[0, i].tolist(),
            **{k: w[i].tolist() for k, w in watts.items()},
        }
        for i in range(inp.soc.shape[1])
    ]
    joins = join_plans(cfg, prm, view, inp)
    for plan in joins:
        plan["name"] = who(int(plan["battery"]))
    return {"horizons": horizons, "batteries": batteries, "joins": joins}


def _col(rows: F64, name: str) -> F64:
    return np.asarray(rows[:, BATTERY_CHANNELS.index(name)], np.float64)


def _f(x: object) -> float:
    if isinstance(x, bool):
        return 1.0 if x else 0.0
    return float(x) if isinstance(x, int | float) else math.nan


def view_of_status(
    rows: F64,
    status: Callable[[str, int], object],
    cols: Sequence[int],
    *,
    bus_v: float,
    load_a: float,
    mode: object = None,
) -> CoreView:
    """The view from one recorded step: ``rows`` the step's battery rows (``BATTERY_CHANNELS``
    columns, the plant's), ``status(name, b)`` a status channel's value for battery row ``b``
    (None when absent), ``cols`` the traction batteries' rows. What the BMS measured
    (``bms_v``, ``bms_a``, ``bms_degc``, ``bms_soc``) stands where it was recorded; the cell
    extremes and switch states are the recorded ones (the feedback the core reads)."""
    c = list(cols)

    def st(name: str) -> F64:
        return np.array([_f(status(name, b)) for b in c], np.float64)

    def measured(channel: str, column: str) -> F64:
        got = [status(channel, b) for b in c]
        truth = _col(rows, column)[c]
        if all(g is None for g in got):
            return truth
        return np.array([_f(g) for g in got], np.float64)

    voltage = measured("bms_v", "voltage_v")
    ok = np.array([status("soc_observer_ok", b) in (True, 1, 1.0) for b in c], np.bool_)
    return CoreView(
        soc_est=st("soc_est"), observer_ok=ok, soc_sigma=st("soc_sigma"),
        reported_soc=measured("bms_soc", "soc"), v_rc_v=st("soc_v_rc_v"),
        r0_ohm=st("soc_r0_ohm"), temp_c=measured("bms_degc", "temp_c"),
        current_a=measured("bms_a", "current_a"), voltage_v=voltage,
        min_cell_v=_col(rows, "min_cell_v")[c], max_cell_v=_col(rows, "max_cell_v")[c],
        present=np.isfinite(voltage), chg_on=_col(rows, "chg_on")[c] > 0.5,
        dsg_on=_col(rows, "dsg_on")[c] > 0.5, limit_dsg_a=st("limit_dsg_a"),
        limit_chg_a=st("limit_chg_a"), tripped=mode in TRIPPED_MODES, bus_v=float(bus_v),
        load_a=float(load_a),
    )  # fmt: skip


__all__ = [
    "HORIZONS_S",
    "TRIPPED_MODES",
    "CoreView",
    "battery_watts",
    "join_plans",
    "joining",
    "power_summary",
    "sop_inputs",
    "state_of_power_now",
    "view_of_status",
]
