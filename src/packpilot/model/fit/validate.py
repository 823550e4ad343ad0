"""Validation is part of the fit: fit on the first part of each log, predict the rest, and
compare with what a straight line would have predicted and with the log's own noise.

Two ways to hold data out (``mode``):

- ``time`` (the default): the first :data:`TRAIN_SHARE` of each log's samples train, the rest
  tests. On a discharge this always tests *extrapolation*: the held-out part lies below the
  training part's state-of-charge window (the dronekit tlog: 1,116 of 1,148 held-out samples);
- ``flights``: leave one flight out. The logs are split into flights
  (:func:`packpilot.model.fit.profile.flights`: load separated by rests); with at least
  :data:`MIN_FLIGHTS` in all, each flight in turn is left out of the fit *by mask* — it stays in
  its profile, so the state of charge (charge counter or integrated current) and the RC branches
  run through it and the next flight starts from the right state; only its voltages are not
  fitted — and predicted by the fit of the others. A flight is *interior* when its log's
  training samples bracket its charge drawn (so its state-of-charge window lies inside theirs:
  SOC = SOC0 - Ah / Q on one log); the verdict judges the interior flights only. A log's last
  flight is extrapolation again (nothing below it is fitted) and is reported but not judged;
  the first flight is interior when the log starts at rest (the rest, never held out, tells the
  OCV above it). The cell set itself is fitted on every flight.

- **noise floor**: the voltage's sample-to-sample scatter where the current barely moves
  (robust: 1.4826 x the median absolute first difference / sqrt 2) — no model can beat it;
- **baseline**: ``V = a - b Ah - R I`` by linear least squares on the same training part; the
  model's *skill* is ``1 - RMSE_model / RMSE_line`` on the held-out part;
- **time to 3.5 V and 3.3 V per cell**: the first time the voltage, as a moving median over
  :data:`SUSTAIN_S` (a pulse's dip is not the pack reaching a level), is at or below each level,
  measured against predicted, over the whole log (a level reached before the split was reached
  while fitting: the held-out check is the one after it);
- **verdict**: ``refused`` when the held-out part cannot judge the model (too few samples, no
  current swing); ``low confidence`` when the held-out RMSE is above twice the noise floor or
  above 50 mV, the skill is not positive, or the capacity is not identifiable; else ``usable``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from packpilot.errors import InputError
from packpilot.model.fit.fit import FitResult, fit
from packpilot.model.fit.profile import (
    F64,
    REST_GAP_S,
    Profile,
    flights,
    noise_floor,
    predict,
)  # fmt: skip

MODES = ("time", "flights")
MIN_FLIGHTS = 3
"""Leave one flight out needs at least one flight with a trained flight on either side."""
TRAIN_SHARE = 0.6
"""The first 60 % of each log's samples train the model; the rest tests it."""
MIN_TEST_SAMPLES = 10
MAX_RMSE_V = 0.050
NOISE_FACTOR = 2.0
THRESHOLDS_V = (3.5, 3.3)
SUSTAIN_S = 10.0
"""Moving-median window for the time to a voltage level."""


@dataclass(frozen=True)
class LogCheck:
    """How one log's held-out part was predicted."""

    name: str
    split_t_s: float
    t_s: F64
    measured_v: F64
    predicted_v: F64
    baseline_v: F64
    test: slice
    rmse_v: float
    max_err_v: float
    baseline_rmse_v: float
    skill: float
    noise_floor_v: float
    soc_swing: float
    crossings: dict[float, tuple[float | None, float | None]]
    """threshold -> (measured, predicted) first time at or below it in the held-out part."""
    interior: bool = True
    """The held-out part's SOC window lies inside the training one (always False for the time
    split of a discharge; leave one flight out: see the module)."""


@dataclass(frozen=True)
class Validation:
    result: FitResult
    checks: list[LogCheck]
    verdict: str
    reasons: list[str]
    mode: str = "time"


def _baseline(p: Profile, train: slice | NDArray[np.bool_]) -> F64:
    ah = p.drawn_ah
    a = np.column_stack([np.ones_like(ah), -ah, -p.current_a])
    coef, *_ = np.linalg.lstsq(a[train], p.voltage_v[train], rcond=None)
    out: F64 = a @ coef
    return out


def _sustained(t: F64, v: F64) -> F64:
    """The moving median of v over the SUSTAIN_S before each sample."""
    lo = np.searchsorted(t, t - SUSTAIN_S, side="left")
    return np.array([np.median(v[a : k + 1]) for k, a in enumerate(lo)])


def _first_below(t: F64, v: F64, level: float) -> float | None:
    hit = np.flatnonzero(_sustained(t, v) <= level)
    return float(t[hit[0]]) if hit.size else None


def _check(p: Profile, r: FitResult, test: slice, name: str = "", interior: bool = False
           ) -> LogCheck:  # fmt: skip
    """How ``p``'s samples ``test`` (left out of the fit ``r``) are predicted; the straight
    line is fitted to the samples the model was fitted to."""
    soc0 = r.soc0[p.name].value
    pred, soc = predict(p, r.values, soc0, r.ocv_soc, r.ocv_v)
    train = p.fitted.copy()
    train[test] = False
    base = _baseline(p, train)
    err = pred[test] - p.voltage_v[test]
    rmse = float(np.sqrt(np.mean(err**2)))
    b_rmse = float(np.sqrt(np.mean((base[test] - p.voltage_v[test]) ** 2)))
    t = p.t_s
    cross = {
        lv: (_first_below(t, p.voltage_v, lv), _first_below(t, pred, lv)) for lv in THRESHOLDS_V
    }
    return LogCheck(
        name=name or p.name, split_t_s=float(p.t_s[test.start]), t_s=p.t_s,
        measured_v=p.voltage_v,
        predicted_v=pred, baseline_v=base, test=test, rmse_v=rmse,
        max_err_v=float(np.max(np.abs(err))), baseline_rmse_v=b_rmse,
        skill=1.0 - rmse / b_rmse if b_rmse > 0 else 0.0, noise_floor_v=noise_floor(p),
        soc_swing=float(np.ptp(soc)), crossings=cross, interior=interior,
    )  # fmt: skip


def fit_and_validate(
    profiles: Sequence[Profile], ocv_soc: F64, ocv_v: F64, *, train_share: float = TRAIN_SHARE,
    max_rc: int = 2, ref_temp_c: float = 25.0, fit_ocv: bool = True, mode: str = "time",
) -> Validation:  # fmt: skip
    """Fit on the first ``train_share`` of every log, test on the rest (``mode="time"``), or
    leave one flight out (``mode="flights"``, see the module)."""
    if mode not in MODES:
        raise InputError(f"fit: --validate {mode}: must be one of {', '.join(MODES)}")
    if mode == "flights":
        return _leave_one_flight_out(profiles, ocv_soc, ocv_v, max_rc=max_rc,
                                     ref_temp_c=ref_temp_c, fit_ocv=fit_ocv)  # fmt: skip
    if not 0.2 <= train_share <= 0.9:
        raise InputError(f"fit: train share {train_share}: must be 0.2..0.9")
    splits = [int(len(p.t_s) * train_share) for p in profiles]
    for p, s in zip(profiles, splits, strict=True):
        if len(p.t_s) - s < MIN_TEST_SAMPLES:
            raise InputError(
                f"fit: {p.name}: {len(p.t_s)} samples leave {len(p.t_s) - s} to test on "
                f"(at least {MIN_TEST_SAMPLES}); the log is too short to validate a fit"
            )
    train = [p.window(0, s) for p, s in zip(profiles, splits, strict=True)]
    result = fit(train, ocv_soc, ocv_v, max_rc=max_rc, ref_temp_c=ref_temp_c, fit_ocv=fit_ocv)
    checks = [_check(p, result, slice(s, len(p.t_s)))
              for p, s in zip(profiles, splits, strict=True)]  # fmt: skip
    verdict, reasons = _verdict(result, checks)
    return Validation(result, checks, verdict, reasons)


def _interior(p: Profile, lo: int, hi: int) -> bool:
    """The log's training samples bracket the charge drawn over samples ``lo:hi`` (its SOC
    window, SOC = SOC0 - Ah / Q, lies inside theirs)."""
    ah = p.drawn_ah
    train = p.fitted.copy()
    train[lo:hi] = False
    if not train.any():
        return False
    return bool(ah[train].min() <= ah[lo:hi].min() and ah[lo:hi].max() <= ah[train].max())


def _leave_one_flight_out(
    profiles: Sequence[Profile], ocv_soc: F64, ocv_v: F64, *, max_rc: int, ref_temp_c: float,
    fit_ocv: bool,
) -> Validation:  # fmt: skip
    """Each flight left out of one fit (by mask) and predicted by it; the verdict from the
    interior ones; the cell set fitted on every flight."""
    pieces = [(j, k, lo, hi) for j, p in enumerate(profiles)
              for k, (lo, hi) in enumerate(flights(p))]  # fmt: skip
    if len(pieces) < MIN_FLIGHTS:
        per_log = ", ".join(f"{p.name}: {sum(1 for x in pieces if x[0] == j)}"
                            for j, p in enumerate(profiles))  # fmt: skip
        raise InputError(
            f"fit: --validate flights needs at least {MIN_FLIGHTS} flights (load separated by "
            f"rests of at least {REST_GAP_S:g} s) in the logs given; found {len(pieces)} "
            f"({per_log}): give more logs or use --validate time"
        )
    checks = []
    for j, k, lo, hi in pieces:
        p = profiles[j]
        if hi - lo < MIN_TEST_SAMPLES or np.count_nonzero(p.fitted[:lo]) + np.count_nonzero(
            p.fitted[hi:]
        ) < MIN_TEST_SAMPLES:
            continue  # too short to judge, or nothing of its log left to set its initial SOC
        held = [q.holding_out(lo, hi) if i == j else q for i, q in enumerate(profiles)]
        r = fit(held, ocv_soc, ocv_v, max_rc=max_rc, ref_temp_c=ref_temp_c, fit_ocv=fit_ocv)
        checks.append(_check(held[j], r, slice(lo, hi), f"{p.name} flight {k + 1}",
                             _interior(p, lo, hi)))  # fmt: skip
    inner = [c for c in checks if c.interior]
    if not inner:
        raise InputError(
            f"fit: --validate flights: none of the {len(pieces)} flights lies inside the "
            "others' state-of-charge window (each would test extrapolation): use --validate time"
        )
    result = fit(profiles, ocv_soc, ocv_v, max_rc=max_rc, ref_temp_c=ref_temp_c,
                 fit_ocv=fit_ocv)  # fmt: skip
    verdict, reasons = _verdict(result, inner)
    outer = [c.name for c in checks if not c.interior]
    if outer:
        reasons.append(
            f"not judged (extrapolation: their SOC window leaves the other flights'): "
            f"{', '.join(outer)}"
        )
    return Validation(result, checks, verdict, reasons, mode="flights")


def _verdict(r: FitResult, checks: Sequence[LogCheck]) -> tuple[str, list[str]]:
    refused: list[str] = []
    low: list[str] = []
    for c in checks:
        i_test = np.ptp(c.measured_v[c.test]) if c.test.stop > c.test.start else 0.0
        if i_test <= 2.0 * c.noise_floor_v:
            refused.append(
                f"{c.name}: the held-out voltage moves {1000 * i_test:.1f} mV, within twice the "
                f"noise floor ({1000 * c.noise_floor_v:.1f} mV): nothing to judge the model on"
            )
            continue
        if c.rmse_v > NOISE_FACTOR * max(c.noise_floor_v, 1e-4):
            low.append(
                f"{c.name}: held-out RMSE {1000 * c.rmse_v:.1f} mV > {NOISE_FACTOR:g} x the "
                f"noise floor {1000 * c.noise_floor_v:.1f} mV"
            )
        if c.rmse_v > MAX_RMSE_V:
            low.append(f"{c.name}: held-out RMSE {1000 * c.rmse_v:.1f} mV > 50 mV per cell")
        if c.skill <= 0.0:
            low.append(
                f"{c.name}: no better than a straight line (skill {c.skill:+.2f}: RMSE "
                f"{1000 * c.rmse_v:.1f} vs {1000 * c.baseline_rmse_v:.1f} mV)"
            )
    low += [f for f in r.flags() if f.startswith(("capacity_ah", "r0_ohm"))]
    if refused and len(refused) == len(checks):
        return "refused", refused
    if refused or low:
        return "low confidence", refused + low
    return "usable", [
        f"held-out RMSE within {NOISE_FACTOR:g} x the noise floor and 50 mV, better than a "
        "straight line, capacity and R0 identified"
    ]


__all__ = ["MODES", "LogCheck", "Validation", "fit_and_validate", "noise_floor"]
