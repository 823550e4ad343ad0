"""Monte-Carlo campaigns: many closed-loop runs of one scenario over parameter spreads, on Dask.

Engineers sizing a pack need the distribution of outcomes over manufacturing spread, wear and
weather, not one run. A campaign draws, for every run index ``i``, a capacity scale, a
resistance scale, an initial-SOC offset and an ambient temperature from
``np.random.default_rng([seed, i])`` — so a run's draw depends only on ``(seed, i)``, never on
batching, scheduling or the other runs — and runs the scenario's closed loop with those values
applied through the plant's hooks (``Runner(..., pack_overrides=...)``).

The unit of work is :func:`run_batch` (``cfg, draws -> rows``): a task carries several runs so
scheduling overhead stays small, and a later step can vectorize a batch through the plant in
one NumPy step without touching the scheduling or storage code.

Results go to Parquet, one row per run. Each finished batch is written at once as a part file
in ``<out>.parts/`` (atomic rename), so an interrupted campaign keeps what it computed; the
parts are consolidated into ``<out>`` at the end. ``resume=True`` skips every run index already
recorded (ok or error) and computes only the missing ones. A failing run (exception or a
non-finite metric) becomes a row with ``status="error"``, its error text and its drawn
parameters; it never stops the campaign.

Hidden test knob: the environment variable ``PACKPILOT_CAMPAIGN_FAIL_RUNS="3,7"`` (read by the
process that drives the campaign, then shipped to the workers) makes those run indices raise
at their first control step — a deliberately failing run.
"""

from __future__ import annotations

import hashlib
import importlib
import json
import logging
import math
import os
import re
import time
import uuid
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from packpilot.config import ScenarioConfig
from packpilot.errors import InputError
from packpilot.sim.loop import ClosedLoop, n_steps

if TYPE_CHECKING:
    import pyarrow as pa

_log = logging.getLogger(__name__)

FAIL_ENV = "PACKPILOT_CAMPAIGN_FAIL_RUNS"
META_KEY = b"packpilot.campaign"
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

# Spread name -> Parquet column (= Draw field), and the physical range draws are clipped to.
SPREAD_NAMES: tuple[str, ...] = ("capacity", "r0", "soc0", "ambient_c")
_COLUMN = {
    "capacity": "capacity_scale",
    "r0": "r0_scale",
    "soc0": "soc0_offset",
    "ambient_c": "ambient_c",
}
_LIMITS: dict[str, tuple[float, float]] = {
    "capacity": (0.05, math.inf),
    "r0": (0.05, math.inf),
    "soc0": (-1.0, 1.0),
    "ambient_c": (-60.0, 80.0),
}
PARAM_COLUMNS: tuple[str, ...] = tuple(_COLUMN[n] for n in SPREAD_NAMES)
ID_COLUMNS: tuple[str, ...] = ("run", "seed", *PARAM_COLUMNS, "status", "error", "wall_time_s")


# --------------------------------------------------------------------------------- spreads
@dataclass(frozen=True)
class Spread:
    """How one parameter varies over the campaign.

    ``kind="normal"``: nominal + ``a`` * N(0, 1) (``a`` = sigma in the parameter's unit);
    ``kind="uniform"``: uniform on ``[a, b]``, or on ``[nominal + a, nominal + b]`` when
    ``relative`` (the ``+-X`` form, so ``ambient_c=+-10`` follows the scenario's ambient).
    Draws are clipped to the parameter's physical range (scales >= 0.05, ambient -60..80 degC).
    """

    name: str
    kind: Literal["normal", "uniform"]
    a: float
    b: float = 0.0
    relative: bool = False

    def sample(self, nominal: float, z: float, u: float) -> float:
        """Map one standard-normal ``z`` and one uniform ``u`` to a value (both always drawn)."""
        if self.kind == "normal":
            x = nominal + self.a * z
        else:
            x = (nominal if self.relative else 0.0) + self.a + (self.b - self.a) * u
        lo, hi = _LIMITS[self.name]
        return float(min(max(x, lo), hi))

    def canonical(self) -> str:
        """Exact text identity of the spread (stored in the file so resume can check it)."""
        rel = ":rel" if self.relative else ""
        return f"{self.name}:{self.kind}:{self.a!r}:{self.b!r}{rel}"


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM_RE = re.compile(rf"^({_NUM})(%?)$")


def _number(text: str, token: str) -> float:
    m = _NUM_RE.match(text.strip())
    if m is None:
        raise InputError(f"spread {token!r}: {text.strip()!r} is not a number")
    value = float(m.group(1)) / (100.0 if m.group(2) else 1.0)
    if not math.isfinite(value):
        raise InputError(f"spread {token!r}: value must be finite")
    return value


def parse_spreads(text: str | None) -> dict[str, Spread]:
    """Parse ``capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35`` into spreads by name.

    Forms of the value: ``X%`` or ``X`` — normal with sigma X/100 or X around nominal (for the
    scales ``capacity``/``r0`` the nominal is 1, so ``5%`` = ``0.05``; for ``soc0`` a percentage
    is SOC points; ``ambient_c`` takes degC, not ``%``); ``+-X`` — uniform nominal +- X;
    ``lo:hi`` — uniform on [lo, hi] in absolute terms (scale, SOC offset, degC).
    Raises :class:`InputError` naming the offending token.
    """
    out: dict[str, Spread] = {}
    if text is None or not text.strip():
        return out
    for raw in text.split(","):
        token = raw.strip()
        if not token:
            continue
        if "=" not in token:
            raise InputError(f"spread {token!r}: expected name=value (e.g. capacity=5%)")
        name, value = (s.strip() for s in token.split("=", 1))
        if name not in SPREAD_NAMES:
            raise InputError(
                f"spread {token!r}: unknown parameter {name!r}; allowed: {', '.join(SPREAD_NAMES)}"
            )
        if name in out:
            raise InputError(f"spread {token!r}: {name} is given twice")
        if not value:
            raise InputError(f"spread {token!r}: missing value")
        if name == "ambient_c" and "%" in value:
            raise InputError(
                f"spread {token!r}: ambient_c takes degC (sigma, +-X or lo:hi), not a percentage"
            )
        if ":" in value:
            lo_t, hi_t = value.split(":", 1)
            lo, hi = _number(lo_t, token), _number(hi_t, token)
            if lo > hi:
                raise InputError(f"spread {token!r}: range lo must be <= hi")
            floor, ceil = _LIMITS[name]
            if lo < floor or hi > ceil:
                raise InputError(f"spread {token!r}: range must lie within [{floor:g}, {ceil:g}]")
            out[name] = Spread(name, "uniform", lo, hi)
        elif value.startswith(("+-", "±")):
            half = _number(value.removeprefix("+-").removeprefix("±"), token)
            if half < 0:
                raise InputError(f"spread {token!r}: +- half-width must be >= 0")
            out[name] = Spread(name, "uniform", -half, half, relative=True)
        else:
            sigma = _number(value, token)
            if sigma < 0:
                raise InputError(f"spread {token!r}: sigma must be >= 0")
            out[name] = Spread(name, "normal", sigma)
    return out


def _spreads_canonical(spreads: Mapping[str, Spread]) -> str:
    return ",".join(spreads[n].canonical() for n in SPREAD_NAMES if n in spreads)


# --------------------------------------------------------------------------------- draws
@dataclass(frozen=True)
class Draw:
    """The drawn parameters of one run (what its Parquet row records before the metrics)."""

    run: int
    seed: int
    capacity_scale: float = 1.0
    r0_scale: float = 1.0
    soc0_offset: float = 0.0
    ambient_c: float = 25.0

    def pack_overrides(self) -> dict[str, Any]:
        """Keyword arguments for ``Pack(cfg, 1, ...)``: the plant's campaign hooks."""
        return {
            "capacity_scale": np.array([self.capacity_scale]),
            "r_scale": np.array([self.r0_scale]),
            "soc_offset": np.array([self.soc0_offset]),
            "ambient_c": np.array([self.ambient_c]),
        }


def draw_run(spreads: Mapping[str, Spread], seed: int, run: int, nominal_ambient_c: float) -> Draw:
    """Run ``run``'s parameters: always 4 normals then 4 uniforms from ``default_rng([seed,
    run])``, one pair per parameter in fixed order, so adding a spread never shifts another's
    draws."""
    rng = np.random.default_rng([seed, run])
    z = rng.standard_normal(len(SPREAD_NAMES))
    u = rng.random(len(SPREAD_NAMES))
    values: dict[str, float] = {}
    for k, name in enumerate(SPREAD_NAMES):
        nominal = nominal_ambient_c if name == "ambient_c" else (0.0 if name == "soc0" else 1.0)
        sp = spreads.get(name)
        values[_COLUMN[name]] = nominal if sp is None else sp.sample(nominal, z[k], u[k])
    return Draw(run=run, seed=seed, **values)


def make_draws(
    spreads: Mapping[str, Spread], seed: int, runs: Iterable[int], nominal_ambient_c: float
) -> list[Draw]:
    return [draw_run(spreads, seed, i, nominal_ambient_c) for i in runs]


# --------------------------------------------------------------------------------- one batch
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


def _row(draw: Draw, metrics: Mapping[str, Any], wall_s: float) -> dict[str, Any]:
    """A finished run's Parquet row: drawn parameters, status, flattened metrics."""
    row: dict[str, Any] = asdict(draw)
    flat = flatten_metrics(metrics)
    bad = _non_finite(flat)
    row.update(status="error" if bad else "ok", error=None)
    if bad:
        row["error"] = "non-finite metric(s): " + ", ".join(bad)
    row["wall_time_s"] = wall_s
    row.update(flat)
    return row


def _deliberate_failure(run: int) -> DeliberateFailure:
    return DeliberateFailure(f"deliberate failure of run {run} ({FAIL_ENV})")


def stack_overrides(draws: Sequence[Draw]) -> dict[str, Any]:
    """The draws' plant overrides as (P,) arrays: one batch, one plant."""
    per = [d.pack_overrides() for d in draws]
    return {
        k: np.concatenate([np.asarray(o[k], np.float64).reshape(1) for o in per]) for k in per[0]
    }


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
    dt = cfg.sim.dt_s
    try:
        for k in range(n_steps(cfg)):
            if not loop.running:
                break
            loop.step(k, dt)
    finally:
        loop.close()
    wall = (time.perf_counter() - t0) / len(draws)
    names = [b.name for b in cfg.pack.batteries]
    rows = []
    for p, d in enumerate(draws):
        if failed[p]:
            rows.append(_error_row(d, _deliberate_failure(d.run), wall))
        else:
            rows.append(_row(d, loop.metrics.of(p, wall, names), wall))
    return rows


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


# --------------------------------------------------------------------------------- storage
def _table_from_rows(rows: Sequence[Mapping[str, Any]], meta: Mapping[str, Any]) -> pa.Table:
    import pyarrow as pa

    cols: list[str] = list(ID_COLUMNS)
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    table = pa.Table.from_pylist([{c: r.get(c) for c in cols} for r in rows])
    return table.replace_schema_metadata({META_KEY: json.dumps(meta).encode()})


def _order_columns(names: Sequence[str]) -> list[str]:
    ids = [c for c in ID_COLUMNS if c in names]
    rest = [c for c in names if c not in ID_COLUMNS and not c.startswith("events_")]
    events = sorted(c for c in names if c.startswith("events_"))
    return ids + rest + events


@dataclass
class ResultStore:
    """``<out>`` (consolidated) plus ``<out>.parts/`` (one part file per finished batch)."""

    out: Path
    meta: dict[str, Any]

    @property
    def parts_dir(self) -> Path:
        return self.out.with_name(self.out.name + ".parts")

    def clear(self) -> None:
        """Start afresh (no resume): remove the previous result and its parts."""
        if self.parts_dir.exists():
            for p in self.parts_dir.iterdir():
                p.unlink()
            self.parts_dir.rmdir()
        if self.out.exists():
            self.out.unlink()

    def _files(self) -> list[Path]:
        files = [self.out] if self.out.exists() else []
        if self.parts_dir.exists():
            files += sorted(self.parts_dir.glob("part-*.parquet"))
        return files

    def _check_meta(self, path: Path, table: pa.Table) -> None:
        raw = (table.schema.metadata or {}).get(META_KEY)
        if raw is None:
            raise InputError(f"{path}: not a PackPilot campaign result (no campaign metadata)")
        theirs = json.loads(raw)
        for key in ("seed", "spreads", "config_sha256"):
            if theirs.get(key) != self.meta.get(key):
                raise InputError(
                    f"{path}: cannot resume: it was made with a different {key} "
                    f"({theirs.get(key)!r}, now {self.meta.get(key)!r})"
                )

    def read(self) -> pa.Table | None:
        """Everything recorded so far (final file + parts), one row per run, sorted by run."""
        import pyarrow as pa
        import pyarrow.compute as pc
        import pyarrow.parquet as pq

        tables = []
        for path in self._files():
            try:
                t = pq.read_table(path)
            except (OSError, pa.ArrowInvalid) as err:
                raise InputError(f"{path}: unreadable campaign result ({err})") from None
            self._check_meta(path, t)
            tables.append(t.replace_schema_metadata(None))
        if not tables:
            return None
        table = pa.concat_tables(tables, promote_options="permissive")
        # First occurrence of each run wins (the consolidated file comes first).
        runs = table.column("run").to_numpy()
        _, first = np.unique(runs, return_index=True)
        table = table.take(pa.array(np.sort(first)))
        table = table.take(pc.sort_indices(table, sort_keys=[("run", "ascending")]))
        table = table.select(_order_columns(table.column_names))
        return self._fill_event_counts(table)

    @staticmethod
    def _fill_event_counts(table: pa.Table) -> pa.Table:
        """An ok run without an ``events_X`` column had zero X events (not an unknown count)."""
        import pyarrow as pa
        import pyarrow.compute as pc

        ok = pc.equal(table.column("status"), "ok")
        for i, name in enumerate(table.column_names):
            if name.startswith("events_"):
                col = pc.cast(table.column(name), pa.int64())
                filled = pc.if_else(pc.and_(ok, pc.is_null(col)), 0, col)
                table = table.set_column(i, name, filled)
        return table

    def done_runs(self) -> set[int]:
        table = self.read()
        return set() if table is None else {int(x) for x in table.column("run").to_pylist()}

    def write_part(self, rows: Sequence[Mapping[str, Any]]) -> Path:
        """Write one finished batch atomically (tmp + rename): a crash never leaves half a part."""
        import pyarrow.parquet as pq

        self.parts_dir.mkdir(parents=True, exist_ok=True)
        first = min(int(r["run"]) for r in rows)
        path = self.parts_dir / f"part-{first:08d}-{uuid.uuid4().hex[:8]}.parquet"
        tmp = path.with_suffix(".tmp")
        pq.write_table(_table_from_rows(rows, self.meta), tmp)
        os.replace(tmp, path)
        return path

    def consolidate(self) -> pa.Table:
        """Merge final file + parts into ``out`` (atomic), then drop the parts."""
        import pyarrow.parquet as pq

        table = self.read()
        if table is None:
            table = _table_from_rows([], self.meta)
        table = table.replace_schema_metadata({META_KEY: json.dumps(self.meta).encode()})
        self.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.out.with_name(self.out.name + ".tmp")
        pq.write_table(table, tmp)
        os.replace(tmp, self.out)
        if self.parts_dir.exists():
            for p in self.parts_dir.glob("part-*.parquet"):
                p.unlink()
            for p in self.parts_dir.glob("*.tmp"):
                p.unlink()
            self.parts_dir.rmdir()
        return table


# --------------------------------------------------------------------------------- scheduling
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
    try:
        for fut in as_completed(futures):
            done(fut.result())
            fut.release()  # the rows are on disk; free the worker's copy
    finally:
        client.cancel([f for f in futures if not f.done()])


@contextmanager
def _client_for(scheduler: str, workers: int) -> Iterator[Any]:
    dist: Any = importlib.import_module("distributed")
    Client, LocalCluster = dist.Client, dist.LocalCluster
    if scheduler == "processes":
        dask: Any = importlib.import_module("dask")
        with warnings.catch_warnings(), dask.config.set(QUIET_WORKER_CONFIG):
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
            client.close()
            cluster.close()
    else:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except OSError as err:
            raise InputError(f"--scheduler {scheduler}: cannot connect ({err})") from None
        try:
            yield client
        finally:
            client.close()


def choose_scheduler(cfg: ScenarioConfig, n_runs: int, workers: int) -> str:
    """``auto``: processes when the estimated work pays for the cluster start, else in-process
    (``sync``; threads are slower than that here, see ``PROCESS_BREAK_EVEN_S``)."""
    steps = math.ceil(cfg.sim.duration_s / cfg.sim.dt_s)
    cells = sum(b.n_cells for b in cfg.pack.batteries)
    work_s = n_runs * steps * BATCH_STEP_COST_S * max(1.0, cells / 12.0) ** 0.5
    return "processes" if workers > 1 and work_s > PROCESS_BREAK_EVEN_S else "sync"


# --------------------------------------------------------------------------------- campaign
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


def campaign_meta(cfg: ScenarioConfig, spreads: Mapping[str, Spread], seed: int) -> dict[str, Any]:
    return {
        "version": 1,
        "seed": seed,
        "spreads": _spreads_canonical(spreads),
        "config_sha256": hashlib.sha256(cfg.model_dump_json().encode()).hexdigest(),
        "battery_names": [b.name for b in cfg.pack.batteries],
    }


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
    if runs < 1:
        raise InputError(f"--runs must be >= 1 (got {runs})")
    if seed < 0:
        raise InputError(f"--seed must be >= 0 (got {seed})")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be >= 1 (got {workers})")
    if batch is not None and batch < 1:
        raise InputError(f"--batch must be >= 1 (got {batch})")
    sp = parse_spreads(spreads) if spreads is None or isinstance(spreads, str) else dict(spreads)
    fail = frozenset(fail_runs) if fail_runs is not None else fail_runs_from_env()
    n_workers = workers or os.cpu_count() or 1
    sched = "client" if client is not None else _check_scheduler(scheduler or "auto")

    store = ResultStore(Path(out), campaign_meta(cfg, sp, seed))
    if resume:
        done_before = store.done_runs()
    else:
        store.clear()
        done_before = set()
    missing = [i for i in range(runs) if i not in done_before]
    skipped = runs - len(missing)
    if limit is not None:
        missing = missing[: max(0, limit)]
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
        if sched in ("threads", "sync"):
            _run_threads(cfg, batches, fail, n_workers, done, sched == "sync")
        elif sched == "client":
            _run_distributed(cfg, batches, fail, client, done)
        else:
            with _client_for(sched, n_workers) as cl:
                _run_distributed(cfg, batches, fail, cl, done)
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


# --------------------------------------------------------------------------------- reporting
def _numeric_columns(table: pa.Table) -> list[str]:
    import pyarrow as pa

    skip = {"run", "seed"}
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
    con.print(
        f"failures: {report.failures}   computed: {report.computed}   skipped: {report.skipped}"
    )
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
