"""Validation is part of the fit: fit on the first part of each log, predict the rest, and
compare with what a straight line would have predicted and with the log's own noise.

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

from packpilot.errors import InputError
from packpilot.model.fit.fit import FitResult, fit
from packpilot.model.fit.profile import F64, Profile, noise_floor, predict

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


@dataclass(frozen=True)
class Validation:
    result: FitResult
    checks: list[LogCheck]
    verdict: str
    reasons: list[str]


def _baseline(p: Profile, train: slice) -> F64:
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


def _check(p: Profile, r: FitResult, split: int) -> LogCheck:
    soc0 = r.soc0[p.name].value
    pred, soc = predict(p, r.values, soc0, r.ocv_soc, r.ocv_v)
    base = _baseline(p, slice(0, split))
    test = slice(split, len(p.t_s))
    err = pred[test] - p.voltage_v[test]
    rmse = float(np.sqrt(np.mean(err**2)))
    b_rmse = float(np.sqrt(np.mean((base[test] - p.voltage_v[test]) ** 2)))
    t = p.t_s
    cross = {
        lv: (_first_below(t, p.voltage_v, lv), _first_below(t, pred, lv)) for lv in THRESHOLDS_V
    }
    return LogCheck(
        name=p.name, split_t_s=float(p.t_s[split]), t_s=p.t_s, measured_v=p.voltage_v,
        predicted_v=pred, baseline_v=base, test=test, rmse_v=rmse,
        max_err_v=float(np.max(np.abs(err))), baseline_rmse_v=b_rmse,
        skill=1.0 - rmse / b_rmse if b_rmse > 0 else 0.0, noise_floor_v=noise_floor(p),
        soc_swing=float(np.ptp(soc)), crossings=cross,
    )  # fmt: skip


def fit_and_validate(
    profiles: Sequence[Profile], ocv_soc: F64, ocv_v: F64, *, train_share: float = TRAIN_SHARE,
    max_rc: int = 2, ref_temp_c: float = 25.0, fit_ocv: bool = True,
) -> Validation:  # fmt: skip
    """Fit on the first ``train_share`` of every log, test on the rest."""
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
    checks = [_check(p, result, s) for p, s in zip(profiles, splits, strict=True)]
    verdict, reasons = _verdict(result, checks)
    return Validation(result, checks, verdict, reasons)


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


__all__ = ["LogCheck", "Validation", "fit_and_validate", "noise_floor"]
