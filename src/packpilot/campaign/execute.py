"""Executing runs: a batch of drawn runs through the one closed loop, one Parquet row each.

The unit of work is :func:`run_batch` (``cfg, draws -> rows``): a task carries several runs so
scheduling overhead stays small, and the batch steps its runs together through the closed loop
(P = len(draws)). A failing run (exception or a non-finite metric) becomes a row with
``status="error"``, its error text and its drawn parameters; it never stops the campaign.

Every ok row carries the run's verdict as ``simulate`` would give it (``verdict``: OK,
WARNING, ALARM, FAULT; ``alarms``: its alarm categories, comma-separated, the names
``--fail-on`` takes; ``overdischarged_at_end``): the event counts give the event alarms, and
:class:`~packpilot.sim.verdict.BatchPhysics` folds the physics checks (over-discharge,
cross-charge, load loss) over the batch step by step, since a campaign keeps no trace.

With ``[soc]`` and ``[sensors]`` a row also carries the run's SOC accuracy (the shown SOC and
today's estimator against the plant's, :mod:`~packpilot.campaign.soc_accuracy`), folded step
by step like the physics checks.

Hidden test knob: the environment variable ``PACKPILOT_CAMPAIGN_FAIL_RUNS="3,7"`` (read by the
process that drives the campaign, then shipped to the workers) makes those run indices raise
at their first control step — a deliberately failing run.
"""

from __future__ import annotations

import logging
import math
import os
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.campaign.soc_accuracy import accuracy_of
from packpilot.campaign.spreads import Draw
from packpilot.config import ScenarioConfig
from packpilot.contract.severity import Severity
from packpilot.errors import InputError
from packpilot.sim.loop import ClosedLoop, n_steps
from packpilot.sim.verdict import BatchPhysics, PhysicsLimits, counted_verdict

_log = logging.getLogger(__name__)

FAIL_ENV = "PACKPILOT_CAMPAIGN_FAIL_RUNS"


class DeliberateFailure(RuntimeError):
    """Raised inside a run listed in PACKPILOT_CAMPAIGN_FAIL_RUNS (tests of failure handling)."""


def flatten_metrics(metrics: Mapping[str, Any]) -> dict[str, Any]:
    """One Parquet cell per value: lists -> ``name_0..``, event counts -> ``events_<Kind>``."""
    flat: dict[str, Any] = {}
    for key, value in metrics.items():
        if key in ("wall_time_s", "battery_names"):
            continue
        if key == "events" and isinstance(value, Mapping):
            for kind, count in sorted(value.items()):
                flat[f"events_{kind}"] = int(count)
        elif isinstance(value, list | tuple):
            for i, x in enumerate(value):
                if isinstance(x, int | float | bool | np.number):
                    flat[f"{key}_{i}"] = float(x) if not isinstance(x, bool | int) else x
        elif isinstance(value, bool | int | float | np.number):
            flat[key] = value.item() if isinstance(value, np.number) else value
    return flat


def _non_finite(flat: Mapping[str, Any]) -> list[str]:
    return [k for k, v in flat.items() if isinstance(v, float) and not math.isfinite(v)]


def _row(
    draw: Draw,
    metrics: Mapping[str, Any],
    wall_s: float,
    physics: tuple[list[tuple[str, Severity]], bool] = ([], False),
) -> dict[str, Any]:
    """A finished run's Parquet row: drawn parameters, status, its verdict (the word, the
    alarm categories, whether it ended over-discharged), flattened metrics."""
    row: dict[str, Any] = asdict(draw)
    flat = flatten_metrics(metrics)
    bad = _non_finite(flat)
    row.update(status="error" if bad else "ok", error=None)
    if bad:
        row["error"] = "non-finite metric(s): " + ", ".join(bad)
    row["wall_time_s"] = wall_s
    alarms, ended_over = physics
    word, cats = counted_verdict(metrics.get("events") or {}, alarms)
    row.update(verdict=word, alarms=",".join(cats), overdischarged_at_end=ended_over)
    row.update(flat)
    return row


def _deliberate_failure(run: int) -> DeliberateFailure:
    return DeliberateFailure(f"deliberate failure of run {run} ({FAIL_ENV})")


def stack_overrides(draws: Sequence[Draw]) -> dict[str, Any]:
    """The draws' plant overrides stacked over the batch, (P,) (``sensor_stream``: (P, 2)):
    one batch, one plant."""
    per = [d.pack_overrides() for d in draws]
    return {k: np.concatenate([np.asarray(o[k]) for o in per]) for k in per[0]}


def unsupported_reason(cfg: ScenarioConfig) -> str | None:
    """Why ``cfg`` cannot run as a campaign (``None``: it can). Only a charger on a real CAN
    interface cannot: a Monte-Carlo batch has no real dock behind each of its packs."""
    if cfg.charger.present and cfg.can is not None and cfg.can.interface != "virtual":
        return f"the charger is on a real CAN interface ({cfg.can.interface})"
    return None


def run_batch_loop(
    cfg: ScenarioConfig, draws: Sequence[Draw], fail_runs: frozenset[int] = frozenset()
) -> list[dict[str, Any]]:
    """The runs of ``draws`` as one batch of the closed loop (P = len(draws)); one row each.

    A run listed in ``fail_runs`` fails at its first step (the failure-handling test knob):
    its row is an error, its pack stops, the others go on. A pack whose metrics turn
    non-finite is an error row too. Raises only for a fault of the batch as a whole.
    """
    t0 = time.perf_counter()
    loop = ClosedLoop.of(cfg, n_packs=len(draws), overrides=stack_overrides(draws))
    failed = np.array([d.run in fail_runs for d in draws], np.bool_)
    loop.metrics.stop(failed)
    names = [b.name for b in cfg.pack.batteries]
    watch = BatchPhysics(
        PhysicsLimits.of_config(cfg.model_dump(mode="json"), names),
        len(draws),
        loop.plant.pack.string_cell_starts,
    )
    acc = accuracy_of(loop)
    dt = cfg.sim.dt_s
    try:
        for k in range(n_steps(cfg)):
            if not loop.running:
                break
            live = loop.metrics.live.copy()  # a pack stopping at this step still counts it
            rec = loop.step(k, dt)
            _watch_step(watch, loop, rec.iv, live)
            if acc is not None:
                acc.feed(live, rec.iv.t_s, dt)
    finally:
        loop.close()
    wall = (time.perf_counter() - t0) / len(draws)
    rows = []
    for p, d in enumerate(draws):
        if failed[p]:
            rows.append(_error_row(d, _deliberate_failure(d.run), wall))
        else:
            rows.append(_row(d, loop.metrics.of(p, wall, names), wall, watch.of(p)))
            if acc is not None:
                rows[-1].update(acc.columns(p))
    return rows


def _watch_step(watch: BatchPhysics, loop: ClosedLoop, iv: Any, live: NDArray[np.bool_]) -> None:
    """Fold the step just taken into the batch's physics checks (the plant's truth)."""
    pack = loop.plant.pack
    soc, _ = pack.cell_states()
    watch.feed(
        live, iv.cell_v, soc, pack.capacity_ah, iv.string_a, iv.load_demand_a, iv.load_a,
        iv.charger_a, loop.cfg.sim.dt_s,
    )  # fmt: skip


def _error_row(draw: Draw, err: BaseException, wall_s: float) -> dict[str, Any]:
    row: dict[str, Any] = asdict(draw)
    row.update(
        status="error", error=f"{type(err).__name__}: {err}".strip()[:2000], wall_time_s=wall_s
    )
    return row


def run_one(cfg: ScenarioConfig, draw: Draw, fail: bool = False) -> dict[str, Any]:
    """One run with drawn parameters -> its Parquet row (a batch of one; never raises)."""
    return run_batch(cfg, [draw], frozenset({draw.run}) if fail else frozenset())[0]


def run_batch(
    cfg: ScenarioConfig,
    draws: Sequence[Draw],
    fail_runs: frozenset[int] = frozenset(),
) -> list[dict[str, Any]]:
    """The unit of work shipped to a worker: several runs as one batch, one row each (in
    ``draws`` order). If the batch raises, its halves are retried (bisection, the same loop),
    so a run that breaks the loop costs only itself: it ends as an error row naming the
    exception, every other run gets its metrics."""
    draws = list(draws)
    if not draws:
        return []
    try:
        return run_batch_loop(cfg, draws, fail_runs)
    except Exception as err:  # a failing run is data, not a crash of the campaign
        if len(draws) == 1:
            return [_error_row(draws[0], err, 0.0)]
        _log.warning(
            "batch of runs %d..%d raised %s: %s; splitting it",
            draws[0].run, draws[-1].run, type(err).__name__, err,
        )  # fmt: skip
        mid = len(draws) // 2
        return run_batch(cfg, draws[:mid], fail_runs) + run_batch(cfg, draws[mid:], fail_runs)


def fail_runs_from_env(env: Mapping[str, str] | None = None) -> frozenset[int]:
    """Run indices that must fail, from ``PACKPILOT_CAMPAIGN_FAIL_RUNS="3,7"``."""
    text = (os.environ if env is None else env).get(FAIL_ENV, "").strip()
    if not text:
        return frozenset()
    try:
        return frozenset(int(t) for t in text.split(",") if t.strip())
    except ValueError:
        raise InputError(f"{FAIL_ENV}={text!r}: expected comma-separated run indices") from None
