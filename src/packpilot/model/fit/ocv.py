"""A correction of the chemistry's default OCV, fitted with the cell to the logs.

Why a correction and not a free curve: a flight log or a cycler record shows the voltage
against the *charge drawn*, never against the state of charge. The state of charge is the charge
drawn over the capacity, so a free OCV curve and the capacity are one unknown (stretch one,
shrink the other: the same voltages). The chemistry's default curve fixes the scale; the data
move it where they see it, by an amount they must pay for:

    OCV(s) = OCV_default(s) + c(s)

``c`` is piecewise linear in SOC with knots every ~:data:`KNOT_SPACING` over the SOC window the
(training) data cover, held at its edge value outside that window (np.interp's rule: the data
say nothing there, so the correction is neither extended nor dropped; the fitted set's notes
say so and a what-if outside the window is flagged). Its parameters are the value at the lowest
knot and one slope per segment, each slope bounded below by ``-(1 - SLOPE_MARGIN)`` times the
default's smallest slope in that segment, so the corrected curve stays increasing whatever the
optimiser does (a bound, not a penalty). It is regularised toward the default: one residual of
the size of the log's noise per :data:`PRIOR_V` of correction at each knot, and per
:data:`CURVATURE_V` of second difference between knots — negligible against thousands of
samples that see the curve, decisive where they do not (the correction then stays near zero and
its knot is flagged not identifiable).

Rest points (relaxed idle: a cycler's rests, a log's idle between flights) need no special
path: through the stepper a relaxed rest is ``V = OCV(s)``, the strongest evidence on the curve
there is, and they are counted in the note. Loaded samples see ``OCV(s) - R I - eta``, which
with R fitted at the same time still sees the curve's shape.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from packpilot.model.fit.profile import F64

KNOT_SPACING = 0.10
"""SOC between the correction's knots (at most :data:`MAX_SEGMENTS` segments)."""
MAX_SEGMENTS = 5
MIN_SHAPE_SWING = 0.05
"""Below this SOC swing the data see no shape: the correction is one offset, flagged."""
PRIOR_V = 0.05
"""Regularisation: one sigma of the correction at a knot (V)."""
CURVATURE_V = 0.02
"""Regularisation: one sigma of the correction's second difference between knots (V)."""
SLOPE_MARGIN = 0.2
"""The corrected curve keeps at least this share of the default's smallest slope."""
MAX_SLOPE_V = 5.0
"""Upper bound of a segment's correction slope (V per unit SOC)."""
UNRESOLVED_SHARE = 0.7
"""A knot whose posterior sigma is above this share of :data:`PRIOR_V` was set by the prior,
not by the data: flagged not identifiable."""


@dataclass(frozen=True)
class OcvShape:
    """Where the correction lives: knots, the default table and the slope bounds."""

    knots: F64
    soc: F64
    base_v: F64
    lo: list[float]
    hi: list[float]

    @property
    def n(self) -> int:
        """Parameters: the value at the first knot, one slope per segment."""
        return len(self.knots)

    def values(self, p: F64) -> F64:
        """The correction at each knot (V) from (value at the first knot, slopes)."""
        out: F64 = p[0] + np.concatenate([[0.0], np.cumsum(p[1:] * np.diff(self.knots))])
        return out

    def table(self, p: F64) -> tuple[F64, F64]:
        """The corrected OCV on the default's SOC grid."""
        c = np.interp(self.soc, self.knots, self.values(p))
        out: F64 = self.base_v + c
        return self.soc, out

    def params_for(self, soc: F64, correction_v: F64) -> F64:
        """The parameters closest to a correction given at other knots (a re-placement)."""
        c = np.interp(self.knots, soc, correction_v)
        p = np.concatenate([[c[0]], np.diff(c) / np.diff(self.knots)])
        out: F64 = np.clip(p, np.array(self.lo) + 1e-9, np.array(self.hi) - 1e-9)
        return out

    def prior(self, p: F64, noise_v: float) -> F64:
        """Regularisation residuals toward the default (see the module)."""
        c = self.values(p)
        curv = np.diff(c, 2) if len(c) > 2 else np.zeros(0)
        rows = [c / PRIOR_V, curv / CURVATURE_V]
        out: F64 = np.concatenate(rows) * noise_v
        return out

    def jacobian(self) -> F64:
        """d(values)/d(parameters): a constant matrix (the values are linear in them)."""
        n = self.n
        a = np.zeros((n, n))
        a[:, 0] = 1.0
        dk = np.diff(self.knots)
        for j in range(1, n):
            a[j:, j] = dk[j - 1]
        return a


def shape(soc_lo: float, soc_hi: float, ocv_soc: F64, ocv_v: F64) -> OcvShape:
    """Knots over the covered window [soc_lo, soc_hi] and the monotonicity bounds."""
    swing = max(soc_hi - soc_lo, 0.0)
    if swing < MIN_SHAPE_SWING:
        knots = np.array([0.5 * (soc_lo + soc_hi)])
    else:
        n_seg = int(min(max(round(swing / KNOT_SPACING), 1), MAX_SEGMENTS))
        knots = np.linspace(soc_lo, soc_hi, n_seg + 1)
    lo, hi = [-0.5], [0.5]
    slope = np.diff(ocv_v) / np.diff(ocv_soc)
    for a, b in itertools.pairwise(knots):
        seg = (ocv_soc[1:] > a) & (ocv_soc[:-1] < b)
        smin = float(slope[seg].min()) if seg.any() else float(np.interp(a, ocv_soc[1:], slope))
        lo.append(-(1.0 - SLOPE_MARGIN) * max(smin, 0.0))
        hi.append(MAX_SLOPE_V)
    return OcvShape(knots, np.asarray(ocv_soc, np.float64), np.asarray(ocv_v, np.float64),
                    lo, hi)  # fmt: skip


@dataclass(frozen=True)
class OcvFit:
    """The fitted correction, as the cell set's notes carry it."""

    knots_soc: list[float]
    correction_v: list[float]
    sigma_v: list[float]
    resolved: list[bool]
    rest_points: int
    flags: list[str]

    @property
    def window(self) -> tuple[float, float]:
        return self.knots_soc[0], self.knots_soc[-1]

    def note(self, chemistry_default: str = "chemistry default") -> str:
        pts = ", ".join(
            f"{1000 * c:+.1f}{'' if ok else '?'} mV at {s:.2f}"
            for s, c, ok in zip(self.knots_soc, self.correction_v, self.resolved, strict=True)
        )
        lo, hi = self.window
        return (
            f"{chemistry_default} corrected from the data over SOC {lo:.2f}..{hi:.2f} "
            f"(piecewise linear, monotone, regularised toward the default; {pts}; "
            f"{self.rest_points} relaxed rest points among the samples); outside that window "
            "the correction is held at its edge value (extrapolated, not fitted)"
        )


def _bound_flags(sh: OcvShape, p: F64) -> list[str]:
    """A correction on a bound: the default's shape is too far from this cell's for a
    regularised correction to reach, and what the correction cannot absorb goes into the
    capacity (flagged with it, see fit.py)."""
    out = []
    for k, (v, lo, hi) in enumerate(zip(p, sh.lo, sh.hi, strict=True)):
        edge = 1e-3 * max(hi - lo, 1e-9)
        if v - lo > edge and hi - v > edge:
            continue
        if k == 0:
            out.append(f"ocv_correction@{sh.knots[0]:.2f}: not identifiable (at its bound, "
                       f"{1000 * v:+.0f} mV)")  # fmt: skip
        else:
            a, b = sh.knots[k - 1], sh.knots[k]
            why = ("the corrected curve as flat as monotonicity allows" if v - lo <= edge
                   else "at the slope bound")  # fmt: skip
            out.append(f"ocv_correction {a:.2f}..{b:.2f}: not identifiable ({why})")
    return out


def summarise(sh: OcvShape, p: F64, cov_p: F64, rest_points: int) -> OcvFit:
    """Values, one-sigma and identifiability per knot from the parameters' covariance."""
    a = sh.jacobian()
    cov = a @ cov_p @ a.T
    sig = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    ok = [bool(s <= UNRESOLVED_SHARE * PRIOR_V) for s in sig]
    flags = []
    if sh.n == 1:
        flags.append(
            "ocv_shape: not identifiable (the data swing the SOC by less than "
            f"{100 * MIN_SHAPE_SWING:.0f} %: one offset fitted, the default's shape kept)"
        )
    flags += _bound_flags(sh, p)
    for s, sd, good in zip(sh.knots, sig, ok, strict=True):
        if not good:
            flags.append(
                f"ocv_correction@{s:.2f}: not identifiable (sigma {1000 * sd:.0f} mV: set by "
                "the regularisation toward the default, not by the data)"
            )
    vals = sh.values(p)
    return OcvFit([float(k) for k in sh.knots], [float(v) for v in vals],
                  [float(x) for x in sig], ok, rest_points, flags)  # fmt: skip


__all__ = ["OcvFit", "OcvShape", "shape", "summarise"]
