"""The in-memory trace of a single run, written by a kernel into growing column blocks.

Every step of a P = 1 run is recorded as plant truth (the battery channels of
:data:`~packpilot.contract.record.BATTERY_CHANNELS`, per-group voltages, bus and charger) plus
every compiled status channel as a number; labels and ``None`` are rendered once, at the end
(:meth:`TraceBuffer.trace`), not every step. A recorder that streams (SQLite, the dashboard)
gets one :class:`StepSample` per step built from the same row.
"""

from __future__ import annotations

import gc
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from itertools import compress
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import MeasArrays
from packpilot.contract.bms import StatusValue
from packpilot.contract.events import value as field_value
from packpilot.contract.record import BATTERY_CHANNELS, StatusLayout, StepSample, Trace
from packpilot.contract.topology import Topology
from packpilot.jit import kernel
from packpilot.model.pack import Interval, Pack

F64 = NDArray[np.float64]
N_CH = len(BATTERY_CHANNELS)
MAX_TRACE_ROWS = 1 << 17
"""Most rows the in-memory trace keeps (131,072: every step of every example, the longest has
28,800). A longer run keeps a decimated trace: when the buffer is full every other row is
dropped and from then on only every 2nd (4th, ...) step is kept, so a week-long run holds as
much memory as a 4-hour one. The last step is always in the trace; a streaming recorder
(``--db``) still receives every step."""


@kernel
def _row(
    k: int, p: int, starts: Any, group_table: Any, cell_v: F64, soc: F64, temp: F64, cap: F64,
    chg_on: Any, dsg_on: Any, welded: Any, fet_shorted: Any, battery_v: F64, string_a: F64,
    chg_d: F64, dsg_d: F64, bal_w: F64, group_v: F64, status: F64, out_bat: F64,
    out_group: F64, out_status: F64, m_v: F64, m_a: F64, m_t: F64, m_soc: F64,
    step: int, t_s: float, bus_v: F64, demand_a: F64, load_a: F64, charger_v: F64,
    charger_a: F64, out_step: Any, out_scalars: F64,
) -> None:  # fmt: skip
    """Row ``k`` of the trace: pack ``p``'s truth after the step (``Runner._sample`` order);
    the gates as the hardware really is (``Pack.effective_gates``); then the core's status
    slots and, after them, what the BMS measured (:data:`MEASURED`, ``m_*`` shaped (P, B));
    the step and the pack's scalars (``TraceBuffer._cols`` order)."""
    out_step[k] = step
    sc = out_scalars[k]
    sc[0] = t_s
    sc[1] = bus_v[p]
    sc[2] = demand_a[p]
    sc[3] = load_a[p]
    sc[4] = charger_v[p]
    sc[5] = charger_a[p]
    S = starts.shape[0]
    C = cell_v.shape[1]
    for s in range(S):
        lo = starts[s]
        hi = starts[s + 1] if s + 1 < S else C
        rem, full = soc[p, lo] * cap[p, lo], cap[p, lo]
        tmax, vmin, vmax = temp[p, lo], cell_v[p, lo], cell_v[p, lo]
        for c in range(lo + 1, hi):  # np.minimum / np.maximum.reduceat: NaN propagates
            r = soc[p, c] * cap[p, c]
            rem = rem if rem <= r or rem != rem else r
            full = full if full <= cap[p, c] or full != full else cap[p, c]
            tmax = tmax if tmax >= temp[p, c] or tmax != tmax else temp[p, c]
            vmin = vmin if vmin <= cell_v[p, c] or vmin != vmin else cell_v[p, c]
            vmax = vmax if vmax >= cell_v[p, c] or vmax != vmax else cell_v[p, c]
        row = out_bat[k, s]
        row[0] = battery_v[p, s]
        row[1] = string_a[p, s]
        row[2] = rem / full
        row[3] = tmax
        row[4] = vmin
        row[5] = vmax
        row[6] = rem
        row[7] = full
        row[8] = 1.0 if chg_on[p, s] | welded[s] | fet_shorted[p, s, 0] else 0.0
        row[9] = 1.0 if dsg_on[p, s] | welded[s] | fet_shorted[p, s, 1] else 0.0
        row[10] = chg_d[p, s]
        row[11] = dsg_d[p, s]
        row[12] = bal_w[p, s]
        for g in range(group_table.shape[1]):
            gi = group_table[s, g]
            out_group[k, s, g] = group_v[p, gi] if gi >= 0 else np.nan
    n_core = status.shape[2]
    for i in range(status.shape[1]):
        for j in range(n_core):
            out_status[k, i, j] = status[p, i, j]
    if m_v.shape[0] > p:
        for i in range(min(out_status.shape[1], m_v.shape[1])):
            out_status[k, i, n_core] = m_v[p, i]
            out_status[k, i, n_core + 1] = m_a[p, i]
            out_status[k, i, n_core + 2] = m_t[p, i]
            out_status[k, i, n_core + 3] = m_soc[p, i]


class _NoBat(NamedTuple):
    voltage_v: F64
    current_a: F64
    temp_c: F64
    soc: F64


_NO_MEASUREMENT = _NoBat(*(np.zeros((0, 0)),) * 4)
"""``_row``'s measured arrays when there are none (their slots are then NaN)."""


@contextmanager
def _gc_paused() -> Iterator[None]:
    """No cyclic garbage collection while a trace's status lists are built: they are acyclic,
    and the hundreds of thousands of small lists of a long run would otherwise trigger full
    collections over the whole heap (3/4 of the rendering time of a 6,000-step uav_mission)."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _render_column(col: F64, kind: str, labels: Any) -> list[list[StatusValue]]:
    """``[[field_value(float(x), kind, labels) for x in row] for row in col]``, fast.

    ``tolist`` gives the same Python floats as ``float(x)`` (bit for bit, -0.0 and NaN
    included). Kinds that are not floats depend only on ``int(x)`` or ``x != 0`` (the same for
    0.0 and -0.0) or on NaN-ness (the same for every NaN), so their values are rendered once per
    distinct number."""
    rows: list[list[float]] = col.tolist()
    if kind == "f":
        return rows  # type: ignore[return-value]
    if kind == "o":
        return [[None if x != x else x for x in row] for row in rows]
    if kind not in ("i", "b", "m") and not kind.startswith("l:"):
        return [[field_value(x, kind, labels) for x in row] for row in rows]
    seen: dict[object, StatusValue] = {}

    def one(x: float) -> StatusValue:
        key: object = x if x == x else "nan"
        v = seen.get(key, seen)
        if v is seen:
            v = seen[key] = field_value(x, kind, labels)
        return v  # type: ignore[return-value]

    return [[one(x) for x in row] for row in rows]


MEASURED: tuple[tuple[str, str], ...] = (
    ("bms_v", "voltage_v"),
    ("bms_a", "current_a"),
    ("bms_degc", "temp_c"),
    ("bms_soc", "soc"),
)
"""Per battery, what the BMS measured (status channel, measurement field): the trace's battery
rows are the plant's truth, and after a sensor fault the two differ (#17 §1: the dashboard
card shows what the BMS saw, NaN included)."""


class _Measured:
    """A status-channel stand-in for a measured quantity (float, no labels)."""

    kind = "f"

    def __init__(self, name: str) -> None:
        self.name = name


class _Layout:
    """What rendering a status row needs, built once per trace: each channel's slot, kind and
    labels, the key order, and whether a row of batteries already is its spread over the
    strings (traction batteries are strings 0..B-1, no aux)."""

    def __init__(self, channels: Sequence[tuple[int, Any, Any]], topology: Topology, n_b: int):
        self.slot = {ch.name: (slot, ch.kind, labels) for slot, ch, labels in channels}
        self.topology = topology
        self.same = topology.traction == tuple(range(topology.n_strings)) and (
            n_b == topology.n_strings
        )

    def spread(self, vals: list[Any]) -> list[StatusValue]:
        return vals if self.same else self.topology.spread(vals)  # type: ignore[return-value]


class StatusRow(Mapping[str, list[StatusValue]]):
    """The status channels of one step, rendered when read (a value per string, as
    ``Topology.spread`` lays it out), from a copy of the step's numbers: the same values
    the whole dict used to hold. ``changed`` names, in order, the channels whose numbers
    changed since the previous sample (``None``: unknown, every channel may have)."""

    def __init__(
        self,
        values: F64,
        layout: _Layout,
        foreign: dict[str, list[StatusValue]] | None,
        changed: tuple[str, ...] | None,
    ) -> None:
        self._values = values
        self._layout = layout
        self._foreign = foreign or {}
        self.changed = changed

    def __getitem__(self, key: str) -> list[StatusValue]:
        lay = self._layout
        hit = lay.slot.get(key)
        if hit is None:
            return lay.topology.spread(self._foreign[key])  # type: ignore[return-value]
        slot, kind, labels = hit
        col: list[float] = self._values[:, slot].tolist()  # the floats float(x) gives
        if kind == "f":
            return lay.spread(col)
        if kind == "o":
            return lay.spread([None if x != x else x for x in col])
        return lay.spread([field_value(x, kind, labels) for x in col])

    def _keys(self) -> list[str]:
        if not self._foreign:
            return list(self._layout.slot)
        keys = dict.fromkeys(self._foreign)
        keys.update(dict.fromkeys(self._layout.slot))
        return list(keys)

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())


class TraceStatus(Mapping[str, list[Sequence[StatusValue]]]):
    """The status channels of a whole trace, a channel rendered (labels, ``None``, booleans)
    only when it is first read, then kept. Rendering every channel of every row cost as much
    per step as the whole BMS (25 us per row of uav_mission), for a run whose caller may read
    none of them (``packpilot simulate`` without outputs reads only what the verdict needs).
    Same keys, order and values as the dict built eagerly before."""

    def __init__(
        self,
        values: F64,
        channels: Sequence[tuple[int, Any, Any]],
        topology: Topology,
        foreign: Sequence[dict[str, list[StatusValue]]],
    ) -> None:
        self._values = values
        self._topology = topology
        self._slot = {ch.name: (slot, ch.kind, labels) for slot, ch, labels in channels}
        self._foreign: dict[str, list[Sequence[StatusValue]]] = {}
        for row in foreign:
            for key, vals in row.items():
                self._foreign.setdefault(key, []).append(topology.spread(vals))  # type: ignore[arg-type]
        keys = dict.fromkeys(self._foreign)
        keys.update(dict.fromkeys(self._slot))
        self._order = list(keys)
        self._done: dict[str, list[Sequence[StatusValue]]] = {}

    def __getitem__(self, key: str) -> list[Sequence[StatusValue]]:
        done = self._done.get(key)
        if done is not None:
            return done
        hit = self._slot.get(key)
        if hit is None:
            return self._foreign[key]
        slot, kind, labels = hit
        topo = self._topology
        with _gc_paused():
            rows = _render_column(self._values[:, :, slot], kind, labels)
            # Traction batteries are strings 0..B-1 with no aux: a row already is its spread.
            same_layout = topo.traction == tuple(range(topo.n_strings))
            if not (same_layout and self._values.shape[1] == topo.n_strings):
                rows = [topo.spread(row) for row in rows]  # type: ignore[misc]
        self._done[key] = rows  # type: ignore[assignment]
        return rows  # type: ignore[return-value]

    def __iter__(self) -> Iterator[str]:
        return iter(self._order)

    def __len__(self) -> int:
        return len(self._order)

    def __repr__(self) -> str:
        return repr(dict(self.items()))


class TraceBuffer:
    """The trace of pack ``p`` of a run, in blocks that double as they fill, up to
    ``max_rows`` rows; past that, decimated (:data:`MAX_TRACE_ROWS`). ``stride`` is the step
    spacing of the rows kept so far."""

    def __init__(
        self,
        pack: Pack,
        topology: Topology,
        channels: Sequence[tuple[int, Any, Any]],
        n_status: int,
        p: int = 0,
        capacity: int = 1024,
        max_rows: int = MAX_TRACE_ROWS,
    ) -> None:
        if max_rows < 2 or max_rows % 2:
            raise ValueError(f"max_rows must be even and >= 2, got {max_rows}")
        self.pack, self.topology, self.p = pack, topology, p
        self.max_rows = max_rows
        self.stride = 1
        self._pending = False
        """Row ``n`` holds the latest step, which the stride did not keep (yet)."""
        capacity = max(1, min(capacity, max_rows + 1))  # + 1: the row of the latest step
        self.n_core = n_status
        """Status slots the core writes; the :data:`MEASURED` slots follow them."""
        self.channels = [
            *channels,
            *((n_status + j, _Measured(name), {}) for j, (name, _) in enumerate(MEASURED)),
        ]
        """(slot, StatusChannel, labels) of every compiled status channel, in output order,
        then the measured values."""
        S, G = pack.n_strings, pack.max_groups
        n_b = len(topology.traction)
        self.n = 0
        self._cols = ("t_s", "bus_v", "load_demand_a", "load_a", "charger_v", "charger_a")
        self.scalars = np.zeros((capacity, len(self._cols)))
        self.step = np.zeros(capacity, np.int64)
        self.battery = np.zeros((capacity, S, N_CH))
        self.group_v = np.zeros((capacity, S, G))
        self.status = np.zeros((capacity, n_b, n_status + len(MEASURED)))
        self.foreign: list[dict[str, list[StatusValue]]] = []
        """Per step, the status of Python parts (P = 1 only)."""
        self._layout = _Layout(self.channels, topology, n_b)
        self._keys = [ch.name for _, ch, _ in self.channels]
        self._key_slot = np.array([slot for slot, _, _ in self.channels], np.int64)
        self._bank: Any = None
        self._bank_ordered = False
        self._views: dict[int, tuple[F64, F64, F64, F64]] = {}
        """id(soc array) -> (soc, temp, their (packs, cells) views): a view made once per
        state buffer, not per step."""
        self._last_sampled: F64 | None = None
        """The status numbers of the last :meth:`sample` (what ``changed`` compares with)."""

    _ARRAYS = ("scalars", "step", "battery", "group_v", "status")

    def _cell_states(self) -> tuple[F64, F64]:
        """``Pack.cell_states()`` without its copies when one bank holds every cell in order
        (the common pack): its state arrays, viewed (packs, cells)."""
        pack = self.pack
        banks = pack.banks
        if len(banks) == 1:
            bank = banks[0]
            if bank is not self._bank:
                n = pack.n_packs * pack.n_cells
                self._bank = bank
                self._bank_ordered = bool(
                    bank.idx.shape == (n,) and np.array_equal(bank.idx, np.arange(n))
                )
            if self._bank_ordered:
                st = bank.state
                hit = self._views.get(id(st.soc))  # the plant swaps two state buffers
                if hit is None or hit[0] is not st.soc or hit[1] is not st.temp_c:
                    if len(self._views) > 4:
                        self._views.clear()
                    shape = (pack.n_packs, pack.n_cells)
                    views = (st.soc.reshape(shape), st.temp_c.reshape(shape))
                    hit = self._views[id(st.soc)] = (st.soc, st.temp_c, *views)
                return hit[2], hit[3]
        return pack.cell_states()

    def _grow(self) -> None:
        size = min(2 * self.step.shape[0], self.max_rows + 1)
        for name in self._ARRAYS:
            a = getattr(self, name)
            b = np.zeros((size, *a.shape[1:]), a.dtype)
            b[: a.shape[0]] = a
            setattr(self, name, b)

    def _decimate(self) -> None:
        """Keep every other row (steps that are multiples of the doubled stride)."""
        n = self.n
        for name in self._ARRAYS:
            a = getattr(self, name)
            half = a[0:n:2].copy()
            a[: half.shape[0]] = half
        if self.foreign:
            self.foreign[:] = self.foreign[0:n:2]
        self.n = (n + 1) // 2
        self.stride *= 2

    def add(
        self,
        k: int,
        iv: Interval,
        status: F64,
        foreign: dict[str, list[StatusValue]] | None,
        m: MeasArrays | None = None,
    ) -> int:
        """Write step ``k`` into the next row and return that row (for :meth:`sample`). The
        row is kept when ``k`` is a multiple of :attr:`stride`; otherwise the next step
        overwrites it (until then it is the trace's last row)."""
        if self.n == self.step.shape[0]:
            self._grow()
        pack, p, n = self.pack, self.p, self.n
        soc, temp = self._cell_states()
        bat = _NO_MEASUREMENT if m is None else m.bat
        _row(
            n, p, pack.string_cell_starts, pack.group_table, iv.cell_v, soc, temp,
            pack.capacity_ah, pack.chg_on, pack.dsg_on, pack.welded, pack.fet_shorted,
            iv.battery_v, iv.string_a, iv.chg_diode_a,
            iv.dsg_diode_a, iv.balancer_in_w, iv.group_v, status, self.battery, self.group_v,
            self.status, bat.voltage_v, bat.current_a, bat.temp_c, bat.soc,
            k, iv.t_s, iv.bus_v, iv.load_demand_a, iv.load_a, iv.charger_v, iv.charger_a,
            self.step, self.scalars,
        )  # fmt: skip
        if m is None:
            self.status[n, :, self.n_core :].fill(np.nan)
        if foreign is not None:
            del self.foreign[n:]
            self.foreign.append(foreign)
        self._pending = k % self.stride != 0
        if not self._pending:
            self.n = n + 1
            if self.n > self.max_rows:
                self._decimate()
        return n if self._pending else self.n - 1

    def status_layout(self) -> StatusLayout:
        """How a row of :attr:`status` reads as the status of a sample (:class:`StatusRow`'s
        channels, in its order, laid out over the strings as it spreads them)."""
        lay = self._layout
        topo = self.topology
        n_b = len(topo.traction)
        positions = tuple(range(n_b)) if lay.same else tuple(topo.traction)
        n_strings = n_b if lay.same else topo.n_strings
        channels = tuple(
            (name, slot, kind, labels) for name, (slot, kind, labels) in lay.slot.items()
        )
        return StatusLayout(channels, positions, n_strings)

    @property
    def rows(self) -> int:
        """Rows the trace holds now: the kept ones and the latest step."""
        return self.n + self._pending

    def sample(self, n: int) -> StepSample:
        """Row ``n`` as the recorders' unit of telemetry. Its status is a :class:`StatusRow`:
        a channel is rendered only when read, and it names the channels whose numbers
        changed since the previous sample (``changed``), so a recorder that stores changes
        (SQLite) reads only those instead of every channel of every step."""
        sc = self.scalars[n]
        row = self.status[n].copy()
        last = self._last_sampled
        changed: tuple[str, ...] | None = None
        if last is not None and last.shape == row.shape:
            moved = (row.view(np.int64) != last.view(np.int64)).any(axis=0)
            changed = tuple(compress(self._keys, moved[self._key_slot].tolist()))
        foreign = self.foreign[n] if self.foreign else None
        if foreign is not None:
            changed = None  # a Python part's status: no numbers to compare, read it all
        self._last_sampled = row
        status = StatusRow(row, self._layout, foreign, changed)
        return StepSample(
            step=int(self.step[n]),
            t_s=float(sc[0]),
            bus_v=float(sc[1]),
            load_demand_a=float(sc[2]),
            load_a=float(sc[3]),
            charger_v=float(sc[4]),
            charger_a=float(sc[5]),
            battery=self.battery[n].copy(),
            group_v=self.group_v[n].copy(),
            status=status,
        )

    def trace(self) -> Trace:
        """Everything recorded, as the run's :class:`Trace`."""
        n = self.rows
        if n == 0:
            raise ValueError("a trace needs at least one sample")
        status = TraceStatus(
            self.status[:n].copy(), self.channels, self.topology, self.foreign[:n]
        )
        sc = self.scalars[:n]
        return Trace(
            t_s=sc[:, 0].copy(),
            bus_v=sc[:, 1].copy(),
            load_demand_a=sc[:, 2].copy(),
            load_a=sc[:, 3].copy(),
            charger_v=sc[:, 4].copy(),
            charger_a=sc[:, 5].copy(),
            battery=self.battery[:n].copy(),
            group_v=self.group_v[:n].copy(),
            status=status,
            aux=None,
            step=self.step[:n].copy(),
        )


__all__ = ["StatusRow", "TraceBuffer", "TraceStatus"]
