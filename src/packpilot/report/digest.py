"""A run's report figures in one pass over its samples, and a decimated trace for the charts.

The report's tables (verdict, KPIs, per-battery figures, switch counts) are exact aggregates:
first and last values, extremes, time-weighted sums, change counts. :class:`RunDigest` folds
them block by block, so a recorded run of any length is read with memory that does not grow
with it (issue #26 §3: ``packpilot report`` of a 7-day run needed 8.2 GB when it held the whole
trace). A run in memory is one block (:meth:`RunDigest.of_result`), so both paths compute
every figure with the same code.

:class:`Decimator` chooses the samples the charts keep while the blocks go by: the minimum and
the maximum of each bucket of :func:`bucket_size` samples of every battery channel, the bus
and the load (so a peak or a cut-off is never lost), the first NaN of a bucket (a gap stays a
gap), and every switch, body-diode and status change up to :data:`CHANGES_PER_BUCKET` per
bucket, all series together (beyond it, shared out rarest series first and thinned evenly), so
the kept samples are at most a fixed number per bucket and the buckets a fixed number. Buckets
start at multiples of their size and blocks hold whole buckets, so the choice does not depend on
how the run was cut into blocks.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
from packpilot.contract.record import BATTERY_CHANNELS, Result, Trace
from packpilot.sim.verdict import RunWatch, Verdict

F64 = NDArray[np.float64]
MINMAX_KEYS: tuple[str, ...] = ("voltage_v", "current_a", "min_cell_v", "max_cell_v", "soc",
                                "temp_c")  # fmt: skip
"""Battery channels whose bucket extremes the charts keep (as ``charts.sample_indices``)."""
CHANGES_PER_BUCKET = 16
"""Switch, diode and status change points a chart bucket keeps at most, all series together
(shared out rarest series first)."""
_DT_VALUES_MAX = 4096
"""Distinct step lengths counted exactly for the median; beyond, they are rounded."""


def bucket_size(n_samples: int, n_batteries: int, full_res_max: int) -> int:
    """Samples per bucket so that the kept extremes of every channel total about
    ``full_res_max`` points (the budget ``charts.sample_indices`` gives an in-memory run),
    at least 100 buckets."""
    budget = max(200, full_res_max // (len(MINMAX_KEYS) * max(n_batteries, 1)))
    n_buckets = max(1, (budget - 2) // 2)
    return max(1, -(-n_samples // n_buckets))


def _bucket_extremes(y: F64, size: int) -> list[NDArray[np.intp]]:
    """Per bucket of ``size`` samples (the last may be short): its min, its max, its first NaN."""
    n = len(y)
    n_buckets = -(-n // size)
    pad = n_buckets * size - n
    nan = np.isnan(y)
    lo = np.concatenate([np.where(nan, np.inf, y), np.full(pad, np.inf)]).reshape(n_buckets, size)
    hi = np.concatenate([np.where(nan, -np.inf, y), np.full(pad, -np.inf)])
    hi = hi.reshape(n_buckets, size)
    base = np.arange(n_buckets, dtype=np.intp) * size
    out = [base + np.argmin(lo, axis=1), base + np.argmax(hi, axis=1)]
    if nan.any():
        nb = np.concatenate([nan, np.zeros(pad, dtype=bool)]).reshape(n_buckets, size)
        out.append((base + np.argmax(nb, axis=1))[nb.any(axis=1)])
    return out


def _capped(changes: NDArray[np.intp], cap: int) -> NDArray[np.intp]:
    """At most ``cap`` change points, evenly thinned when there are more."""
    if len(changes) <= cap:
        return changes
    pick = np.linspace(0, len(changes) - 1, cap).round().astype(np.intp)
    return changes[pick]


def _fair_share(series: list[NDArray[np.intp]], budget: int) -> list[NDArray[np.intp]]:
    """Change points of several series within ``budget`` in all: the rarest series first and
    in full (a one-off trip flag is never crowded out by a chattering one), the rest thinned
    evenly to an equal share of what is left."""
    out: list[NDArray[np.intp]] = []
    left = budget
    order = sorted(range(len(series)), key=lambda j: len(series[j]))
    for i, j in enumerate(order):
        share = left // (len(order) - i)
        out.append(_capped(series[j], share))
        left -= len(out[-1])
    return out


def _float_changes(x: F64) -> NDArray[np.intp]:
    """Rows (after the first) whose value differs from the row before (NaN to NaN: unchanged)."""
    a, b = x[1:], x[:-1]
    return np.flatnonzero((a != b) & ~(np.isnan(a) & np.isnan(b))) + 1


def _status_changes(seqs: Sequence[Sequence[StatusValue]]) -> list[int]:
    """Rows of a status channel (aligned on its own start) whose tuple differs from the last."""
    out: list[int] = []
    prev: Any = None
    for i, s in enumerate(seqs):
        if s is prev:  # forward-filled rows repeat the very same tuple
            continue
        if prev is not None and tuple(s) != tuple(prev):
            out.append(i)
        prev = s
    return out


@dataclass
class Decimator:
    """The samples of a run the charts keep, chosen block by block (see the module doc)."""

    size: int
    """Samples per bucket."""
    change_cap: int = CHANGES_PER_BUCKET
    """Change points kept per bucket at most, all series together."""
    kept: int = 0
    """Samples chosen so far."""

    def choose(self, tr: Trace) -> NDArray[np.intp]:
        """Indices into block ``tr`` of the samples to keep; the block starts at a multiple of
        :attr:`size` of the run's samples (blocks hold whole buckets, the last one excepted)."""
        n = len(tr.t_s)
        if n == 0:
            return np.zeros(0, dtype=np.intp)
        parts: list[NDArray[np.intp]] = [np.array([0, n - 1], dtype=np.intp)]
        for key in MINMAX_KEYS:
            col = tr.channel(key)
            for b in range(col.shape[1]):
                parts += _bucket_extremes(col[:, b], self.size)
        for pack in (tr.bus_v, tr.load_a):
            parts += _bucket_extremes(pack, self.size)
        changes: list[NDArray[np.intp]] = []
        for key in ("chg_on", "dsg_on"):
            col = tr.channel(key)
            changes += [_float_changes(col[:, b]) for b in range(col.shape[1])]
        for key in ("chg_diode_a", "dsg_diode_a"):
            on = np.abs(np.nan_to_num(tr.channel(key))) > 1e-6
            changes += [np.flatnonzero(np.diff(on[:, b])) + 1 for b in range(on.shape[1])]
        for seqs in tr.status.values():
            offset = n - len(seqs)
            rows = np.asarray(_status_changes(seqs), dtype=np.intp) + offset
            changes.append(np.append(rows, offset).astype(np.intp))
        parts += _fair_share(changes, self.change_cap * -(-n // self.size))
        idx = np.unique(np.concatenate(parts))
        idx = idx[(idx >= 0) & (idx < n)]
        self.kept += len(idx)
        return idx


def slice_trace(tr: Trace, idx: NDArray[np.intp]) -> Trace:
    """The rows ``idx`` (sorted) of a trace; a status channel that starts within the trace
    keeps the rows it covers (so it stays aligned on the end)."""
    n = len(tr.t_s)
    status: dict[str, list[Sequence[StatusValue]]] = {}
    for name, seqs in tr.status.items():
        offset = n - len(seqs)
        status[name] = [seqs[int(k) - offset] for k in idx if k >= offset]
    return Trace(
        t_s=tr.t_s[idx],
        bus_v=tr.bus_v[idx],
        load_demand_a=tr.load_demand_a[idx],
        load_a=tr.load_a[idx],
        charger_v=tr.charger_v[idx],
        charger_a=tr.charger_a[idx],
        battery=tr.battery[idx],
        group_v=tr.group_v[idx],
        status=status,
        aux=tr.aux[idx] if tr.aux is not None else None,
        step=tr.step[idx] if tr.step is not None else None,
    )


def concat_traces(parts: Sequence[Trace]) -> Trace:
    """Blocks of one run, in order, as one trace (status channels aligned on the end; group
    arrays padded with NaN to the widest block)."""
    width = max(p.group_v.shape[2] for p in parts)
    groups = [
        np.concatenate([p.group_v, np.full((*p.group_v.shape[:2], width - p.group_v.shape[2]),
                                           np.nan)], axis=2)
        for p in parts
    ]  # fmt: skip
    status: dict[str, list[Sequence[StatusValue]]] = {}
    for p in parts:
        for name, seqs in p.status.items():
            status.setdefault(name, []).extend(seqs)
    aux = None
    if any(p.aux is not None for p in parts):
        n_c = len(BATTERY_CHANNELS)
        aux = np.concatenate(
            [p.aux if p.aux is not None else np.full((len(p.t_s), n_c), np.nan) for p in parts]
        )
    steps = [p.step for p in parts]
    return Trace(
        t_s=np.concatenate([p.t_s for p in parts]),
        bus_v=np.concatenate([p.bus_v for p in parts]),
        load_demand_a=np.concatenate([p.load_demand_a for p in parts]),
        load_a=np.concatenate([p.load_a for p in parts]),
        charger_v=np.concatenate([p.charger_v for p in parts]),
        charger_a=np.concatenate([p.charger_a for p in parts]),
        battery=np.concatenate([p.battery for p in parts]),
        group_v=np.concatenate(groups),
        status=status,
        aux=aux,
        step=None if any(s is None for s in steps) else np.concatenate(steps),  # type: ignore[arg-type]
    )


def _fold(old: F64, new: F64, fn: Any) -> F64:
    """Combine per-battery extremes, NaN meaning "none yet" (``np.fmin``/``np.fmax``)."""
    return np.asarray(fn(old, new), dtype=np.float64)


def _block_ext(x: F64, fn: Any) -> F64:
    """Per column ``fn`` (nanmin / nanmax) over the rows, NaN for an all-NaN column."""
    out = np.full(x.shape[1], np.nan)
    has = ~np.isnan(x).all(axis=0)
    if has.any():
        out[has] = fn(x[:, has], axis=0)
    return out


@dataclass
class RunDigest:
    """Every figure the report's tables take from the samples, folded block by block."""

    names: list[str]
    config: Mapping[str, Any] | None
    n: int = 0
    t_first: float = math.nan
    t_last: float = math.nan
    decimated: int = 0
    """Samples per chart bucket when the charts carry a decimated trace (0: every sample)."""
    watch: RunWatch = field(init=False)
    dt_counts: Counter[float] = field(default_factory=Counter)
    _ext: dict[str, F64] = field(default_factory=dict)
    _finite: dict[str, NDArray[np.bool_]] = field(default_factory=dict)
    _carry: tuple[float, F64, F64, F64] | None = None
    """The previous block's last row: t, current, chg_on, dsg_on (its dt needs the next t)."""
    _t_prev: float = math.nan
    """The time of the sample before the last one (the last sample's dt at the end)."""

    def __post_init__(self) -> None:
        n_b = len(self.names)
        self.watch = RunWatch(self.config, self.names)
        nan = np.full(n_b, math.nan)
        for key in ("soc_first", "soc_last", "end_soc", "v_min", "v_max", "cmin", "cmax", "i_min",
                    "i_max", "temp_max"):  # fmt: skip
            self._ext[key] = nan.copy()
        for key in ("out_as", "in_as", "chg_on", "dsg_on", "chg_changes", "dsg_changes"):
            self._ext[key] = np.zeros(n_b)
        for key in ("v", "cell_min", "cell_max", "i", "temp"):
            self._finite[key] = np.zeros(n_b, dtype=bool)
        self._finite["chg_eq_dsg"] = np.ones(n_b, dtype=bool)
        self._finite["chg_diode"] = np.zeros(n_b, dtype=bool)
        self._finite["dsg_diode"] = np.zeros(n_b, dtype=bool)
        self.load_any = False
        self.charger_any = False
        self.demand_is_load = True

    @classmethod
    def of_result(cls, result: Result, config: Mapping[str, Any] | None) -> RunDigest:
        """The digest of a run held in memory: its whole trace as one block."""
        digest = cls(list(result.battery_names), config)
        digest.feed(result.trace)
        digest.feed_events(result.events)
        return digest

    # -- folding -------------------------------------------------------------------------
    def feed_events(self, events: Sequence[Event]) -> None:
        self.watch.events.feed(events)

    def feed(self, tr: Trace) -> None:
        """The next block of samples, in order."""
        m = len(tr.t_s)
        if m == 0:
            return
        self.watch.physics.feed(tr.t_s, tr.battery, tr.load_demand_a, tr.load_a, tr.charger_a)
        if self.n == 0:
            self.t_first = float(tr.t_s[0])
        self._extremes(tr)
        self._flows(tr)
        self._pack(tr)
        self._t_prev = float(tr.t_s[-2]) if m > 1 else self.t_last
        self.t_last = float(tr.t_s[-1])
        self.n += m

    def _extremes(self, tr: Trace) -> None:
        e, f = self._ext, self._finite
        soc = tr.channel("soc")
        fin = np.isfinite(soc)
        for b in range(soc.shape[1]):
            rows = np.flatnonzero(fin[:, b])
            if rows.size:
                if math.isnan(e["soc_first"][b]):
                    e["soc_first"][b] = soc[rows[0], b]
                e["soc_last"][b] = soc[rows[-1], b]
        e["end_soc"] = soc[-1].astype(np.float64)
        for key, chan, fin_key, fn, fold in (
            ("v_min", "voltage_v", "v", np.nanmin, np.fmin),
            ("v_max", "voltage_v", "v", np.nanmax, np.fmax),
            ("cmin", "min_cell_v", "cell_min", np.nanmin, np.fmin),
            ("cmax", "max_cell_v", "cell_max", np.nanmax, np.fmax),
            ("i_min", "current_a", "i", np.nanmin, np.fmin),
            ("i_max", "current_a", "i", np.nanmax, np.fmax),
            ("temp_max", "temp_c", "temp", np.nanmax, np.fmax),
        ):
            x = tr.channel(chan)
            e[key] = _fold(e[key], _block_ext(x, fn), fold)
            f[fin_key] |= np.isfinite(x).any(axis=0)
        for path in ("chg", "dsg"):
            d = np.abs(np.nan_to_num(tr.channel(f"{path}_diode_a"))) > 1e-6
            f[f"{path}_diode"] |= d.any(axis=0)
        f["chg_eq_dsg"] &= np.array(
            [np.array_equal(tr.channel("chg_on")[:, b], tr.channel("dsg_on")[:, b],
                            equal_nan=True) for b in range(len(self.names))],
            dtype=bool,
        )  # fmt: skip

    def _flows(self, tr: Trace) -> None:
        """Charge in and out, time on, switch changes: each row weighted by the time to the
        next one, so the previous block's last row is settled with this block's first time."""
        e = self._ext
        t, cur = tr.t_s, tr.channel("current_a")
        chg, dsg = tr.channel("chg_on"), tr.channel("dsg_on")
        if self._carry is not None:
            t0, c0, g0, d0 = self._carry
            t = np.concatenate([[t0], t])
            cur = np.concatenate([c0[None, :], cur])
            chg = np.concatenate([g0[None, :], chg])
            dsg = np.concatenate([d0[None, :], dsg])
        else:  # the run's first row counts here; later blocks' first rows came as the carry
            e["chg_on"] += np.sum(chg[:1] > 0.5, axis=0)
            e["dsg_on"] += np.sum(dsg[:1] > 0.5, axis=0)
        dt = np.diff(t)
        head = cur[:-1]
        e["out_as"] += np.nansum(np.clip(head, 0, None) * dt[:, None], axis=0)
        e["in_as"] += np.nansum(np.clip(-head, 0, None) * dt[:, None], axis=0)
        e["chg_on"] += np.sum(chg[1:] > 0.5, axis=0)
        e["dsg_on"] += np.sum(dsg[1:] > 0.5, axis=0)
        e["chg_changes"] += np.count_nonzero(np.diff(chg, axis=0) != 0, axis=0)
        e["dsg_changes"] += np.count_nonzero(np.diff(dsg, axis=0) != 0, axis=0)
        self._count_dt(dt)
        self._carry = (float(t[-1]), cur[-1].copy(), chg[-1].copy(), dsg[-1].copy())

    def _count_dt(self, dt: F64) -> None:
        values, counts = np.unique(dt, return_counts=True)
        self.dt_counts.update(dict(zip(values.tolist(), counts.tolist(), strict=True)))
        if len(self.dt_counts) > _DT_VALUES_MAX:  # floating-point noise: round it away
            rounded: Counter[float] = Counter()
            for v, c in self.dt_counts.items():
                rounded[float(f"{v:.9g}")] += c
            self.dt_counts = rounded

    def _pack(self, tr: Trace) -> None:
        with np.errstate(invalid="ignore"):
            self.load_any |= bool(np.nanmax(np.abs(tr.load_a), initial=0.0) > 0)
            self.charger_any |= bool(np.nanmax(np.abs(tr.charger_a), initial=0.0) > 0)
        self.demand_is_load &= bool(
            np.allclose(tr.load_demand_a, tr.load_a, rtol=1e-6, atol=1e-6, equal_nan=True)
        )

    # -- figures -------------------------------------------------------------------------
    @property
    def span_s(self) -> float:
        return self.t_last - self.t_first if self.n > 1 else 0.0

    def dt_median(self) -> float:
        """The median step length (as ``np.median(np.diff(t))``)."""
        total = sum(self.dt_counts.values())
        if total == 0:
            return math.nan
        want = [(total - 1) // 2, total // 2]
        got: list[float] = []
        seen = 0
        for v in sorted(self.dt_counts):
            c = self.dt_counts[v]
            while want and want[0] < seen + c:
                got.append(v)
                want.pop(0)
            seen += c
        return (got[0] + got[1]) / 2.0

    def charge_ah(self) -> tuple[list[float], list[float]]:
        """(out, in) per battery, the last sample weighted by the step before it."""
        e = self._ext
        out, inn = e["out_as"].copy(), e["in_as"].copy()
        if self._carry is not None:
            last_dt = self.t_last - self._t_prev if self.n > 1 else 0.0
            c = self._carry[1]
            out += np.nan_to_num(np.clip(c, 0, None) * last_dt)
            inn += np.nan_to_num(np.clip(-c, 0, None) * last_dt)
        return [float(x) / 3600.0 for x in out], [float(x) / 3600.0 for x in inn]

    def extreme(self, key: str) -> list[float]:
        """Per battery: ``v_min``, ``v_max``, ``cmin``, ``cmax``, ``i_min``, ``i_max``,
        ``temp_max`` (NaN for a battery without a finite value), ``soc_first``, ``soc_last``
        (first / last finite), ``end_soc`` (the last sample, as recorded)."""
        fin_of = {"v_min": "v", "v_max": "v", "cmin": "cell_min", "cmax": "cell_max",
                  "i_min": "i", "i_max": "i", "temp_max": "temp"}  # fmt: skip
        vals = self._ext[key]
        if key in fin_of:
            fin = self._finite[fin_of[key]]
            return [float(v) if fin[b] else math.nan for b, v in enumerate(vals)]
        return [float(v) for v in vals]

    def on_share(self, path: str) -> list[float]:
        """Share of samples with the path closed (``chg`` or ``dsg``)."""
        return [float(x) / self.n if self.n else math.nan for x in self._ext[f"{path}_on"]]

    def changes(self, path: str) -> list[int]:
        return [int(x) for x in self._ext[f"{path}_changes"]]

    def same_paths(self, b: int) -> bool:
        """CHG and DSG of battery ``b`` were equal at every sample."""
        return bool(self._finite["chg_eq_dsg"][b])

    def diode_conducted(self, path: str, b: int) -> bool:
        return bool(self._finite[f"{path}_diode"][b])

    def verdict(self) -> Verdict:
        return self.watch.verdict()


__all__ = [
    "CHANGES_PER_BUCKET",
    "Decimator",
    "RunDigest",
    "bucket_size",
    "concat_traces",
    "slice_trace",
]
