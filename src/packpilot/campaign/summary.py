"""Campaign summary: percentiles, histograms, the JSON view, the console table, a progress bar."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from packpilot.campaign.spreads import PARAM_COLUMNS

if TYPE_CHECKING:
    import pyarrow as pa

    from packpilot.campaign import CampaignReport


VERDICT_ORDER = ("OK", "WARNING", "ALARM", "FAULT")


def verdict_counts(table: pa.Table) -> dict[str, Any]:
    """How many ok runs got each verdict, how many had an alarm of each category, and how many
    ended over-discharged: the campaign's answer to "did the runs go well", the same verdict
    ``simulate`` gives one run (``failures`` counts only runs that could not be computed)."""
    out: dict[str, Any] = {"verdicts": dict.fromkeys(VERDICT_ORDER, 0), "categories": {},
                           "overdischarged_at_end": 0}  # fmt: skip
    if table.num_rows == 0 or "verdict" not in table.column_names:
        return out
    status = table.column("status").to_pylist()
    verdicts = table.column("verdict").to_pylist()
    alarms = table.column("alarms").to_pylist()
    ended = table.column("overdischarged_at_end").to_pylist()
    cats: dict[str, int] = {}
    for st, v, a, e in zip(status, verdicts, alarms, ended, strict=True):
        if st != "ok" or v is None:
            continue
        out["verdicts"][v] = out["verdicts"].get(v, 0) + 1
        for c in (a or "").split(","):
            if c:
                cats[c] = cats.get(c, 0) + 1
        out["overdischarged_at_end"] += bool(e)
    out["categories"] = dict(sorted(cats.items(), key=lambda kv: (-kv[1], kv[0])))
    return out


def fail_on_runs(table: pa.Table, categories: list[str]) -> dict[str, int]:
    """For ``campaign --fail-on``: how many ok runs had an alarm of each listed category (only
    the categories some run had)."""
    counts = verdict_counts(table)["categories"]
    return {c: counts[c] for c in categories if counts.get(c)}


def _numeric_columns(table: pa.Table) -> list[str]:
    import pyarrow as pa

    skip = {"run", "seed", "overdischarged_at_end"}
    return [
        f.name
        for f in table.schema
        if f.name not in skip and (pa.types.is_floating(f.type) or pa.types.is_integer(f.type))
    ]


def summarize(table: pa.Table) -> list[dict[str, Any]]:
    """P5 / P50 / P95 of every numeric column over the ok runs (drawn parameters first)."""
    import pyarrow.compute as pc

    if table.num_rows == 0:
        return []
    ok = table.filter(pc.equal(table.column("status"), "ok"))
    rows = []
    for name in _numeric_columns(table):
        x = np.asarray(ok.column(name).to_numpy(zero_copy_only=False), dtype=float)
        x = x[np.isfinite(x)]
        if x.size == 0:
            rows.append({"metric": name, "n": 0, "p5": None, "p50": None, "p95": None})
            continue
        p5, p50, p95 = np.percentile(x, [5, 50, 95])
        rows.append(
            {
                "metric": name,
                "n": int(x.size),
                "p5": float(p5),
                "p50": float(p50),
                "p95": float(p95),
            }
        )
    return rows


def plot_histograms(table: pa.Table, path: str | Path, max_panels: int = 36) -> Path | None:
    """PNG of one histogram per varying numeric column over the ok runs (Agg, no display).

    Drawn parameters are drawn in orange, outcomes in blue; constant columns are left out (a
    single bar says nothing) and counted in the title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow.compute as pc

    if table.num_rows == 0:
        return None
    ok = table.filter(pc.equal(table.column("status"), "ok"))
    series = []
    constant = 0
    for name in _numeric_columns(table):
        x = np.asarray(ok.column(name).to_numpy(zero_copy_only=False), dtype=float)
        x = x[np.isfinite(x)]
        if x.size == 0:
            continue
        if np.ptp(x) <= 1e-9 * max(1.0, float(np.abs(x).max())):
            constant += 1
            continue
        series.append((name, x))
    series = series[:max_panels]
    if not series:
        return None
    ncol = min(4, len(series))
    nrow = math.ceil(len(series) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.4 * ncol, 2.4 * nrow), squeeze=False)
    for ax, (name, x) in zip(axes.ravel(), series, strict=False):
        color = "#d9822b" if name in PARAM_COLUMNS else "#3b6ea5"
        ax.hist(x, bins=min(30, max(5, int(math.sqrt(x.size)))), color=color)
        ax.set_title(name, fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(series) :]:
        ax.set_visible(False)
    failures = table.num_rows - ok.num_rows
    fig.suptitle(
        f"campaign: {ok.num_rows} ok runs, {failures} failed"
        f" ({constant} constant column(s) not shown)",
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0, 1, 0.96))
    p = Path(path)
    fig.savefig(p, dpi=90)
    plt.close(fig)
    return p


def report_to_dict(report: CampaignReport, png: Path | None = None) -> dict[str, Any]:
    """JSON-able view of a report (the CLI's ``--json`` output)."""
    return {
        "out": str(report.out),
        "histograms_png": None if png is None else str(png),
        "runs": report.runs,
        "rows": report.table.num_rows,
        "computed": report.computed,
        "skipped": report.skipped,
        "failures": report.failures,
        "wall_s": report.wall_s,
        "runs_per_s": report.runs_per_s,
        "scheduler": report.scheduler,
        "workers": report.workers,
        "batch": report.batch,
        "engine": report.engine,
        **verdict_counts(report.table),
        "summary": {
            r["metric"]: {k: r[k] for k in ("n", "p5", "p50", "p95")} for r in report.summary
        },
    }


def print_summary(report: CampaignReport, console: Any = None) -> None:
    """Rich table: P5 / P50 / P95 per metric, then the failure count and throughput."""
    from rich.console import Console
    from rich.table import Table

    con = console or Console()
    table = Table(title=f"campaign summary ({report.table.num_rows} runs)")
    table.add_column("metric")
    for col in ("P5", "P50", "P95"):
        table.add_column(col, justify="right")
    for r in report.summary:
        cells = ["-" if r[k] is None else f"{r[k]:.4g}" for k in ("p5", "p50", "p95")]
        table.add_row(r["metric"], *cells)
    con.print(table)
    vc = verdict_counts(report.table)
    con.print(
        "verdicts: " + ", ".join(f"{v} {n}" for v, n in vc["verdicts"].items())
        + f"  (of {sum(vc['verdicts'].values())} computed runs)",
        markup=False, highlight=False,
    )  # fmt: skip
    cats = vc["categories"]
    con.print(
        "alarms: "
        + (", ".join(f"{c} in {n} run(s)" for c, n in cats.items()) if cats else "none"),
        markup=False, highlight=False,
    )  # fmt: skip
    con.print(
        f"over-discharged at the end: {vc['overdischarged_at_end']} run(s)",
        markup=False, highlight=False,
    )  # fmt: skip
    con.print(
        f"failed to compute: {report.failures}   computed: {report.computed}"
        f"   skipped: {report.skipped}",
        markup=False, highlight=False,
    )  # fmt: skip
    con.print(
        f"{report.runs_per_s:.2f} runs/s ({report.scheduler}, {report.workers} worker(s),"
        f" batch {report.batch}, {report.engine})"
    )
    if report.failures:
        import pyarrow.compute as pc

        bad = report.table.filter(pc.not_equal(report.table.column("status"), "ok"))
        pairs = zip(bad["run"].to_pylist(), bad["error"].to_pylist(), strict=True)
        for run, err in list(pairs)[:5]:
            con.print(f"  run {run}: {err}", markup=False, highlight=False, soft_wrap=True)
        if bad.num_rows > 5:
            con.print(f"  ... {bad.num_rows - 5} more failed run(s) in {report.out}")


@contextmanager
def rich_progress(enabled: bool) -> Iterator[Callable[[int, int], None] | None]:
    """A progress bar with runs/s, or ``None`` when disabled (JSON output, not a terminal)."""
    if not enabled:
        yield None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        ProgressColumn,
        Task,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )
    from rich.text import Text

    class RateColumn(ProgressColumn):
        def render(self, task: Task) -> Text:
            elapsed = task.elapsed or 0.0
            rate = task.completed / elapsed if elapsed > 0 else 0.0
            return Text(f"{rate:.2f} runs/s")

    bar = Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        RateColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        transient=True,
    )
    task_id = bar.add_task("campaign", total=None)

    def update(done: int, total: int) -> None:
        bar.update(task_id, completed=done, total=total)

    with bar:
        yield update
