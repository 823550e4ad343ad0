"""Issue #28 items 3 and 4 on the plant: state of power and the join planner.

**State of power.** For a sweep of SOC (packs' SOC shifted by -0.3, 0, +0.3 around 0.5),
ambient temperature (5, 25, 40 degC) and battery spread (two equal batteries; one fresh and
one aged: 1.8x resistance, 0.8x capacity, 8 % less charge; three batteries of spread age),
the core's predicted 10 s discharge limit (``control.power`` from the plant's true state) is
drawn from the plant as a constant current for 10 s: no cell may fall below the cut-off, no
battery exceed its current limit or its temperature limit. The *true* 10 s limit is then
found by bisection on the plant (the largest constant current that crosses nothing), and the
prediction must reach >= 90 % of it.

**Join planner.** A battery at rest joins a bus held by another (resting, or after 60 s at
20 A, so that the one on the bus is polarised), over a sweep of dV (via the joining
battery's SOC), its resistance (1x, 2x, 4x) and the switch type (relay; MOSFET pair with
both FETs closing). The predicted peak current through the switch is compared with the
plant's largest current in the 2 s after the switch closes (within 15 %).

**Leads, connectors and shunt** (``--series-ohm X[,Y...]``, issue #27's ``series_ohm``): every
case again with that resistance in each battery's branch (A, B, C in order; the last value
repeats), outside its cells: the plant's bus sits ``I x series_ohm`` lower while the cells'
voltages and heat are unchanged, so only the split between batteries, the bus voltage (the
limit's power) and a join's loop resistance move.

``python benchmarks/bench_power.py [--series-ohm X[,Y...]] [--append]``; ``--append`` adds a
dated section at the end of ``benchmarks/RESULTS.md`` (``make bench`` does, without series
resistance).
"""

from __future__ import annotations

import datetime as _dt
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig
from packpilot.config.scenario import parse_config
from packpilot.control import power as pw
from packpilot.model.pack import Pack
from packpilot.sim.power import (
    current_limits,
    inputs_from_core,
    inputs_from_plant,
    params_of,
    traction,
)

HERE = Path(__file__).resolve().parent
DT_S = 0.1
HOLD_S = 10.0
H10 = 1  # index of 10 s in HORIZONS_S

SPREADS: dict[str, list[dict[str, Any]]] = {
    "equal": [
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.02},
        {"name": "B", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.02},
    ],
    "fresh+aged": [
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.02},
        {"name": "B", "cells_per_group": 6, "soc0": 0.42, "resistance_ohm": 0.036,
         "capacity_ah": 4.0},
    ],
    "three": [
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.018},
        {"name": "B", "cells_per_group": 6, "soc0": 0.46, "resistance_ohm": 0.026,
         "capacity_ah": 4.5},
        {"name": "C", "cells_per_group": 6, "soc0": 0.42, "resistance_ohm": 0.034,
         "capacity_ah": 4.0},
    ],
}  # fmt: skip
SOC_SHIFT = (-0.3, 0.0, 0.3)
AMBIENT_C = (5.0, 25.0, 40.0)


def with_series(bats: list[dict[str, Any]], series_ohm: tuple[float, ...]) -> list[dict[str, Any]]:
    """The batteries with ``series_ohm`` in their branches (by position; the last repeats;
    none for an empty tuple)."""
    if not series_ohm:
        return bats
    return [
        {**b, "series_ohm": series_ohm[min(k, len(series_ohm) - 1)]} for k, b in enumerate(bats)
    ]


def scenario(bats: list[dict[str, Any]], kind: str = "mosfet_pair",
             series_ohm: tuple[float, ...] = ()) -> ScenarioConfig:  # fmt: skip
    bats = with_series(bats, series_ohm)
    return parse_config({
        "pack": {"name": "sop", "cell": "uav_5ah", "ambient_c": 25.0,
                 "switch": {"kind": kind, "on_ohm": 0.0005}, "batteries": bats},
        "limits": {},
        "load": {"kind": "current", "value": 0.0},
        "sim": {"dt_s": DT_S, "duration_s": 10.0},
    }, "bench_power")  # fmt: skip


PRELOAD_A = 60.0
PRELOAD_S = 60.0


def _plant(cfg: ScenarioConfig, preload: bool = False) -> Pack:
    """The sweep's packs (SOC shift x ambient), fresh, or after ``PRELOAD_S`` at
    ``PRELOAD_A`` (polarised: what a BMS without an observer does not see)."""
    n = len(SOC_SHIFT) * len(AMBIENT_C)
    shift = np.repeat(SOC_SHIFT, len(AMBIENT_C))
    amb = np.tile(AMBIENT_C, len(SOC_SHIFT))
    pack = Pack(cfg, n_packs=n, soc_offset=shift, ambient_c=amb)
    if preload:
        for _ in range(round(PRELOAD_S / DT_S)):
            pack.step(DT_S, "current", np.full(n, PRELOAD_A))
    return pack


def crossed(cfg: ScenarioConfig, current_a: np.ndarray, hold_s: float = HOLD_S,
            preload: bool = False, bus: bool = False) -> Any:  # fmt: skip
    """Per pack: which limit the plant crossed drawing ``current_a`` for ``hold_s`` (0 none,
    else ``WHY_*``); with ``bus``, also the lowest bus voltage on the way (what the limit's
    power is that current times)."""
    prm = params_of(cfg)
    pack = _plant(cfg, preload)
    strings = [k for k, b in enumerate(cfg.pack.batteries) if b.role != "aux"]
    caps = np.array([b.capacity_ah or 5.0 for b in traction(cfg)])
    lim_d, _ = current_limits(cfg, caps)
    why = np.zeros(pack.n_packs, np.int64)
    bus_min = np.full(pack.n_packs, np.inf)
    for _ in range(round(hold_s / DT_S)):
        iv = pack.step(DT_S, "current", current_a)
        bus_min = np.minimum(bus_min, iv.bus_v)
        _soc, temp = pack.cell_states()
        for i, k in enumerate(strings):
            c0 = pack.string_cell_starts[k]
            sl = slice(c0, c0 + cfg.pack.batteries[k].n_cells)
            cur = iv.string_a[:, k]
            cut = (cur > 0) & (iv.cell_v[:, sl].min(axis=1) < prm.cell_v_min[i])
            over = cur > lim_d[i]
            hot = (cur > 0) & (temp[:, sl].max(axis=1) > prm.temp_max_dsg_c[i])
            why = np.where((why == 0) & over, pw.WHY_CURRENT, why)
            why = np.where((why == 0) & cut, pw.WHY_CUTOFF, why)
            why = np.where((why == 0) & hot, pw.WHY_TEMP, why)
        why = np.where((why == 0) & ~iv.supplied, pw.WHY_SUPPLY, why)
    return (why, bus_min) if bus else why


def true_limit(cfg: ScenarioConfig, hi: np.ndarray, iters: int = 16,
               preload: bool = False) -> np.ndarray:  # fmt: skip
    """The largest constant current each pack holds for 10 s on the plant (bisection)."""
    top = hi.copy()
    ok_top = crossed(cfg, top, preload=preload) == 0
    lo = np.zeros_like(hi)
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        ok = crossed(cfg, mid, preload=preload) == 0
        lo = np.where(ok, mid, lo)
        hi = np.where(ok, hi, mid)
    return np.where(ok_top, top, lo)


def sop_sweep(series_ohm: tuple[float, ...] = ()) -> list[dict[str, Any]]:
    rows = []
    for name, bats in SPREADS.items():
        cfg = scenario(bats, series_ohm=series_ohm)
        prm = params_of(cfg)
        inp = inputs_from_plant(cfg, _plant(cfg))
        pw.state_of_power(prm, inp)  # compiled (or loaded) before timing
        t0 = time.process_time()
        out = pw.state_of_power(prm, inp)
        cpu = time.process_time() - t0
        pred = out.pack_dsg_a[:, H10].copy()
        why_pred, bus_min = crossed(cfg, pred, bus=True)
        upper = np.sum(inp.limit_dsg_a, axis=1) * 1.2
        truth = true_limit(cfg, upper)
        aged = out.alone_dsg_a[:, -1, H10]
        for p in range(pred.size):
            rows.append({
                "spread": name, "soc": round(float(inp.soc[p].mean()), 3),
                "ambient_c": AMBIENT_C[p % len(AMBIENT_C)],
                "prediction_a": round(float(pred[p] / (1.0 - prm.margin)), 2),
                "published_a": round(float(pred[p]), 2), "true_a": round(float(truth[p]), 2),
                "ratio": round(float(pred[p] / truth[p]), 4) if truth[p] > 0 else float("nan"),
                "crossed": pw.WHY_NAMES[int(why_pred[p])],
                "binding": pw.WHY_NAMES[int(out.why_dsg[p, H10])],
                "bus_pred_v": round(float(out.pack_dsg_w[p, H10] / pred[p]), 3)
                if pred[p] > 0 else float("nan"),
                "bus_plant_v": round(float(bus_min[p]), 3),
                "weakest_alone_a": round(float(aged[p]), 2),
                "cpu_ms_per_pack": round(1e3 * cpu / pred.size, 2),
            })  # fmt: skip
    return rows


def _core_inputs(cfg: ScenarioConfig, pack: Pack, p: int) -> Any:
    """What the core has today for pack ``p`` of the plant (``inputs_from_core``: no
    polarisation), from the plant's state as a smart battery reports it."""
    strings = [k for k, b in enumerate(cfg.pack.batteries) if b.role != "aux"]
    soc, temp = pack.cell_states()
    v_cell = pack.cell_voltage_now()
    chg, dsg = pack.effective_gates()
    rows: dict[str, list[float]] = {k: [] for k in ("soc", "t", "i", "v", "lo", "hi")}
    for k in strings:
        c0 = pack.string_cell_starts[k]
        sl = slice(c0, c0 + cfg.pack.batteries[k].n_cells)
        rows["soc"].append(float(soc[p, sl].min()))
        rows["t"].append(float(temp[p, sl].max()))
        rows["i"].append(float(pack.string_a[p, k]))
        rows["v"].append(float(v_cell[p, sl].sum()))
        rows["lo"].append(float(v_cell[p, sl].min()))
        rows["hi"].append(float(v_cell[p, sl].max()))
    a = {k: np.array(v) for k, v in rows.items()}
    return inputs_from_core(
        cfg, soc=a["soc"], temp_c=a["t"], current_a=a["i"], voltage_v=a["v"],
        min_cell_v=a["lo"], max_cell_v=a["hi"], present=np.ones(len(strings), bool),
        chg_on=chg[p, strings], dsg_on=dsg[p, strings],
    )  # fmt: skip


def preload_sweep(series_ohm: tuple[float, ...] = ()) -> list[dict[str, Any]]:
    """After 60 s at 60 A: the prediction from the plant's truth (polarisation known, what an
    observer gives) and from what the core has today (no polarisation)."""
    cfg = scenario(SPREADS["fresh+aged"], series_ohm=series_ohm)
    prm = params_of(cfg)
    pack = _plant(cfg, preload=True)
    truth = pw.state_of_power(prm, inputs_from_plant(cfg, pack)).pack_dsg_a[:, H10]
    today = np.array([
        pw.state_of_power(prm, _core_inputs(cfg, pack, p)).pack_dsg_a[0, H10]
        for p in range(pack.n_packs)
    ])  # fmt: skip
    upper = np.full(pack.n_packs, 250.0)
    real = true_limit(cfg, upper, preload=True)
    why_t = crossed(cfg, truth, preload=True)
    why_c = crossed(cfg, today, preload=True)
    rows = []
    for p in range(pack.n_packs):
        rows.append({
            "soc_shift": SOC_SHIFT[p // len(AMBIENT_C)], "ambient_c": AMBIENT_C[p % len(AMBIENT_C)],
            "true_a": round(float(real[p]), 2),
            "truth_prediction_a": round(float(truth[p] / (1.0 - prm.margin)), 2),
            "from_truth_a": round(float(truth[p]), 2),
            "truth_crossed": pw.WHY_NAMES[int(why_t[p])],
            "from_core_today_a": round(float(today[p]), 2),
            "core_crossed": pw.WHY_NAMES[int(why_c[p])],
        })  # fmt: skip
    return rows


def _join_case(kind: str, dsoc: float, r_mult: float, preload: bool,
               series_ohm: tuple[float, ...] = ()) -> dict[str, Any]:  # fmt: skip
    bats = [
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.02},
        {"name": "B", "cells_per_group": 6, "soc0": 0.5 + dsoc, "resistance_ohm": 0.02 * r_mult,
         "switch": {"kind": kind, "on_ohm": 0.0005, "chg_on": False, "dsg_on": False}},
    ]  # fmt: skip
    cfg = scenario(bats, kind, series_ohm)
    pack = Pack(cfg, n_packs=1)
    load = np.array([20.0 if preload else 0.0])
    for _ in range(round(60.0 / DT_S)):
        pack.step(DT_S, "current", load)
    prm = params_of(cfg)
    inp = inputs_from_plant(cfg, pack)
    inp.chg_on[0, 1] = True
    inp.dsg_on[0, 1] = True
    plan = pw.plan_join(prm, inp, 1, float("nan"), load_a=float(load[0]), horizon_s=2.0,
                        n_steps=20)  # fmt: skip
    pack.chg_on[0, 1] = True
    pack.dsg_on[0, 1] = True
    peak = 0.0
    for _ in range(round(2.0 / DT_S)):
        iv = pack.step(DT_S, "current", load)
        x = float(iv.string_a[0, 1])
        peak = x if abs(x) > abs(peak) else peak
    err = (plan.peak_a - peak) / peak if peak != 0 else float("nan")
    ocv_b = float(np.interp(inp.soc[0, 1], prm.ocv_soc, prm.ocv_v))
    dv = prm.series[1] * ocv_b - inp.v1_v[0, 1] - inp.v2_v[0, 1] - plan.bus_v
    return {
        "switch": kind, "dsoc": dsoc, "dv_v": round(float(dv), 3), "r_B_ohm": 0.02 * r_mult,
        "preload_a": float(load[0]),
        "predicted_peak_a": round(plan.peak_a, 2), "plant_peak_a": round(peak, 2),
        "error": round(err, 4),
    }


def join_sweep(series_ohm: tuple[float, ...] = ()) -> list[dict[str, Any]]:
    rows = []
    for kind in ("relay", "mosfet_pair"):
        for dsoc in (-0.3, -0.1, 0.05, 0.2):
            for r_mult in (1.0, 2.0, 4.0):
                for preload in (False, True):
                    rows.append(_join_case(kind, dsoc, r_mult, preload, series_ohm))
    return rows


def _table(rows: list[dict[str, Any]]) -> str:
    cols = list(rows[0])
    out = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    out += ["| " + " | ".join(str(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(out)


def run(series_ohm: tuple[float, ...] = ()) -> dict[str, Any]:
    sop = sop_sweep(series_ohm)
    pre = preload_sweep(series_ohm)
    join = join_sweep(series_ohm)
    ratios = [r["ratio"] for r in sop]
    errors = [abs(r["error"]) for r in join]
    pre_ratio = [r["from_truth_a"] / r["true_a"] for r in pre if r["true_a"] > 0]
    return {
        "sop": sop, "join": join, "pre": pre,
        "pre_truth_crossings": sum(r["truth_crossed"] != "none" for r in pre),
        "pre_core_crossings": sum(r["core_crossed"] != "none" for r in pre),
        "pre_min_ratio": min(pre_ratio), "pre_n": len(pre),
        "sop_crossings": sum(r["crossed"] != "none" for r in sop),
        "sop_min_ratio": min(ratios), "sop_n": len(sop),
        "join_max_error": max(errors), "join_n": len(join),
        "bus_max_over_v": float(np.nanmax([r["bus_pred_v"] - r["bus_plant_v"] for r in sop])),
        "series_ohm": series_ohm,
    }  # fmt: skip


def section(res: dict[str, Any]) -> str:
    now = _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")
    return (
        f"\n## State of power and join planner (issue #28 items 3-4), {now}\n\n"
        f"Command: `python benchmarks/bench_power.py{_series_arg(res)} --append` "
        f"(`make bench`: without series resistance).{_series_note(res)} Plant: "
        "uav_5ah cells, 6S batteries behind MOSFET pairs, default `[limits]` (cut-off 2.7 V, "
        "20 C discharge trip, 60 degC), dt 0.1 s. Predictions from the plant's true state "
        "(`sim/power.py:inputs_from_plant`); published = prediction x (1 - 0.02), the "
        "margin `sim/power.py:MARGIN`; `prediction_a` is the figure before it.\n\n"
        "| figure | measured | target |\n|---|---|---|\n"
        f"| SOP 10 s: predicted limit drawn on the plant, runs crossing a cut-off / current / "
        f"temperature limit | {res['sop_crossings']} of {res['sop_n']} | 0 |\n"
        f"| SOP 10 s: predicted / true limit (bisection on the plant), worst | "
        f"{res['sop_min_ratio']:.3f} | >= 0.90 |\n"
        f"| join planner: predicted vs plant peak current, worst relative error | "
        f"{100 * res['join_max_error']:.1f} % over {res['join_n']} joins | <= 15 % |\n"
        f"| SOP 10 s after 60 s at 60 A, from the plant's truth (polarisation known): "
        f"crossings; worst predicted / true | {res['pre_truth_crossings']} of {res['pre_n']}; "
        f"{res['pre_min_ratio']:.3f} | 0; >= 0.90 |\n"
        f"| SOP 10 s after 60 s at 60 A, from what the core has today (no polarisation "
        f"estimate): crossings | {res['pre_core_crossings']} of {res['pre_n']} | stated "
        f"(the observer's inputs fix it) |\n"
        f"| SOP 10 s: predicted lowest bus voltage (the power's) above the plant's, worst | "
        f"{res['bus_max_over_v']:+.3f} V | <= 0 (stated) |\n\n"
        "State of power, every case:\n\n" + _table(res["sop"]) + "\n\n"
        "After 60 s at 60 A (fresh + aged), every case:\n\n" + _table(res["pre"]) + "\n\n"
        "Join planner, every case:\n\n" + _table(res["join"]) + "\n"
    )


def _series_arg(res: dict[str, Any]) -> str:
    s = res["series_ohm"]
    return f" --series-ohm {','.join(f'{x:g}' for x in s)}" if s else ""


def _series_note(res: dict[str, Any]) -> str:
    s = res["series_ohm"]
    if not s:
        return ""
    return (
        f" Every battery with `series_ohm` {', '.join(f'{1e3 * x:g}' for x in s)} mOhm "
        "(A, B, C; the last repeats) in its branch, outside its cells."
    )


def series_arg(argv: list[str]) -> tuple[float, ...]:
    """``--series-ohm X[,Y...]``: the batteries' series resistances (empty: none)."""
    if "--series-ohm" not in argv:
        return ()
    k = argv.index("--series-ohm")
    return tuple(float(x) for x in argv[k + 1].split(","))


def main() -> int:
    res = run(series_arg(sys.argv[1:]))
    text = section(res)
    print(text)
    if "--append" in sys.argv[1:]:
        with (HERE / "RESULTS.md").open("a") as f:
            f.write(text)
    ok = res["sop_crossings"] == 0 and res["sop_min_ratio"] >= 0.9 and res["join_max_error"] <= 0.15
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
