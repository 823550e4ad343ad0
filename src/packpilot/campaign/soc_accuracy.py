"""SOC accuracy of campaign runs (issue #28): the SOC the BMS shows against the plant's, and
today's estimator beside it, folded step by step over a batch (a campaign keeps no trace).

Why in the campaign: the acceptance of the battery observer is a distribution — SOC error
<= 2 % RMS after the first 5 minutes and <= 3 % max over runs with spread capacity, resistance,
initial SOC and ambient, under sensor errors — and one run says nothing about the spread.

Definitions, per run and traction battery, over the steps at or after ``SETTLE_S`` (the
period's start time ``t_s``, as the trace stamps it) while the run is live:

- truth: the plant's SOC of the battery, its weakest cell's remaining charge over the weakest
  cell's full charge (:func:`~packpilot.sim.sensors.true_soc`, the trace's ``soc`` channel),
  at the end of the step, clipped to [0, 1]: a battery that nothing protects can be run past
  empty (the plant's SOC goes below 0), and 0 % is then what any SOC display, and both
  estimators, show; the time the truth spent outside is its own column;
- the observer's error: the SOC the BMS shows at that step (``shown_soc``, status
  ``soc_est``: the observer while it is healthy, else its fallback) minus the truth;
- today's error: the coulomb counter with OCV after a rest (``soc``, status ``soc_fallback``,
  the estimator before #28, run beside the observer on the same readings) minus the truth;
- RMS and maximum of |error| over those steps; a step where an estimate is NaN (a battery not
  yet reported) is left out; no step left: null (not measured), never a made-up 0.

The truth at the end of the step against the estimate made at its start is the trace's own
pairing (one row); the lag is one step's charge, I dt / (3600 Q): 0.02 % of SOC at 30 A,
0.1 s, 5 Ah.

Columns (per battery ``_i``, and the worst battery without suffix): ``soc_err_rms``,
``soc_err_max``, ``soc_err_old_rms``, ``soc_err_old_max``; ``soc_fallback_s`` (seconds after
``SETTLE_S`` that the shown SOC came from the fallback, the observer not trusted),
``soc_truth_outside_s`` (seconds after ``SETTLE_S`` that the plant's SOC was below 0 or above 1)
and ``soc_err_steps`` (steps judged); ``_s`` columns: the run's worst battery.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.sim.loop import ClosedLoop
from packpilot.sim.sensors import soc_state, true_soc

SETTLE_S = 300.0
"""The acceptance's "after the first 5 minutes" (the wrong start is forgiven until then)."""
EPS_S = 1e-6
"""Slack on a step's start time: ``t_s`` is a running sum of ``dt_s`` (300 s is 299.99999...)."""

Array = NDArray[np.float64]


def judged(cfg: ScenarioConfig) -> bool:
    """A campaign measures SOC accuracy when the scenario has an estimator to judge (``[soc]``)
    and says what its sensors read (``[sensors]``: estimates are judged against what a real BMS
    reads, issue #28); without ``[sensors]`` the columns are absent, as before."""
    return cfg.soc is not None and cfg.sensors is not None


def accuracy_of(loop: ClosedLoop) -> SocAccuracy | None:
    """The accumulator for ``loop``'s batch, or None when its scenario is not judged."""
    if not judged(loop.cfg) or soc_state(loop.core) is None:
        return None
    return SocAccuracy(loop)


class SocAccuracy:
    """Squared-error sums, maxima and counts per (pack, battery), for the observer (``new``)
    and today's estimator (``old``)."""

    def __init__(self, loop: ClosedLoop, settle_s: float = SETTLE_S) -> None:
        self.loop = loop
        self.st = soc_state(loop.core)
        if self.st is None:
            raise ValueError("SOC accuracy needs the [soc] estimator in the core")
        self.settle_s = settle_s
        shape = self.st.soc.shape
        self.traction = loop.plant.traction
        self.sum2 = {k: np.zeros(shape) for k in ("new", "old")}
        self.peak = {k: np.zeros(shape) for k in ("new", "old")}
        self.n = {k: np.zeros(shape, np.int64) for k in ("new", "old")}
        self.fallback_s = np.zeros(shape)
        self.outside_s = np.zeros(shape)

    def feed(self, live: NDArray[np.bool_], t_s: float, dt_s: float) -> None:
        """Fold the step just taken (period start ``t_s``) for the packs ``live`` at its start."""
        if t_s < self.settle_s - EPS_S:
            return
        raw = true_soc(self.loop.plant.pack, self.traction)
        truth = np.clip(raw, 0.0, 1.0)  # past empty (or full) is 0 % (100 %) for any display
        rows = live[:, None]
        self.outside_s += np.where(rows & ((raw < 0.0) | (raw > 1.0)), dt_s, 0.0)
        for key, est in (("new", self.st.shown_soc), ("old", self.st.soc)):
            err = np.abs(est - truth)
            ok = rows & np.isfinite(err)
            e = np.where(ok, err, 0.0)
            self.sum2[key] += e * e
            np.maximum(self.peak[key], e, out=self.peak[key])
            self.n[key] += ok
        self.fallback_s += np.where(rows & ~self.st.obs_ok, dt_s, 0.0)

    def columns(self, p: int) -> dict[str, Any]:
        """Pack ``p``'s SOC columns (see the module doc); null where nothing was judged."""
        out: dict[str, Any] = {}
        worst: dict[str, float | None] = {}
        for key, tag in (("new", ""), ("old", "_old")):
            n = self.n[key][p]
            rms = [
                math.sqrt(s / k) if k else None for s, k in zip(self.sum2[key][p], n, strict=True)
            ]
            mx = [float(m) if k else None for m, k in zip(self.peak[key][p], n, strict=True)]
            for name, vals in ((f"soc_err{tag}_rms", rms), (f"soc_err{tag}_max", mx)):
                for i, v in enumerate(vals):
                    out[f"{name}_{i}"] = v
                got = [v for v in vals if v is not None]
                worst[name] = max(got) if got else None
        out.update(worst)
        out["soc_fallback_s"] = float(self.fallback_s[p].max())
        out["soc_truth_outside_s"] = float(self.outside_s[p].max())
        out["soc_err_steps"] = int(self.n["new"][p].min())
        return out


__all__ = ["EPS_S", "SETTLE_S", "SocAccuracy", "accuracy_of", "judged"]
