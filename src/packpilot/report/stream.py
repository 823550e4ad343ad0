"""Reading a recorded run for its report with memory that does not grow with the run.

A run of up to :data:`~packpilot.report.charts.FULL_RES_MAX` samples is read whole, as before:
its report is the one ``simulate --report`` makes of the same run in memory. A longer run is
read in blocks of whole chart buckets: :class:`~packpilot.report.digest.RunDigest` folds every
figure of the report's tables from each block, :class:`~packpilot.report.digest.Decimator`
keeps the block's bucket extremes and change points, and the block is dropped. What stays is
the digest (fixed size), the kept samples (about ``FULL_RES_MAX``, whatever the run's length)
and the run's events.
"""

from __future__ import annotations

from pathlib import Path

from packpilot.contract.record import Result
from packpilot.io.telemetry.reader import RunTail
from packpilot.report.charts import FULL_RES_MAX
from packpilot.report.digest import Decimator, RunDigest, bucket_size, concat_traces, slice_trace

BLOCK_ROWS = 50_000
"""Samples read per block (rounded down to whole buckets): ~10 MB of arrays for two batteries."""


def read_run(
    path: Path | str,
    run_id: int | None = None,
    full_res_max: int = FULL_RES_MAX,
    block_rows: int = BLOCK_ROWS,
) -> tuple[Result, RunDigest]:
    """The run (a decimated trace when it is longer than ``full_res_max`` samples, with all
    its events and metrics) and the digest of all its samples."""
    tail = RunTail(path, run_id)
    try:
        n_total = tail.count()
        if n_total <= full_res_max:
            result = tail.read().result
            return result, RunDigest.of_result(result, tail.config)
        names = list(tail.names)
        size = bucket_size(n_total, len(names), full_res_max)
        block = size * max(1, block_rows // size)
        digest = RunDigest(names, tail.config, decimated=size)
        decimator = Decimator(size)
        kept, events = [], []
        while True:
            chunk = tail.read(block)
            tr = chunk.result.trace
            digest.feed(tr)
            digest.feed_events(chunk.result.events)
            events.extend(chunk.result.events)
            if len(tr.t_s):
                kept.append(slice_trace(tr, decimator.choose(tr)))
            if len(chunk.steps) < block:
                break
    finally:
        tail.close()
    last = chunk.result
    trace = concat_traces(kept) if kept else last.trace
    result = Result(names, trace, events, last.metrics, run_id=last.run_id,
                    build_time_s=last.build_time_s)  # fmt: skip
    return result, digest


__all__ = ["BLOCK_ROWS", "read_run"]
