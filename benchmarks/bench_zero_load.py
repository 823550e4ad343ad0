"""Issue #28: the zero-load invariant without the comparator, on randomized abrupt load losses.

Each case is a pack of 2-6 parallel 6S batteries of spread age (capacity 0.7-1.0 x 5 Ah,
resistance 1-2 x 18 mOhm, correlated: an aged battery has less capacity and more resistance)
and spread SOC (0.45-1.0 each), behind charge/discharge MOSFET pairs with body diodes and **no
reverse-current comparator**, run by sequencing with the battery observer (``[soc]``) on the
real plant. The pack rests ``REST_S``, holds a constant current of 10-60 A for 1-20 minutes,
and the load then vanishes at once; the run goes on ``AFTER_S``. In every period of the whole
run, the current into each battery is compared with its charge limit (``charge_limit_c`` x its
capacity): the invariant holds when no ratio exceeds 1.

A hold the pack cannot supply is shortened: its charge is capped at 70 % of what the batteries
hold above 15 % SOC (a longer hold would brown the load out, which is a different event; the
cap is reported). Control period 0.5 s (the sequencing property's coarsest, where the -dV/dI
resistance estimate takes in the most polarisation). ``sensors``: the issue's acceptance errors
(cell-voltage noise sigma 5 mV, current gain +1 % and offset +0.2 A).

Each case runs twice: with the observer hook (``[sequencing] zero_load_observer = true``, the
default) and without it (the -dV/dI estimate: the baseline), side by side.

    PYTHONPATH=src python benchmarks/bench_zero_load.py [--cases 500] [--seed0 0] [--sensors]
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, parse_config
from packpilot.control.sequencing.rules import R3_HOLD_S
from packpilot.model import loads
from packpilot.sim.loop import ClosedLoop

DT_S = 0.5
REST_S = 10.0
AFTER_S = 15.0
SEED = 2811
SENSORS = {
    "seed": 28,
    "cell_v": {"noise_sigma": 0.005},
    "current": {"gain": 1.01, "offset": 0.2},
}


@dataclass(frozen=True)
class Case:
    seed: int
    capacity_ah: tuple[float, ...]
    resistance_ohm: tuple[float, ...]
    soc0: tuple[float, ...]
    load_a: float
    hold_s: float
    drawn_hold_s: float
    """The hold as drawn, before the cap on the charge the pack holds."""


def draw(seed: int) -> Case:
    """Case ``seed`` (deterministic: numpy's generator seeded with (SEED, seed))."""
    rng = np.random.default_rng([SEED, seed])
    n = int(rng.integers(2, 7))
    age = rng.uniform(0.0, 1.0, n)
    cap = 5.0 * (1.0 - 0.3 * age) * rng.uniform(0.97, 1.03, n)
    res = 0.018 * (1.0 + age) * rng.uniform(0.9, 1.1, n)
    soc0 = rng.uniform(0.45, 1.0, n)
    amps = float(rng.uniform(10.0, 60.0))
    hold = float(rng.uniform(60.0, 1200.0))
    usable_ah = float(np.sum(cap * np.maximum(soc0 - 0.15, 0.0)))
    cap_s = 0.7 * usable_ah * 3600.0 / amps
    held = max(60.0, min(hold, cap_s))
    rnd = lambda x: tuple(round(float(v), 4) for v in x)  # noqa: E731
    return Case(seed, rnd(cap), rnd(res), rnd(soc0), round(amps, 3), round(held, 1), hold)


def scenario(
    case: Case,
    hook: bool,
    sensors: bool = False,
    open_: bool = True,
    extra: dict[str, Any] | None = None,
) -> ScenarioConfig:
    bats = [
        {
            "name": f"B{k}",
            "series_groups": 6,
            "cells_per_group": 1,
            "soc0": s,
            "capacity_ah": q,
            "resistance_ohm": r,
        }
        for k, (q, r, s) in enumerate(
            zip(case.capacity_ah, case.resistance_ohm, case.soc0, strict=True)
        )
    ]
    data: dict[str, Any] = {
        "pack": {
            "cell": "uav_5ah",
            "switch": {
                "kind": "mosfet_pair",
                "on_ohm": 0.0005,
                "diode_drop_v": 0.6,
                "reverse_comparator": False,
            },
            "batteries": bats,
        },
        "load": {"kind": "current", "value": 1.0, "v_min_v": 15.0},
        "controller": ["sequencing"],
        "sequencing": {"zero_load_observer": hook, "zero_load_open": open_, **(extra or {})},
        "soc": {},
        "sim": {"dt_s": DT_S, "duration_s": duration_s(case), "progress": False},
    }
    if sensors:
        data["sensors"] = SENSORS
    return parse_config(data, f"zero_load_{case.seed}")


def duration_s(case: Case) -> float:
    return REST_S + case.hold_s + AFTER_S


def _loop(case: Case, cfg: ScenarioConfig) -> ClosedLoop:
    """The closed loop of ``cfg`` with the case's load: rest, hold, then nothing."""
    loop = ClosedLoop.of(cfg, 1)
    t_off = REST_S + case.hold_s
    loop.profile = loads.LoadProfile(
        kind="current",
        t_s=np.array([0.0, REST_S, t_off, duration_s(case) + 1.0]),
        value=np.array([0.0, case.load_a, 0.0, 0.0]),
    )
    return loop


class _Exposure:
    """Periods of the hold in which a loss of the load would push more than the charge limit
    into some engaged battery (the observer's prediction, within ~7 %): ``any_s``; of them,
    by a battery R3 closed less than ``R3_HOLD_S`` ago (rule 8b's hold): ``r3_s``; and of
    those, with the observer trusted (rule 8b may act), by one whose diode carried at most
    ``diode_hold_a`` when R3 closed it (rule 8c could hold it on the diode): ``cap_s``, the
    window rule 8b's hold left open before h28look."""

    def __init__(self, n: int, cap_a: float) -> None:
        self.cap_a = cap_a
        self.closure_a = np.full(n, np.nan)
        """What each charge diode carried in the period R3 measured when it closed the FET."""
        self._diode_a = np.zeros(n)
        self.any_s = self.r3_s = self.cap_s = 0.0

    def closures(self, forced_s: np.ndarray, t0: float, diode_a: np.ndarray) -> None:
        self.closure_a = np.where(forced_s == t0, self._diode_a, self.closure_a)
        self._diode_a = diode_a.copy()

    def add(self, t0: float, pred: np.ndarray, forced_s: np.ndarray, trusted: bool) -> None:
        above = pred > 1.0
        in_hold = (t0 - forced_s < R3_HOLD_S) & above
        self.any_s += DT_S if bool(np.any(above)) else 0.0
        self.r3_s += DT_S if bool(np.any(in_hold)) else 0.0
        within = in_hold & (self.closure_a <= self.cap_a) & trusted
        self.cap_s += DT_S if bool(np.any(within)) else 0.0


def run_case(
    case: Case,
    hook: bool,
    sensors: bool = False,
    open_: bool = True,
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The worst ratio of current into a battery to its charge limit over every period of the
    run (and where it happened), with what the controller predicted for it, the charge-FET
    changes per minute of hold, and what the charge diodes carried (seconds, joules, the
    largest power in one period: the cost of rule 8c)."""
    loop = _loop(case, scenario(case, hook, sensors, open_, extra))
    t_off = REST_S + case.hold_s
    slots = {ch.name: s for s, ch, _ in loop.core.status_channels()}
    s_pred, s_risk, s_ok = (
        slots["seq_zero_load_into_a"],
        slots["seq_at_risk"],
        slots["soc_observer_ok"],
    )
    tr = np.array(loop.plant.topology.traction)
    lim = 0.5 * np.array(case.capacity_ah)
    n_steps = round(duration_s(case) / DT_S)
    worst = 0.0
    at: dict[str, Any] = {"t_s": math.nan, "battery": -1}
    pred_before = np.zeros(len(lim))
    risk_before = np.zeros(len(lim), bool)
    ok_before = np.zeros(len(lim), bool)
    unsupplied = False
    at_loss = np.full(len(lim), np.nan)
    r3_forced = np.zeros(len(lim), bool)
    seq = next(x for x in loop.core.compiled if x.method.name == "sequencing")
    s_chg = slots["seq_chg_on"]
    last_chg = None
    changes = 0
    exp = _Exposure(len(lim), float((extra or {}).get("diode_hold_a", 0.0)))
    pack = loop.plant.pack
    diode_w = 0.0
    for k in range(n_steps):
        j0 = pack.chg_diode_j[0, tr].copy()
        t0 = loop.plant.t_s
        rec = loop.step(k, DT_S)
        exp.closures(seq.st.forced_s[0], t0, rec.iv.chg_diode_a[0, tr])
        into = np.maximum(-loop.plant.pack.string_a[0, tr], 0.0) / lim
        first_off = t0 >= t_off - 1e-9 and np.isnan(at_loss[0])
        if first_off:  # the period in which the load vanished
            at_loss = -loop.plant.pack.string_a[0, tr] / lim
            # R3 closed it (its diode carried current) within the hold rule 8b leaves it
            r3_forced = t0 - seq.st.forced_s[0] < R3_HOLD_S
        j = int(np.argmax(into))
        if into[j] > worst:
            worst = float(into[j])
            at = {"t_s": float(t0), "battery": j, "after_loss": bool(t0 >= t_off - 1e-9)}
        if t0 < t_off - 1e-9 or first_off:  # the decision in force when the load vanished
            st = loop.core.status[0]
            pred_before = st[:, s_pred] / lim
            risk_before = st[:, s_risk] > 0.5
            ok_before = st[:, s_ok] > 0.5
        unsupplied = unsupplied or not bool(loop.was_supplied[0])
        diode_w = max(diode_w, float(np.max(pack.chg_diode_j[0, tr] - j0)) / DT_S)
        chg = loop.core.status[0][:, s_chg] > 0.5
        if last_chg is not None and REST_S <= t0 < t_off - 1e-9:
            changes += int(np.sum(chg != last_chg))
            st = loop.core.status[0]
            exp.add(t0, st[:, s_pred] / lim, seq.st.forced_s[0], bool(np.all(st[:, s_ok] > 0.5)))
        last_chg = chg
    j = at["battery"]
    return {
        "seed": case.seed,
        "n": len(lim),
        "load_a": case.load_a,
        "hold_s": case.hold_s,
        "worst": worst,
        **at,
        "predicted": float(pred_before[j]) if j >= 0 else math.nan,
        "flagged": bool(risk_before[j]) if j >= 0 else False,
        "r3_forced": bool(r3_forced[j]) if j >= 0 else False,
        "observer_ok": bool(ok_before.all()),
        "unsupplied": unsupplied,
        "fet_changes_per_min": changes / (case.hold_s / 60.0),
        "exposed_share": exp.any_s / case.hold_s,
        "exposed_r3_share": exp.r3_s / case.hold_s,
        "exposed_cap_share": exp.cap_s / case.hold_s,
        "diode_s": float(np.max(pack.chg_diode_s[0, tr])),
        "diode_j": float(np.max(pack.chg_diode_j[0, tr])),
        "diode_w": diode_w,
        "predicted_all": [float(x) for x in pred_before],
        "at_loss_all": [float(x) for x in at_loss],
    }


VARIANTS: dict[str, tuple[bool, bool, dict[str, Any]]] = {
    "8a+8b+8c": (True, True, {"diode_hold_a": 5.0}),
    "8a+8c": (True, False, {"diode_hold_a": 5.0}),
    "8a+8b": (True, True, {}),
    "8a": (True, False, {}),
    "base": (False, False, {}),
}
"""(zero_load_observer, zero_load_open, other [sequencing] fields) of each column: the
observer's prediction with rule 8b and rule 8c (R3 leaves a battery on its diode, up to
5 A, while closing it would put it above its limit), ..., the -dV/dI prediction (the
baseline)."""
LABELS = {
    "8a+8b+8c": "observer prediction + rule 8b + rule 8c (diode_hold_a = 5)",
    "8a+8c": "observer prediction + rule 8c (diode_hold_a = 5)",
    "8a+8b": "observer prediction + rule 8b (zero_load_open = true)",
    "8a": "observer prediction alone (default)",
    "base": "baseline: -dV/dI (zero_load_observer = false)",
}


def campaign(
    n_cases: int, seed0: int = 0, sensors: bool = False, hooks: tuple[str, ...] = tuple(VARIANTS)
) -> dict[str, list[dict[str, Any]]]:
    out: dict[str, list[dict[str, Any]]] = {h: [] for h in hooks}
    for s in range(seed0, seed0 + n_cases):
        case = draw(s)
        for h in hooks:
            hook, open_, extra = VARIANTS[h]
            out[h].append(run_case(case, hook, sensors, open_, extra))
    return out


def _share(rows: list[dict[str, Any]], key: str) -> str:
    """How many holds have a positive ``key`` share, its median and its largest value."""
    x = [r[key] for r in rows]
    return f"{sum(1 for v in x if v > 0.0)} / {float(np.median(x)):.1%} / {max(x):.1%}"


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    w = np.array([r["worst"] for r in rows])
    bad = [r for r in rows if r["worst"] > 1.0]
    top = max(rows, key=lambda r: r["worst"])
    return {
        "cases": len(rows),
        "worst ratio": float(w.max()),
        "median worst ratio": float(np.median(w)),
        "cases above the limit": len(bad),
        "of them after the loss": sum(1 for r in bad if r.get("after_loss")),
        "of them flagged": sum(1 for r in bad if r["flagged"]),
        "of them R3-forced": sum(1 for r in bad if r["r3_forced"]),
        "charge-FET changes per minute of hold (median / max)": "{:.2f} / {:.2f}".format(
            float(np.median([r["fet_changes_per_min"] for r in rows])),
            max(r["fet_changes_per_min"] for r in rows),
        ),
        "holds exposed (a loss then would exceed; cases / median / max share of the hold)": (
            "{} / {:.1%} / {:.1%}".format(
                sum(1 for r in rows if r["exposed_share"] > 0.0),
                float(np.median([r["exposed_share"] for r in rows])),
                max(r["exposed_share"] for r in rows),
            )
        ),
        "of it within R3_HOLD_S of an R3 closure (cases / median / max share)": _share(
            rows, "exposed_r3_share"
        ),
        "... trusted, diode <= diode_hold_a at that closure (cases / median / max)": _share(
            rows, "exposed_cap_share"
        ),
        "load unsupplied": sum(1 for r in rows if r["unsupplied"]),
        "charge-diode s / J per case (median / max)": "{:.0f} / {:.0f} s, {:.0f} / {:.0f} J".format(
            float(np.median([r["diode_s"] for r in rows])),
            max(r["diode_s"] for r in rows),
            float(np.median([r["diode_j"] for r in rows])),
            max(r["diode_j"] for r in rows),
        ),
        "largest diode power (W)": max(r["diode_w"] for r in rows),
        "worst case": f"seed {top['seed']} (n {top['n']}, {top['load_a']:.1f} A, "
        f"{top['hold_s']:.0f} s): battery {top['battery']} at {top['t_s']:.1f} s, "
        f"predicted {top['predicted']:.2f}",
    }


def run() -> list[dict[str, Any]]:
    """``make bench`` (``run_all.py``): the 500 cases with and without the hook."""
    res = campaign(500)
    return [{"prediction": LABELS[h], **summary(res[h])} for h in res]


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cases", type=int, default=500)
    ap.add_argument("--seed0", type=int, default=0)
    ap.add_argument("--sensors", action="store_true")
    ap.add_argument("--variant", action="append", choices=list(VARIANTS), default=[])
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--hold", type=float, help="diode_hold_a of the 8c variants (A)")
    a = ap.parse_args(argv)
    if a.hold is not None:
        for h, (hook, open_, extra) in list(VARIANTS.items()):
            if "diode_hold_a" in extra:
                VARIANTS[h] = (hook, open_, {**extra, "diode_hold_a": a.hold})
                LABELS[h] = LABELS[h].replace("diode_hold_a = 5", f"diode_hold_a = {a.hold:g}")
    hooks = tuple(a.variant) or tuple(VARIANTS)
    t0 = time.process_time()
    res = campaign(a.cases, a.seed0, a.sensors, hooks)
    cpu = time.process_time() - t0
    if a.verbose:
        for i in range(a.cases):
            line = " | ".join(
                f"{h} {res[h][i]['worst']:.3f}"
                f" b{res[h][i]['battery']} t{res[h][i]['t_s']:.0f}"
                f" p{res[h][i]['predicted']:.2f}{'F' if res[h][i]['flagged'] else ''}"
                f"{'R' if res[h][i]['r3_forced'] else ''}"
                f" fpm{res[h][i]['fet_changes_per_min']:.1f}"
                f" x{100 * res[h][i]['exposed_share']:.0f}%"
                f"/{100 * res[h][i]['exposed_r3_share']:.0f}%"
                f"/{100 * res[h][i]['exposed_cap_share']:.0f}%"
                f" d{res[h][i]['diode_s']:.0f}s/{res[h][i]['diode_j']:.0f}J"
                f"/{res[h][i]['diode_w']:.1f}W"
                for h in hooks
            )
            r = res[hooks[0]][i]
            print(f"seed {r['seed']} n{r['n']} {r['load_a']:.1f} A {r['hold_s']:.0f} s | {line}")
    print("| prediction | " + " | ".join(summary(res[hooks[0]]).keys()) + " |")
    print("|---" * (1 + len(summary(res[hooks[0]]))) + "|")
    for h in hooks:
        s = summary(res[h])
        print(
            f"| {LABELS[h]} | "
            + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in s.values())
            + " |"
        )
    print(f"cases {a.cases}, sensors {a.sensors}, dt {DT_S} s, CPU {cpu:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
