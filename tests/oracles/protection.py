"""ORACLE: the scalar discharge protection as it was before the compiled core (tests only;
deleted once the golden and equivalence tests have held). The config classes now live in
``packpilot.config.protection``.

Condition-dependent discharge protection (US10868343B2; ``spec/discharge_protection.md``).

A fixed "cut-off voltage + longest sustainable time" wastes capacity when the load is heavy or
the battery is cold (the voltage sags under load while plenty of charge is left) and is too lax
when the load is light. Here the protection parameter (cut-off, t_max) is looked up every tick
from the battery's status (current, temperature, optionally SOH) in an N-dimensional range
table, and the time spent at or below the *active* cut-off is accumulated with the weight
``n = m / t_max`` (``m`` = LCM of all t_max). The battery's discharge path is opened, and stays
open until the next discharge cycle, once the weighted sum reaches ``m``; this is the same as
``sum(t_k / t_max_k) >= 1``: each second under parameter k uses up ``1 / t_max_k`` of the
allowance.

Exactness: the sum is kept as an exact :class:`fractions.Fraction` in weighted milliseconds
(``n`` is an integer because ``m`` is the LCM of whole-millisecond durations), so the spec's
worked examples trip exactly at 5 s, 15 s and 10 s and never one tick late from float round-off.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction

from packpilot.config.protection import AxisRange, ProtectionConfig, ProtectionParameter
from packpilot.contract.bms import BatteryMeasurement, Commands, ControlOutput, Event, Measurements
from packpilot.contract.topology import PackInfo

AxisExtractor = Callable[[BatteryMeasurement, PackInfo, int], float]


def _soh(bm: BatteryMeasurement, pack: PackInfo, i: int) -> float:
    """State of health as full / nominal capacity; NaN (= unknown) without a nominal value."""
    if i < len(pack.capacity_ah) and pack.capacity_ah[i] > 0.0:
        return bm.full_capacity_ah / pack.capacity_ah[i]
    return math.nan


AXES: Mapping[str, AxisExtractor] = {
    "current_a": lambda bm, pack, i: bm.current_a,
    "temp_c": lambda bm, pack, i: bm.temp_c,
    "soh": _soh,
}
"""Status parameters a table may use as axes. Internal resistance and cycle count (spec §2)
need a field in :class:`BatteryMeasurement` first; then they are one line here."""

_ALL = AxisRange()


@dataclass(frozen=True)
class CompiledTable:
    """The validated table in lookup form, with m and the integer weights."""

    axes: tuple[str, ...]
    rows: tuple[tuple[int, tuple[AxisRange, ...]], ...]
    """(parameter index, one range per axis) per table row."""
    params: tuple[ProtectionParameter, ...]
    """Parameters referenced by the table, in order of first appearance."""
    m_ms: int
    weights: tuple[int, ...]
    """n = m / t_max per parameter (exact integers)."""

    @classmethod
    def from_config(cls, cfg: ProtectionConfig) -> CompiledTable:
        by_name = {p.name: p for p in cfg.parameters}
        used: list[str] = []
        for r in cfg.table:
            if r.param not in used:
                used.append(r.param)
        params = tuple(by_name[n] for n in used)
        m_ms = math.lcm(*(p.t_max_ms for p in params))
        axes = cfg.axes
        rows = tuple(
            (used.index(r.param), tuple(r.ranges.get(a, _ALL) for a in axes)) for r in cfg.table
        )
        return cls(
            axes=axes,
            rows=rows,
            params=params,
            m_ms=m_ms,
            weights=tuple(m_ms // p.t_max_ms for p in params),
        )

    def lookup(self, values: Sequence[float]) -> int:
        """Row index for fully known axis values (the table covers everything exactly once)."""
        for k, (_, ranges) in enumerate(self.rows):
            if all(r.contains(x) for r, x in zip(ranges, values, strict=True)):
                return k
        raise AssertionError("validated table does not cover the point")  # pragma: no cover

    def most_conservative(self, values: Sequence[float]) -> int:
        """Among rows consistent with the finite values (NaN = unknown), the highest cut-off.

        Ties go to the shortest t_max, then to the first row: when a sensor fails the battery
        is protected as if the unknown status were the worst the table allows.
        """
        best = -1
        best_key = (0.0, 0.0)
        for k, (p, ranges) in enumerate(self.rows):
            if all(math.isnan(x) or r.contains(x) for r, x in zip(ranges, values, strict=True)):
                key = (self.params[p].cutoff_v, -self.params[p].t_max_s)
                if best < 0 or key > best_key:
                    best, best_key = k, key
        return best


_DT_CACHE: dict[float, Fraction] = {}


def dt_to_ms(dt_s: float) -> Fraction:
    """Exact milliseconds for a tick, snapping float noise (0.1 s -> 100 ms, 1/3 s -> 1000/3)."""
    hit = _DT_CACHE.get(dt_s)
    if hit is None:
        hit = Fraction(dt_s * 1000.0).limit_denominator(1000)
        if len(_DT_CACHE) > 4096:
            _DT_CACHE.clear()
        _DT_CACHE[dt_s] = hit
    return hit


@dataclass
class BatteryProtectionState:
    """Everything one battery's protection remembers between ticks."""

    acc_wms: Fraction = Fraction(0)
    """Weighted sum in weight x milliseconds (trip at m_ms)."""
    tripped: bool = False
    row: int = -1
    """Active table row (-1 before the first tick)."""
    discharging: bool = False
    """Last known discharge state (held while the current reading is not finite)."""
    charge_s: float = 0.0
    charge_cycle_started: bool = False
    absent: bool = False
    filtered: dict[str, float] = field(default_factory=dict)
    faults: set[str] = field(default_factory=set)
    """Fields currently non-finite (a Fault event is emitted once per episode)."""


@dataclass
class ProtectionState:
    batteries: list[BatteryProtectionState]


class ProtectionController:
    """Per-battery condition-dependent discharge protection; see the module docstring.

    Tick semantics: each call's measurement is taken to hold for ``dt_s``; the trip fires on the
    call whose ``dt_s`` makes the weighted sum reach ``m``. Commands: ``dsg_on=False`` for a
    tripped battery until its next discharge cycle, otherwise ``None`` (no opinion).
    """

    def __init__(self, config: ProtectionConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.table = CompiledTable.from_config(config)
        self._extract = tuple(AXES[a] for a in self.table.axes)
        self._bands = tuple(config.hysteresis.get(a, 0.0) for a in self.table.axes)
        self._use_hysteresis = any(b > 0.0 for b in self._bands)
        self.state = ProtectionState(
            batteries=[BatteryProtectionState() for _ in range(pack.n_batteries)]
        )

    @property
    def m_s(self) -> float:
        return self.table.m_ms / 1000.0

    def weights(self) -> dict[str, int]:
        return {p.name: n for p, n in zip(self.table.params, self.table.weights, strict=True)}

    def parameter(self, battery: int) -> ProtectionParameter | None:
        """Active parameter of a battery (None before its first tick)."""
        row = self.state.batteries[battery].row
        return None if row < 0 else self.table.params[self.table.rows[row][0]]

    def fraction(self, battery: int) -> float:
        """Used-up share of the allowance, sum(t_k / t_max_k): 0 .. 1 (and above at a trip)."""
        return float(self.state.batteries[battery].acc_wms / self.table.m_ms)

    def start_new_cycle(self, battery: int) -> None:
        """Host command: clear the sum and the latch (e.g. battery charged off-pack)."""
        st = self.state.batteries[battery]
        st.acc_wms = Fraction(0)
        st.tripped = False

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        events: list[Event] = []
        dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
        dsg: list[bool | None] = []
        names: list[str | None] = []
        cutoffs: list[float | None] = []
        tmaxs: list[float | None] = []
        fractions: list[float] = []
        tripped: list[bool] = []
        for i, st in enumerate(self.state.batteries):
            bm = meas.batteries[i] if i < len(meas.batteries) else None
            self._step_battery(i, bm, st, meas.t_s, dt, events)
            p = self.parameter(i)
            dsg.append(False if st.tripped else None)
            names.append(None if p is None else p.name)
            cutoffs.append(None if p is None else p.cutoff_v)
            tmaxs.append(None if p is None else p.t_max_s)
            fractions.append(self.fraction(i))
            tripped.append(st.tripped)
        status: dict[str, Sequence[float | int | str | bool | None]] = {
            "protection_param": names,
            "protection_cutoff_v": cutoffs,
            "protection_tmax_s": tmaxs,
            "protection_fraction": fractions,
            "protection_tripped": tripped,
        }
        return ControlOutput(
            commands=Commands(dsg_on=tuple(dsg)), events=tuple(events), status=status
        )

    # -- internals -----------------------------------------------------------------------

    def _fault(
        self,
        i: int,
        st: BatteryProtectionState,
        t_s: float,
        name: str,
        ok: bool,
        what: str,
        events: list[Event],
    ) -> None:
        if ok:
            st.faults.discard(name)
        elif name not in st.faults:
            st.faults.add(name)
            events.append(
                Event(
                    t_s=t_s,
                    kind="Fault",
                    battery=i,
                    message=f"protection: {name} is not finite; {what}",
                    data={"source": "protection", "field": name},
                )
            )

    def _new_cycle(
        self, i: int, st: BatteryProtectionState, t_s: float, reason: str, events: list[Event]
    ) -> None:
        if st.acc_wms or st.tripped:
            events.append(
                Event(
                    t_s=t_s,
                    kind="ProtectionReset",
                    battery=i,
                    message=f"new discharge cycle ({reason}): protection sum and latch cleared",
                    data={
                        "reason": reason,
                        "was_tripped": st.tripped,
                        "accumulated_s": float(st.acc_wms) / 1000.0,
                    },
                )
            )
        st.acc_wms = Fraction(0)
        st.tripped = False

    def _select(self, st: BatteryProtectionState, values: list[float]) -> int:
        if any(math.isnan(x) for x in values):
            return self.table.most_conservative(values)
        if self._use_hysteresis and st.row >= 0:
            ranges = self.table.rows[st.row][1]
            if all(r.contains(x, b) for r, x, b in zip(ranges, values, self._bands, strict=True)):
                return st.row
        return self.table.lookup(values)

    def _check_voltage(self, i: int, bm: BatteryMeasurement) -> tuple[float, str]:
        """Min cell voltage; else the weakest group's mean cell; else the mean cell; else NaN.

        A group is ``cells_per_group`` cells in series, so ``group_v / cells_per_group`` is that
        group's mean cell voltage (>= its minimum: the fallbacks under-count, never over-trip).
        """
        if math.isfinite(bm.min_cell_v):
            return bm.min_cell_v, "min_cell_v"
        pack = self.pack
        per_group = pack.cells_per_group[i] if i < len(pack.cells_per_group) else 0
        n_groups = pack.groups_per_battery[i] if i < len(pack.groups_per_battery) else 0
        g = bm.group_voltages_v
        if per_group > 0 and g and all(math.isfinite(v) for v in g):
            return min(g) / per_group, "group_voltages_v"
        if per_group > 0 and n_groups > 0 and math.isfinite(bm.voltage_v):
            return bm.voltage_v / (n_groups * per_group), "voltage_v"
        return math.nan, "none"

    def _step_battery(
        self,
        i: int,
        bm: BatteryMeasurement | None,
        st: BatteryProtectionState,
        t_s: float,
        dt: float,
        events: list[Event],
    ) -> None:
        cfg = self.config
        if bm is None or not bm.present:
            st.absent = True
            st.charge_s = 0.0
            return
        if st.absent:
            st.absent = False
            if cfg.reset_on_reinsert:
                self._new_cycle(i, st, t_s, "reinserted", events)

        cur = bm.current_a
        cur_ok = math.isfinite(cur)
        self._fault(
            i,
            st,
            t_s,
            "current_a",
            cur_ok,
            "discharge state held, most conservative parameter for the known status",
            events,
        )
        # New discharge cycle: sustained charging (spec §7/§10.4).
        if cur_ok and cur < -cfg.charge_threshold_a:
            st.charge_s += dt
            if st.charge_s >= cfg.charge_detect_s and not st.charge_cycle_started:
                st.charge_cycle_started = True
                self._new_cycle(i, st, t_s, "charge", events)
        else:
            st.charge_s = 0.0
            st.charge_cycle_started = False
        if cur_ok:
            st.discharging = cur > cfg.discharge_threshold_a

        values: list[float] = []
        for axis, extract in zip(self.table.axes, self._extract, strict=True):
            x = extract(bm, self.pack, i)
            if axis != "current_a":
                self._fault(
                    i,
                    st,
                    t_s,
                    axis,
                    math.isfinite(x),
                    "most conservative parameter for the known status",
                    events,
                )
            if not math.isfinite(x):
                values.append(math.nan)
                continue
            tau = cfg.filter_tau_s.get(axis)
            if tau is not None:
                prev = st.filtered.get(axis)
                x = x if prev is None else prev + (1.0 - math.exp(-dt / tau)) * (x - prev)
                st.filtered[axis] = x
            values.append(x)
        st.row = self._select(st, values)
        p_idx = self.table.rows[st.row][0]
        param = self.table.params[p_idx]

        v_chk, source = self._check_voltage(i, bm)
        self._fault(
            i,
            st,
            t_s,
            "min_cell_v",
            source == "min_cell_v",
            f"checking {source} instead"
            if source != "none"
            else "no accumulation until a voltage is available",
            events,
        )
        if st.tripped or math.isnan(v_chk):
            return
        below = (
            v_chk <= param.cutoff_v if cfg.voltage_comparison == "<=" else (v_chk < param.cutoff_v)
        )
        if below and st.discharging:
            st.acc_wms += self.table.weights[p_idx] * dt_to_ms(dt)
        elif not below and cfg.reset_on_recovery:
            st.acc_wms = Fraction(0)
        m = self.table.m_ms
        if st.acc_wms > m or (cfg.trip_comparison == ">=" and st.acc_wms == m):
            st.tripped = True
            events.append(
                Event(
                    t_s=t_s,
                    kind="ProtectionTripped",
                    battery=i,
                    message=(
                        f"discharge protection tripped under {param.name} "
                        f"({param.cutoff_v:g} V / {param.t_max_s:g} s): discharge path opened"
                    ),
                    data={
                        "param": param.name,
                        "cutoff_v": param.cutoff_v,
                        "t_max_s": param.t_max_s,
                        "weight": self.table.weights[p_idx],
                        "accumulated_s": float(st.acc_wms) / 1000.0,
                        "m_s": m / 1000.0,
                        "fraction": float(st.acc_wms / m),
                        "check_v": v_chk,
                        "check_v_source": source,
                        "min_cell_v": bm.min_cell_v,
                        "voltage_v": bm.voltage_v,
                        "current_a": bm.current_a,
                        "temp_c": bm.temp_c,
                        "soc": bm.soc,
                        "remaining_capacity_ah": bm.remaining_capacity_ah,
                        "full_capacity_ah": bm.full_capacity_ah,
                    },
                )
            )


__all__ = [
    "AXES",
    "BatteryProtectionState",
    "CompiledTable",
    "ProtectionController",
    "ProtectionState",
    "dt_to_ms",
]
