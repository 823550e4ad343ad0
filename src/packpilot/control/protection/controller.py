"""Condition-dependent discharge protection as a core method, and its one-pack face
:class:`ProtectionController`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from packpilot.config.protection import AXES, AxisRange, ProtectionConfig, ProtectionParameter
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.control.protection import rules
from packpilot.control.protection.rules import B1, F64, ProtectionParams, ProtectionState
from packpilot.errors import ConfigError

assert AXES[rules.AX_CURRENT] == "current_a" and AXES[rules.AX_TEMP] == "temp_c"
assert AXES[rules.AX_SOH] == "soh" and AXES[rules.AX_RES] == "resistance_ohm"
assert AXES[rules.AX_CYCLES] == "cycle_count" and len(AXES) == rules.N_AXES

FIELDS = (*AXES, "min_cell_v")
"""Fields a Fault event names (the axis codes, then the check voltage)."""
V_SOURCES = ("min_cell_v", "group_voltages_v", "voltage_v", "none")
RESETS = ("reinserted", "charge")

_FAULT = ("source:l:source", "field:l:fields")
REASONS = (
    Reason(
        "Fault",
        "protection: {field} is not finite; discharge state held, most conservative "
        "parameter for the known status",
        fields(*_FAULT),
    ),
    Reason(
        "Fault",
        "protection: {field} is not finite; most conservative parameter for the known status",
        fields(*_FAULT),
    ),
    Reason(
        "Fault",
        "protection: {field} is not finite; checking group_voltages_v instead",
        fields(*_FAULT),
    ),
    Reason(
        "Fault", "protection: {field} is not finite; checking voltage_v instead", fields(*_FAULT)
    ),
    Reason(
        "Fault",
        "protection: {field} is not finite; no accumulation until a voltage is available",
        fields(*_FAULT),
    ),
    Reason(
        "ProtectionReset",
        "new discharge cycle ({reason}): protection sum and latch cleared",
        fields("reason:l:resets", "was_tripped:b", "accumulated_s"),
    ),
    Reason(
        "ProtectionTripped",
        "discharge protection tripped under {param} ({cutoff_v:g} V / {t_max_s:g} s): "
        "discharge path opened",
        fields(
            "param:l:params",
            "cutoff_v",
            "t_max_s",
            "weight:i",
            "accumulated_s",
            "m_s",
            "fraction",
            "check_v",
            "check_v_source:l:vsources",
            "min_cell_v",
            "voltage_v",
            "current_a",
            "temp_c",
            "soc",
            "remaining_capacity_ah",
            "full_capacity_ah",
        ),
    ),
    Reason(
        "ProtectionWarning",
        "discharge protection at {fraction:.0%} of its allowance under {param} "
        "({cutoff_v:g} V / {t_max_s:g} s): trip in {time_to_trip_s:g} s at or below the cut-off",
        fields(
            "param:l:params",
            "cutoff_v",
            "t_max_s",
            "fraction",
            "share",
            "time_to_trip_s",
            "check_v",
            "current_a",
            "temp_c",
            "soc",
        ),
    ),
)
assert [r.kind for r in REASONS].index("ProtectionReset") == rules.RESET
assert [r.kind for r in REASONS].index("ProtectionWarning") == rules.WARNING
assert [r.kind for r in REASONS].index("ProtectionTripped") == rules.TRIPPED

STATUS = (
    StatusChannel("protection_param", "l:params"),
    StatusChannel("protection_cutoff_v", "o"),
    StatusChannel("protection_tmax_s", "o"),
    StatusChannel("protection_fraction", "f"),
    StatusChannel("protection_tripped", "b"),
    StatusChannel("protection_time_to_trip_s", "o"),
    StatusChannel("protection_time_to_empty_s", "o"),
)
assert STATUS[rules.ST_TIME_TO_TRIP].name == "protection_time_to_trip_s"
assert STATUS[rules.ST_TIME_TO_EMPTY].name == "protection_time_to_empty_s"

_ANY = AxisRange()


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
    lo: F64 = field(default_factory=lambda: np.zeros((0, 0)), compare=False, repr=False)
    """(rows, axes) lower edges as the rules read them; likewise ``hi``, ``lo_closed``,
    ``hi_closed``."""
    hi: F64 = field(default_factory=lambda: np.zeros((0, 0)), compare=False, repr=False)
    lo_closed: B1 = field(
        default_factory=lambda: np.zeros((0, 0), np.bool_), compare=False, repr=False
    )
    hi_closed: B1 = field(
        default_factory=lambda: np.zeros((0, 0), np.bool_), compare=False, repr=False
    )

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
            (used.index(r.param), tuple(r.ranges.get(a, _ANY) for a in axes)) for r in cfg.table
        )
        shape = (len(rows), len(axes))
        lo = np.array([[x.lo for x in rr] for _, rr in rows], np.float64).reshape(shape)
        hi = np.array([[x.hi for x in rr] for _, rr in rows], np.float64).reshape(shape)
        lo_c = np.array([[x.lo_closed for x in rr] for _, rr in rows], np.bool_).reshape(shape)
        hi_c = np.array([[x.hi_closed for x in rr] for _, rr in rows], np.bool_).reshape(shape)
        return cls(
            axes=axes,
            rows=rows,
            params=params,
            m_ms=m_ms,
            weights=tuple(m_ms // p.t_max_ms for p in params),
            lo=lo,
            hi=hi,
            lo_closed=lo_c,
            hi_closed=hi_c,
        )

    def _values(self, values: Sequence[float]) -> F64:
        if len(values) != len(self.axes):
            raise ValueError(f"need one value per axis {self.axes}, got {len(values)}")
        return np.array([float(x) for x in values], np.float64).reshape(1, 1, len(self.axes))

    def lookup(self, values: Sequence[float]) -> int:
        """Row index for fully known axis values (the table covers everything exactly once)."""
        vals = self._values(values)
        k = int(rules.lookup(self.lo, self.hi, self.lo_closed, self.hi_closed, vals, 0, 0))
        if k < 0:  # pragma: no cover
            raise AssertionError("validated table does not cover the point")
        return k

    def most_conservative(self, values: Sequence[float]) -> int:
        """Among rows consistent with the finite values (NaN = unknown), the highest cut-off;
        ties to the shortest t_max, then to the first row."""
        return int(
            rules.most_conservative(
                self.lo,
                self.hi,
                self.lo_closed,
                self.hi_closed,
                np.array([p for p, _ in self.rows], np.int64),
                np.array([p.cutoff_v for p in self.params], np.float64),
                np.array([p.t_max_s for p in self.params], np.float64),
                self._values(values),
                0,
                0,
            )
        )


def build(
    config: ProtectionConfig, infos: Sequence[PackInfo]
) -> tuple[ProtectionParams, ProtectionState]:
    table = CompiledTable.from_config(config)
    if table.m_ms > rules.M_MAX:
        raise ConfigError(
            f"protection: m = LCM of the t_max = {table.m_ms} ms is too large for the exact "
            f"sum (at most 2**43 ms); use rounder durations"
        )
    n = infos[0].n_batteries
    if any(pk.n_batteries != n for pk in infos):
        raise ConfigError("protection: every pack of a batch needs the same battery count")
    axes = table.axes
    names = [p.name.encode() for p in table.params]
    prm = ProtectionParams(
        axis_code=np.array([AXES.index(a) for a in axes], np.int64),
        row_param=np.array([p for p, _ in table.rows], np.int64),
        row_lo=table.lo,
        row_hi=table.hi,
        row_lo_closed=table.lo_closed,
        row_hi_closed=table.hi_closed,
        cutoff_v=np.array([float(p.cutoff_v) for p in table.params], np.float64),
        t_max_s=np.array([float(p.t_max_s) for p in table.params], np.float64),
        weight=np.array(table.weights, np.int64),
        m_ms=int(table.m_ms),
        band=np.array([float(config.hysteresis.get(a, 0.0)) for a in axes], np.float64),
        use_hysteresis=any(config.hysteresis.get(a, 0.0) > 0.0 for a in axes),
        tau_s=np.array([float(config.filter_tau_s.get(a, math.nan)) for a in axes], np.float64),
        has_filter=np.array([a in config.filter_tau_s for a in axes], np.bool_),
        voltage_le=config.voltage_comparison == "<=",
        trip_ge=config.trip_comparison == ">=",
        discharge_threshold_a=float(config.discharge_threshold_a),
        charge_threshold_a=float(config.charge_threshold_a),
        charge_detect_s=float(config.charge_detect_s),
        reset_on_recovery=bool(config.reset_on_recovery),
        reset_on_reinsert=bool(config.reset_on_reinsert),
        warn_share=float(config.warning_share),
        predict_tau_s=float(config.predict_tau_s),
        res_step_a=float(config.resistance_step_a),
        res_gain=float(config.resistance_gain),
        name_len=np.array([len(b) for b in names], np.int64),
        name_utf8=np.array(list(b"".join(names)), np.int64),
    )
    shape = (len(infos), n)
    na = len(axes)
    st = ProtectionState(
        acc_num=np.zeros(shape, np.int64),
        acc_den=np.ones(shape, np.int64),
        tripped=np.zeros(shape, np.bool_),
        row=np.full(shape, -1, np.int64),
        discharging=np.zeros(shape, np.bool_),
        charge_s=np.zeros(shape),
        charge_cycle_started=np.zeros(shape, np.bool_),
        absent=np.zeros(shape, np.bool_),
        filtered=np.full((*shape, na), np.nan),
        filtered_set=np.zeros((*shape, na), np.bool_),
        faults=np.zeros((*shape, rules.N_FIELDS), np.bool_),
        values=np.full((*shape, na), np.nan),
        warned=np.zeros(shape, np.bool_),
        v_prev=np.full(shape, np.nan),
        dvdt=np.full(shape, np.nan),
        r_est=np.full(shape, np.nan),
        r_i=np.full(shape, np.nan),
        r_v=np.full(shape, np.nan),
    )
    return prm, st


def param_names(prm: ProtectionParams) -> tuple[str, ...]:
    raw = bytes(int(b) for b in prm.name_utf8)
    out: list[str] = []
    k = 0
    for n in prm.name_len:
        out.append(raw[k : k + int(n)].decode())
        k += int(n)
    return tuple(out)


def labels(prm: ProtectionParams) -> Labels:
    return {
        "params": param_names(prm),
        "fields": FIELDS,
        "vsources": V_SOURCES,
        "resets": RESETS,
        "source": ("protection",),
    }


METHOD = Method(
    name="protection",
    src=0,
    config=ProtectionConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=labels,
    max_events=lambda info: rules.EVENTS_PER_BATTERY * info.n_batteries,
)


class BatteryView:
    """Read-only view of one battery's protection state (live: reads the state arrays)."""

    __slots__ = ("_ctl", "_i")

    def __init__(self, ctl: ProtectionController, battery: int) -> None:
        self._ctl = ctl
        self._i = battery

    @property
    def acc_wms(self) -> Fraction:
        """Weighted sum in weight x milliseconds (trip at m_ms)."""
        st = self._ctl.st
        return Fraction(int(st.acc_num[0, self._i]), int(st.acc_den[0, self._i]))

    @property
    def tripped(self) -> bool:
        return bool(self._ctl.st.tripped[0, self._i])

    @property
    def row(self) -> int:
        """Active table row (-1 before the first tick)."""
        return int(self._ctl.st.row[0, self._i])

    @property
    def discharging(self) -> bool:
        return bool(self._ctl.st.discharging[0, self._i])

    @property
    def resistance_ohm(self) -> float:
        """Cell-level internal resistance estimated from current steps (NaN before one)."""
        return float(self._ctl.st.r_est[0, self._i])

    @property
    def charge_s(self) -> float:
        return float(self._ctl.st.charge_s[0, self._i])

    @property
    def charge_cycle_started(self) -> bool:
        return bool(self._ctl.st.charge_cycle_started[0, self._i])

    @property
    def absent(self) -> bool:
        return bool(self._ctl.st.absent[0, self._i])

    @property
    def filtered(self) -> dict[str, float]:
        """Filtered value per filtered axis (once it had a finite reading)."""
        st, i = self._ctl.st, self._i
        return {
            a: float(st.filtered[0, i, k])
            for k, a in enumerate(self._ctl.table.axes)
            if st.filtered_set[0, i, k]
        }

    @property
    def faults(self) -> frozenset[str]:
        """Fields currently not finite (a Fault event is emitted once per episode)."""
        row = self._ctl.st.faults[0, self._i]
        return frozenset(name for k, name in enumerate(FIELDS) if row[k])


class ProtectionController(CompiledController):
    """Per-battery condition-dependent discharge protection (one pack); see ``rules.py``.

    Tick semantics: each call's measurement is taken to hold for ``dt_s``; the trip fires on the
    call whose ``dt_s`` makes the weighted sum reach ``m``. Commands: ``dsg_on=False`` for a
    tripped battery until its next discharge cycle, otherwise ``None`` (no opinion).
    """

    method = METHOD
    config: ProtectionConfig
    prm: ProtectionParams
    st: ProtectionState

    def __init__(self, config: ProtectionConfig, pack: PackInfo) -> None:
        super().__init__(config, pack)
        self.table = CompiledTable.from_config(self.config)

    @property
    def m_s(self) -> float:
        return self.table.m_ms / 1000.0

    def weights(self) -> dict[str, int]:
        return {p.name: n for p, n in zip(self.table.params, self.table.weights, strict=True)}

    def battery(self, battery: int) -> BatteryView:
        """Read-only view of a battery's protection state."""
        if not 0 <= battery < self.pack.n_batteries:
            raise IndexError(f"battery {battery} out of range")
        return BatteryView(self, battery)

    def parameter(self, battery: int) -> ProtectionParameter | None:
        """Active parameter of a battery (None before its first tick)."""
        row = int(self.st.row[0, battery])
        return None if row < 0 else self.table.params[self.table.rows[row][0]]

    def fraction(self, battery: int) -> float:
        """Used-up share of the allowance, sum(t_k / t_max_k): 0 .. 1 (and above at a trip)."""
        st = self.st
        return float(rules.acc_fraction(st.acc_num, st.acc_den, 0, battery, self.prm.m_ms))

    def start_new_cycle(self, battery: int) -> None:
        """Host command: clear the sum and the latch (e.g. battery charged off-pack)."""
        self.st.acc_num[0, battery] = 0
        self.st.acc_den[0, battery] = 1
        self.st.tripped[0, battery] = False
        self.st.warned[0, battery] = False

    def time_to_trip(self, battery: int) -> float:
        """Last published predicted time to trip (s; NaN = none predicted)."""
        return float(self._status[0, battery, rules.ST_TIME_TO_TRIP])


__all__ = [
    "METHOD",
    "REASONS",
    "STATUS",
    "BatteryView",
    "CompiledTable",
    "ProtectionController",
    "build",
    "labels",
]
