"""Scheduling: batches of runs on Dask (in-process, threads, a LocalCluster or a cluster).

:func:`choose_scheduler` picks in-process or a process cluster from the estimated work,
:func:`default_batch` sizes the batches, and the runners hand each finished batch's rows to a
callback (the campaign stores them at once).
"""

from __future__ import annotations

import contextlib
import importlib
import logging
import math
import os
import re
import signal
import threading
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from packpilot.campaign.execute import run_batch
from packpilot.campaign.spreads import Draw
from packpilot.config import ScenarioConfig
from packpilot.errors import InputError

BATCH_STEP_COST_S = 8e-6
"""CPU cost of one pack-step of the whole supervised BMS and plant in a batch of 128-256
packs (bench_campaign; used only to choose between in-process and a process cluster)."""
PROCESS_BREAK_EVEN_S = 5.0
"""Estimated single-core work above which ``auto`` picks the process LocalCluster over the
in-process synchronous scheduler. Measured on the 2-core dev box: the cluster costs ~1.5-2.5 s
to start (spawn, imports, numba cache load per worker) and then runs ~1.75x faster; 30 runs of
60 s took 4.9 s on it vs 4.4 s in-process, 100 runs 10.0 s vs 14.6 s. The threaded scheduler
is *slower* than one thread here (30 runs: 9.2 s): the loop is Python holding the GIL between
short GIL-free numba kernels, and two threads mostly trade the GIL back and forth."""

LOCAL_SCHEDULERS = ("auto", "processes", "threads", "sync")
CONNECT_TIMEOUT_S = 10.0
"""How long to wait for an existing Dask scheduler (``--scheduler tcp://...``)."""


QUIET_WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
"""The worker's statistical profiler samples the task thread every 10 ms and competes for the
GIL with a Python-heavy loop: off in our own LocalCluster (measured +5-10 % runs/s)."""


def _check_scheduler(text: str) -> str:
    name = text.strip()
    if name in ("synchronous", "single-threaded"):
        return "sync"
    if name in LOCAL_SCHEDULERS or "://" in name or re.fullmatch(r"[\w.\-]+:\d+", name):
        return name
    raise InputError(
        f"--scheduler {text!r}: expected {', '.join(LOCAL_SCHEDULERS)} or an address"
        " such as tcp://host:8786"
    )


MAX_BATCH = 256
"""Largest batch: at 256 packs the per-step Python overhead of the loop is spread thin; a
bigger batch only loses more work to an interruption and moves the progress bar less often."""


def default_batch(n_runs: int, workers: int) -> int:
    """Enough tasks (~4 per worker) to balance, as many packs per batch as that allows (what
    makes a step cheap), at most ``MAX_BATCH``, and at least 16 (below that the per-step
    overhead dominates)."""
    per_task = math.ceil(n_runs / (4 * max(1, workers)))
    return max(1, min(n_runs, 16), min(MAX_BATCH, per_task))


def _batches(draws: Sequence[Draw], size: int) -> list[list[Draw]]:
    return [list(draws[i : i + size]) for i in range(0, len(draws), size)]


BatchDone = Callable[[list[dict[str, Any]]], None]


def _run_threads(
    cfg: ScenarioConfig,
    batches: list[list[Draw]],
    fail: frozenset[int],
    workers: int,
    done: BatchDone,
    sync: bool = False,
) -> None:
    """Dask's local threaded (or synchronous) scheduler; each batch is stored as it finishes."""
    # dask's public API is untyped for mypy --strict: use it through Any.
    dask: Any = importlib.import_module("dask")
    Callback: Any = importlib.import_module("dask.callbacks").Callback

    keys = {f"campaign-batch-{j}": b for j, b in enumerate(batches)}
    tasks = [
        dask.delayed(run_batch, pure=False)(cfg, b, fail, dask_key_name=k) for k, b in keys.items()
    ]

    def posttask(key: Any, result: Any, dsk: Any, state: Any, worker_id: Any) -> None:
        if isinstance(key, str) and key in keys:
            done(result)

    with Callback(posttask=posttask):
        dask.compute(
            *tasks,
            scheduler="sync" if sync else "threads",
            num_workers=workers,
            optimize_graph=False,
        )


def _run_distributed(
    cfg: ScenarioConfig,
    batches: list[list[Draw]],
    fail: frozenset[int],
    client: Any,
    done: BatchDone,
) -> None:
    as_completed: Any = importlib.import_module("distributed").as_completed

    futures = [client.submit(run_batch, cfg, b, fail, pure=False) for b in batches]
    interrupted = False
    try:
        for fut in as_completed(futures):
            done(fut.result())
            fut.release()  # the rows are on disk; free the worker's copy
    except KeyboardInterrupt:
        interrupted = True  # the cluster is torn down (ours) or the client closed (theirs)
        raise
    finally:
        if not interrupted:
            client.cancel([f for f in futures if not f.done()])


def _is_upstream_cancel_race(record: logging.LogRecord) -> bool:
    """distributed's ``sync`` (2026.8) answers a Ctrl-C by scheduling ``cancel`` on the client's
    loop; when the Ctrl-C lands before its coroutine has assigned ``future``, ``cancel`` raises
    ``NameError: cannot access free variable 'future'`` on the loop thread and tornado logs it,
    traceback and all (CI at e219e17: the campaign's Ctrl-C test saw it before its one
    "interrupted:" line). Nothing is lost: the interrupt is already on its way out of
    ``sync``. Only that record is dropped; any other error on the loop still shows."""
    exc = record.exc_info[1] if record.exc_info else None
    return isinstance(exc, NameError) and "sync.<locals>.cancel" in record.getMessage()


class _DropUpstreamCancelRace(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not _is_upstream_cancel_race(record)


_CANCEL_RACE_FILTER = _DropUpstreamCancelRace()


def quiet_upstream_cancel_race() -> None:
    """Drop distributed's Ctrl-C race record from tornado's log (idempotent: one instance)."""
    logging.getLogger("tornado.application").addFilter(_CANCEL_RACE_FILTER)


@contextmanager
def _client_for(scheduler: str, workers: int) -> Iterator[Any]:
    quiet_upstream_cancel_race()
    dist: Any = importlib.import_module("distributed")
    Client, LocalCluster = dist.Client, dist.LocalCluster
    if scheduler == "processes":
        dask: Any = importlib.import_module("dask")
        with warnings.catch_warnings(), dask.config.set(QUIET_WORKER_CONFIG), _no_sigint():
            # The scheduler's small HTTP server moves off :8787 if taken; nothing to report.
            warnings.filterwarnings("ignore", message="Port .* is already in use")
            cluster = LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address=None,
            )
        client = Client(cluster)
        try:
            yield client
        finally:
            # every result is stored (or, after Ctrl-C, lost with its batch): nothing to wait
            # for. A graceful close waited 4 s for idle workers on a loaded machine and warned
            # "Worker process still alive after 4.0 seconds, killing", twice.
            _close_quietly(client, cluster)
    else:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except OSError as err:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({err})") from None
        try:
            yield client
        finally:
            client.close()


@contextmanager
def _no_sigint() -> Iterator[None]:
    """SIGINT ignored while the cluster spawns its worker processes, so they inherit that: a
    Ctrl-C in the terminal (sent to the whole process group) then reaches only this process,
    which stops the campaign and closes the cluster, instead of every worker dying with its
    own traceback and the nannies warning about it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _close_quietly(client: Any, cluster: Any) -> None:
    """Close our LocalCluster at once: end its worker processes (after Ctrl-C their unfinished
    batches are lost anyway, at the end there are none; killed, they cannot log a cancelled
    task or a lost scheduler), then close the client and the cluster with short timeouts,
    distributed's own logging silenced meanwhile (workers torn down is what was asked for,
    not news)."""
    names = ["distributed"] + [
        n for n in list(logging.root.manager.loggerDict) if n.startswith("distributed.")
    ]
    levels = {n: logging.getLogger(n).level for n in names}
    for n in names:
        logging.getLogger(n).setLevel(logging.CRITICAL + 1)
    try:
        for nanny in list(getattr(cluster, "workers", {}).values()):
            proc = getattr(getattr(nanny, "process", None), "process", None)
            pid = getattr(proc, "pid", None)
            if isinstance(pid, int):
                with contextlib.suppress(OSError):
                    os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(Exception):
            client.close(timeout=1)
        with contextlib.suppress(Exception):
            cluster.close(timeout=1)
    finally:
        for n, level in levels.items():
            logging.getLogger(n).setLevel(level)


def choose_scheduler(cfg: ScenarioConfig, n_runs: int, workers: int) -> str:
    """``auto``: processes when the estimated work pays for the cluster start, else in-process
    (``sync``; threads are slower than that here, see ``PROCESS_BREAK_EVEN_S``)."""
    steps = math.ceil(cfg.sim.duration_s / cfg.sim.dt_s)
    cells = sum(b.n_cells for b in cfg.pack.batteries)
    work_s = n_runs * steps * BATCH_STEP_COST_S * max(1.0, cells / 12.0) ** 0.5
    return "processes" if workers > 1 and work_s > PROCESS_BREAK_EVEN_S else "sync"
