"""Monte-Carlo campaigns: many closed-loop runs of one scenario over parameter spreads, on Dask.

Engineers sizing a pack need the distribution of outcomes over manufacturing spread, wear and
weather, not one run. A campaign draws every run's capacity scale, resistance scale,
initial-SOC offset and ambient temperature from ``(seed, run)`` and runs the scenario's closed
loop with those values applied through the plant's hooks. This module is the entry point
(:func:`run_campaign`, :class:`CampaignReport`); the jobs live in one module each:

- :mod:`~packpilot.campaign.spreads` — spreads, their parsing, and each run's draw;
- :mod:`~packpilot.campaign.execute` — a batch of runs through the closed loop, one row each
  (failures as error rows, the ``PACKPILOT_CAMPAIGN_FAIL_RUNS`` test knob);
- :mod:`~packpilot.campaign.soc_accuracy` — SOC error of the BMS (and of today's estimator)
  against the plant's, per run, when the scenario has ``[soc]`` and ``[sensors]`` (#28);
- :mod:`~packpilot.campaign.store` — Parquet part files, resume and consolidation;
- :mod:`~packpilot.campaign.schedule` — Dask schedulers and batch sizes;
- :mod:`~packpilot.campaign.summary` — percentiles, histograms, JSON and console output.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from packpilot.campaign.execute import (
    FAIL_ENV,
    DeliberateFailure,
    fail_runs_from_env,
    flatten_metrics,
    run_batch,
    run_batch_loop,
    run_one,
    stack_overrides,
    unsupported_reason,
)
from packpilot.campaign.schedule import (
    _batches,
    _check_scheduler,
    _client_for,
    _run_distributed,
    _run_threads,
    choose_scheduler,
    default_batch,
)
from packpilot.campaign.spreads import (
    PARAM_COLUMNS,
    SPREAD_NAMES,
    Draw,
    Spread,
    draw_run,
    make_draws,
    parse_spreads,
)
from packpilot.campaign.store import ID_COLUMNS, META_KEY, ResultStore, campaign_meta
from packpilot.campaign.summary import (
    fail_on_runs,
    plot_histograms,
    print_summary,
    report_to_dict,
    rich_progress,
    summarize,
    verdict_counts,
)
from packpilot.config import ScenarioConfig
from packpilot.errors import InputError

if TYPE_CHECKING:
    import pyarrow as pa


@dataclass
class CampaignReport:
    """What a campaign call did and where its results are."""

    out: Path
    table: pa.Table
    runs: int
    computed: int
    skipped: int
    failures: int
    wall_s: float
    scheduler: str
    workers: int
    batch: int
    summary: list[dict[str, Any]] = field(default_factory=list)
    engine: str = "batch"
    """How the runs were stepped: ``batches of N packs`` through the one loop."""

    @property
    def runs_per_s(self) -> float:
        return self.computed / self.wall_s if self.wall_s > 0 and self.computed else 0.0


def _check_counts(runs: int, seed: int, workers: int | None, batch: int | None) -> None:
    if runs < 1:
        raise InputError(f"--runs must be >= 1 (got {runs})")
    if seed < 0:
        raise InputError(f"--seed must be >= 0 (got {seed})")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be >= 1 (got {workers})")
    if batch is not None and batch < 1:
        raise InputError(f"--batch must be >= 1 (got {batch})")


def _missing_runs(
    store: ResultStore, runs: int, resume: bool, limit: int | None
) -> tuple[list[int], int]:
    """The run indices still to compute (at most ``limit``) and how many are already done;
    without ``resume`` the store starts empty."""
    if resume:
        done_before = store.done_runs()
    else:
        store.clear()
        done_before = set()
    missing = [i for i in range(runs) if i not in done_before]
    skipped = runs - len(missing)
    if limit is not None:
        missing = missing[: max(0, limit)]
    return missing, skipped


def _dispatch(
    cfg: ScenarioConfig,
    sched: str,
    batches: list[list[Draw]],
    fail: frozenset[int],
    n_workers: int,
    client: Any,
    done: Callable[[list[dict[str, Any]]], None],
) -> None:
    """Run ``batches`` on the scheduler ``sched`` names (``client`` when it is ``"client"``)."""
    if sched in ("threads", "sync"):
        _run_threads(cfg, batches, fail, n_workers, done, sched == "sync")
    elif sched == "client":
        _run_distributed(cfg, batches, fail, client, done)
    else:
        with _client_for(sched, n_workers) as cl:
            _run_distributed(cfg, batches, fail, cl, done)


def run_campaign(
    cfg: ScenarioConfig,
    runs: int,
    out: str | Path,
    spreads: str | Mapping[str, Spread] | None = None,
    seed: int = 0,
    scheduler: str | None = None,
    workers: int | None = None,
    batch: int | None = None,
    resume: bool = False,
    limit: int | None = None,
    client: Any = None,
    on_progress: Callable[[int, int], None] | None = None,
    fail_runs: Iterable[int] | None = None,
) -> CampaignReport:
    """Run (or complete, with ``resume``) a campaign of ``runs`` runs and consolidate ``out``.

    ``scheduler``: ``None`` (default: ``DEFAULT_SCHEDULER``), ``"processes"`` (a loopback
    ``LocalCluster`` of ``workers`` single-threaded processes), ``"threads"``, ``"sync"``, or a
    Dask scheduler address (``tcp://host:8786``); or pass a ``distributed.Client`` as
    ``client``. ``limit`` computes at most that many of the missing runs (a partial campaign
    that ``resume`` completes later). ``on_progress(done, total)`` is called after each batch.
    ``fail_runs`` defaults to ``PACKPILOT_CAMPAIGN_FAIL_RUNS``. Every batch steps its runs
    together through the one closed loop (the whole supervised BMS, charger links and fault
    schedules included).
    """
    _check_counts(runs, seed, workers, batch)
    sp = parse_spreads(spreads) if spreads is None or isinstance(spreads, str) else dict(spreads)
    fail = frozenset(fail_runs) if fail_runs is not None else fail_runs_from_env()
    n_workers = workers or os.cpu_count() or 1
    sched = "client" if client is not None else _check_scheduler(scheduler or "auto")

    store = ResultStore(Path(out), campaign_meta(cfg, sp, seed))
    missing, skipped = _missing_runs(store, runs, resume, limit)
    draws = make_draws(sp, seed, missing, cfg.pack.ambient_c)
    why_not = unsupported_reason(cfg)
    if why_not is not None:
        raise InputError(f"campaign: {why_not}; use the virtual interface (the default)")
    if sched == "auto":
        sched = choose_scheduler(cfg, len(draws), n_workers)
    size = batch or default_batch(len(draws), 1 if sched == "sync" else n_workers)
    engine = f"batches of up to {size} packs"
    batches = _batches(draws, size)

    computed = 0

    def done(rows: list[dict[str, Any]]) -> None:
        nonlocal computed
        store.write_part(rows)
        computed += len(rows)
        if on_progress is not None:
            on_progress(computed, len(draws))

    if on_progress is not None:
        on_progress(0, len(draws))
    t0 = time.perf_counter()
    if batches:
        _dispatch(cfg, sched, batches, fail, n_workers, client, done)
    wall = time.perf_counter() - t0
    table = store.consolidate()
    status = table.column("status").to_pylist() if table.num_rows else []
    return CampaignReport(
        out=store.out,
        table=table,
        runs=runs,
        computed=computed,
        skipped=skipped,
        failures=sum(s != "ok" for s in status),
        wall_s=wall,
        scheduler=sched,
        workers=1 if sched == "sync" else n_workers,
        batch=size,
        summary=summarize(table),
        engine=engine,
    )


def kept_runs(out: Path) -> int:
    """How many distinct runs an interrupted campaign left on disk (``out`` and its parts),
    read without the identity check: this only counts them."""
    import pyarrow.parquet as pq

    files = [out] if out.exists() else []
    parts = out.with_name(out.name + ".parts")
    if parts.is_dir():
        files += sorted(parts.glob("part-*.parquet"))
    seen: set[int] = set()
    for f in files:
        try:
            seen.update(int(r) for r in pq.read_table(f, columns=["run"]).column("run").to_pylist())
        except Exception:  # a file being written when Ctrl-C came: not kept
            continue
    return len(seen)


def interrupted_note(out: Path, runs: int) -> str:
    """What Ctrl-C during a campaign leaves, said truthfully: how many finished runs are kept
    (batches are stored whole, so runs of an unfinished batch are lost)."""
    n = kept_runs(out)
    if n == 0:
        return f"interrupted: no batch of runs had finished; nothing kept (of {runs} runs)"
    return (
        f"interrupted: {n} of {runs} runs finished and kept; rerun with --resume --out {out}"
        " to compute the rest"
    )


__all__ = [
    "FAIL_ENV",
    "ID_COLUMNS",
    "META_KEY",
    "PARAM_COLUMNS",
    "SPREAD_NAMES",
    "CampaignReport",
    "DeliberateFailure",
    "Draw",
    "ResultStore",
    "Spread",
    "campaign_meta",
    "choose_scheduler",
    "default_batch",
    "draw_run",
    "fail_on_runs",
    "fail_runs_from_env",
    "flatten_metrics",
    "interrupted_note",
    "kept_runs",
    "make_draws",
    "parse_spreads",
    "plot_histograms",
    "print_summary",
    "report_to_dict",
    "rich_progress",
    "run_batch",
    "run_batch_loop",
    "run_campaign",
    "run_one",
    "stack_overrides",
    "summarize",
    "unsupported_reason",
    "verdict_counts",
]
