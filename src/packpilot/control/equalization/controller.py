"""Equalization as a core method, and its one-pack face :class:`EqualizationController`.

The status channels depend on the topology: ``eq_fault``, then ``eq_dv_mv_g{k}``,
``eq_ah_g{k}``, ``eq_time_s_g{k}``, ``eq_i_a_g{k}`` and ``eq_owed_ah_g{k}`` for every group k of
the largest
battery (None for a battery with fewer groups). :data:`METHOD` declares them for
:data:`MAX_GROUPS` groups, which bounds the memory any pack's kernel may write; a core that
runs a given topology takes :func:`method_for` (exactly the channels of its groups) and
renders them with :func:`status_of` (the None of the missing groups).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from packpilot.config.equalization import EqualizationConfig
from packpilot.contract.arrays import (
    clear_commands,
    commands,
    put_measurements,
)
from packpilot.contract.bms import ControlOutput, Measurements, StatusValue
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.equalization import rules
from packpilot.control.equalization.rules import (
    EVENT_RESOLUTION_AH,
    EqParams,
    EqState,
    formula1,
    formula2,
)
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.errors import ConfigError

F64 = NDArray[np.float64]

Formula = Literal["formula1", "formula2", "subtract_min"]
FORMULAS: tuple[Formula, ...] = ("formula1", "formula2", "subtract_min")
"""Indexed by ``rules.FORMULA1`` / ``FORMULA2`` / ``SUBTRACT_MIN``."""

MAX_GROUPS = 64
"""Most series groups per battery the method's declared status layout covers."""

EVENTS_PER_GROUP = 24
"""Room for ``BalancingUpdated`` events of one group in one step. A formula moves AH by half
its distance to N (or to 0) and AH stays within 0..1 Ah, so changes of more than
``EVENT_RESOLUTION_AH`` number at most 14 per sample however long it stands for; one more
for the subtraction. (Events beyond the room would be counted in ``EventBuf.dropped``.)"""

_SOURCE = "source:l:source"
REASONS = (
    Reason(
        "BalancingUpdated",
        "group {group} AH {old:.4f} -> {new:.4f} ({formula})",
        fields("group:i", "formula:l:formula", "old", "new", "dv_v"),
    ),
    Reason(
        "Fault",
        "equalization stopped: expected {expected} group voltages, got {got}",
        fields(_SOURCE, "_expected:i", "_got:i"),
    ),
    Reason(
        "Fault",
        "equalization stopped: group {group} voltage {v} is not a positive finite number",
        fields(_SOURCE, "_group:i", "_v"),
    ),
    Reason(
        "Fault",
        "equalization stopped: string current {current} is not finite",
        fields(_SOURCE, "_current"),
    ),
    Reason(
        "FaultCleared",
        "equalization resumed: group voltages valid again",
        fields(_SOURCE),
    ),
)
LABELS: Labels = {"formula": FORMULAS, "source": ("equalization",)}


def status_channels(n_groups: int) -> tuple[StatusChannel, ...]:
    """``eq_fault`` and the five channels of each of ``n_groups`` groups, in the kernel's
    order (``1 + 5k + j``)."""
    out = [StatusChannel("eq_fault", "b")]
    for k in range(n_groups):
        out += [
            StatusChannel(f"eq_dv_mv_g{k}"),
            StatusChannel(f"eq_ah_g{k}"),
            StatusChannel(f"eq_time_s_g{k}"),
            StatusChannel(f"eq_i_a_g{k}"),
            StatusChannel(f"eq_owed_ah_g{k}"),
        ]
    return tuple(out)


STATUS = status_channels(MAX_GROUPS)


def params(config: EqualizationConfig, status_groups: int = 0) -> EqParams:
    """The kernels' view of ``config`` (``status_groups``: groups of the status layout)."""
    return EqParams(
        dv_set_v=float(config.dv_set_v),
        t1_s=float(config.t1_s),
        t2_s=float(config.t2_s),
        n_ah=float(config.n_ah),
        sample_period_s=float(config.sample_period_s),
        fixed_current=config.time_mode == "fixed_current",
        min_current_a=float(config.min_current_a),
        equalizer_max_a=float(config.equalizer_max_a),
        fixed_current_a=float(config.fixed_current_a),
        balance_at_rest=bool(config.balance_at_rest),
        bidirectional=config.equalizer == "bidirectional",
        status_groups=int(status_groups),
    )


def new_state(
    n_packs: int, n_batteries: int, n_groups: int, events: int = 0, log: int = 0
) -> EqState:
    """Fresh state: AH 0, timers 0, no ΔV yet (NaN); room for ``events`` recorded events per
    pack and step, and for ``log`` updates of a sample."""
    g = max(n_groups, 1)
    shape = (n_packs, n_batteries, g)

    def zeros() -> F64:
        return np.zeros(shape)

    return EqState(
        ah=zeros(),
        hi_timer_s=zeros(),
        lo_timer_s=zeros(),
        owed_ah=zeros(),
        remaining_s=zeros(),
        dv_v=np.full(shape, np.nan),
        current_a=zeros(),
        ledger_time_s=zeros(),
        ledger_granted_ah=zeros(),
        ledger_gross_ah=zeros(),
        ledger_net_ah=zeros(),
        since_sample_s=np.zeros((n_packs, n_batteries)),
        faulted=np.zeros((n_packs, n_batteries), np.bool_),
        counts=np.zeros((n_packs, n_batteries, 3), np.int64),
        partials=np.zeros((n_packs, g)),
        sort_buf=np.zeros((n_packs, g)),
        updated=np.zeros((n_packs, g), np.bool_),
        rec_n=np.zeros(n_packs, np.int64),
        rec_code=np.zeros((n_packs, events, 2), np.int64),
        rec_val=np.zeros((n_packs, events, 5)),
        log=np.zeros((n_packs, log, 4)),
        log_n=np.zeros(n_packs, np.int64),
    )


def _max_events(info: PackInfo) -> int:
    return sum(2 + EVENTS_PER_GROUP * g for g in info.groups_per_battery)


def build(config: EqualizationConfig, infos: Sequence[PackInfo]) -> tuple[EqParams, EqState]:
    info = infos[0]
    groups = tuple(info.groups_per_battery)
    if len(groups) != info.n_batteries:
        raise ConfigError(
            f"equalization: PackInfo gives {len(groups)} group counts for "
            f"{info.n_batteries} batteries"
        )
    g = max(groups, default=0)
    if g > MAX_GROUPS:
        raise ConfigError(
            f"equalization: a battery has {g} series groups, at most {MAX_GROUPS} supported"
        )
    return params(config, g), new_state(len(infos), info.n_batteries, g, _max_events(info))


def _labels(prm: EqParams) -> Labels:
    return LABELS


METHOD = Method(
    name="equalization",
    src=3,
    config=EqualizationConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=_labels,
    max_events=_max_events,
)


def method_for(config: EqualizationConfig, infos: Sequence[PackInfo]) -> Method:
    """:data:`METHOD` with exactly the status channels of this topology (any config)."""
    return dataclasses.replace(
        METHOD, status=status_channels(max(infos[0].groups_per_battery, default=0))
    )


def status_of(
    status: F64, p: int, s0: int, groups: Sequence[int], n_groups: int
) -> dict[str, list[StatusValue]]:
    """The status channels of pack ``p`` as the scalar contract has them: ``eq_fault`` a bool,
    the group channels floats (NaN stays NaN), None where a battery has no group k."""
    out: dict[str, list[StatusValue]] = {
        "eq_fault": [bool(x != 0.0) for x in status[p, :, s0 + rules.ST_FAULT]]
    }
    names = ("eq_dv_mv_g", "eq_ah_g", "eq_time_s_g", "eq_i_a_g", "eq_owed_ah_g")
    for k in range(n_groups):
        c = s0 + 1 + rules.PER_GROUP * k
        for j, name in enumerate(names):
            col = status[p, :, c + j]
            out[f"{name}{k}"] = [
                float(col[i]) if k < groups[i] else None for i in range(len(groups))
            ]
    return out


# --------------------------------------------------------------------------- pure helpers


@dataclass(frozen=True, slots=True)
class AhUpdate:
    """One application of a rule to one group's AH."""

    group: int
    formula: Formula
    old_ah: float
    new_ah: float


@dataclass(frozen=True, slots=True)
class SampleResult:
    """State of one string after one sample of S1-S42."""

    ah: tuple[float, ...]
    hi_timer_s: tuple[float, ...]
    lo_timer_s: tuple[float, ...]
    dv_v: tuple[float, ...]
    updates: tuple[AhUpdate, ...]
    subtracted_min: bool


def equalizer_current_a(string_current_a: float, config: EqualizationConfig) -> float:
    """Current one equalizer carries while balancing, or 0 when the gate is closed."""
    return float(rules.equalizer_current(params(config), float(string_current_a)))


def balancing_time_s(ah: float, string_current_a: float, config: EqualizationConfig) -> float:
    """S43: seconds of balancing that deliver ``ah`` Ah at the equalizer current.

    The current is the one the equalizer will actually carry (string current clamped to its
    rating, or I_eq), so time × current = AH: proportional to AH, never clamped (an update
    period too short to deliver it leaves the rest owed). Zero when the gate is closed ("skip
    below a minimum current").
    """
    return float(rules.balancing_time(params(config), float(ah), float(string_current_a)))


def lower_median(values: Sequence[float]) -> float:
    """The lower of the two middle values: ties favour not drawing charge from groups."""
    xs = np.array([float(x) for x in values], np.float64)
    if xs.shape[0] == 0:
        raise IndexError("lower_median of no values")
    return float(rules.lower_median(xs, xs.shape[0], np.empty_like(xs)))


def _log_size(n: int, ts_s: float, timers: Sequence[float], config: EqualizationConfig) -> int:
    """Room for every update one sample can make: each timer fires at most (timer + ts)/T2
    + 1 times (T2 < T1), and the subtraction once per group."""
    longest = max((abs(x) for x in timers), default=0.0) + abs(ts_s)
    if not math.isfinite(longest):
        longest = 0.0  # a NaN timer never fires (an infinite one never stops, as before)
    return n * (int(longest / config.t2_s) + 3)


def sample_groups(
    voltages_v: Sequence[float],
    ah: Sequence[float],
    hi_timer_s: Sequence[float],
    lo_timer_s: Sequence[float],
    ts_s: float,
    config: EqualizationConfig,
) -> SampleResult:
    """Steps S1-S42 for one string, by the rule kernel: ΔV, persistence timers, formula 1/2,
    subtract-the-minimum.

    ``ts_s`` is the time this sample stands for (zero-order hold). A timer that reaches its set
    time fires and is reduced by it, so the update repeats every T1/T2 while the condition
    persists, and a long sample (ts_s ≥ k·T) applies the formula k times.
    """
    n = len(voltages_v)
    if n == 0:
        raise ZeroDivisionError("sample_groups needs at least one group voltage")
    prm = params(config)
    log = _log_size(n, float(ts_s), [*hi_timer_s, *lo_timer_s], config)
    st = new_state(1, 1, n, log=log)  # no room for events: only the log is read
    st.ah[0, 0, :n] = [float(x) for x in ah]
    st.hi_timer_s[0, 0, :n] = [float(x) for x in hi_timer_s]
    st.lo_timer_s[0, 0, :n] = [float(x) for x in lo_timer_s]
    gv = np.array([float(x) for x in voltages_v], np.float64).reshape(1, 1, n)
    sub = rules.sample_string(prm, st, gv, 0, 0, n, float(ts_s), math.nan)
    k = int(st.log_n[0])
    assert k <= log, (k, log)
    updates = tuple(
        AhUpdate(
            int(st.log[0, j, 0]),
            FORMULAS[int(st.log[0, j, 1])],
            float(st.log[0, j, 2]),
            float(st.log[0, j, 3]),
        )
        for j in range(k)
    )

    def row(a: F64) -> tuple[float, ...]:
        return tuple(float(x) for x in a[0, 0, :n])

    return SampleResult(
        ah=row(st.ah),
        hi_timer_s=row(st.hi_timer_s),
        lo_timer_s=row(st.lo_timer_s),
        dv_v=row(st.dv_v),
        updates=updates,
        subtracted_min=bool(sub),
    )


# --------------------------------------------------------------------------- one pack


class _Row:
    """A per-group quantity of one string, as a list (read) or from a sequence (write)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __get__(self, view: StringView, owner: type | None = None) -> list[float]:
        a = getattr(view.ctrl.st, self.name)
        return [float(x) for x in a[0, view.battery, : view.n_groups]]

    def __set__(self, view: StringView, values: Sequence[float]) -> None:
        if self.name == "remaining_s":
            raise AttributeError("remaining_s is derived from owed_ah: write owed_ah")
        a = getattr(view.ctrl.st, self.name)
        vals = [float(x) for x in values]
        if len(vals) != view.n_groups:
            raise ValueError(f"{self.name}: {len(vals)} values for {view.n_groups} groups")
        a[0, view.battery, : view.n_groups] = vals


class StringView:
    """One string's equalizer state (AH, timers, owed Ah, remaining times, ledger, counts),
    read from and written into the controller's state arrays."""

    ah = _Row("ah")
    hi_timer_s = _Row("hi_timer_s")
    lo_timer_s = _Row("lo_timer_s")
    owed_ah = _Row("owed_ah")
    """Charge granted and not yet delivered (carried over until delivered)."""
    remaining_s = _Row("remaining_s")
    """Time to deliver ``owed_ah`` at the present equalizer current (read-only)."""
    dv_v = _Row("dv_v")
    ledger_time_s = _Row("ledger_time_s")
    """Seconds each group's balancing was active (prorated on the last partial step)."""
    ledger_granted_ah = _Row("ledger_granted_ah")
    """Charge granted by S43 (the changes of the owed Ah at the updates): delivered + owed."""
    ledger_gross_ah = _Row("ledger_gross_ah")
    """Charge the AH rule delivered into each group: Σ I_eq·time/3600."""
    ledger_net_ah = _Row("ledger_net_ah")
    """Charge actually commanded (after the bidirectional median shift): Σ balancer_a·dt/3600."""

    def __init__(self, ctrl: EqualizationController, battery: int) -> None:
        self.ctrl = ctrl
        self.battery = battery
        self.n_groups = int(ctrl.pack.groups_per_battery[battery])

    @property
    def since_sample_s(self) -> float:
        return float(self.ctrl.st.since_sample_s[0, self.battery])

    @property
    def faulted(self) -> bool:
        return bool(self.ctrl.st.faulted[0, self.battery])

    @property
    def counts(self) -> dict[str, int]:
        st, b = self.ctrl.st, self.battery
        return {name: int(st.counts[0, b, k]) for k, name in enumerate(FORMULAS)}


class EqualizationController(CompiledController):
    """One Newton-iterated equalizer per string; commands ``Commands.balancer_a``.

    Fail-safe: a string whose group voltages or current are NaN/non-positive/missing gets all
    its equalizers at 0 A, its timers cleared (AH and the owed Ah are kept) and one
    ``Fault`` event; ``FaultCleared`` is emitted when valid data returns. An absent battery is
    idled silently. ``strings[b]`` reads (and, for tests, writes) string b's state.
    """

    method = METHOD
    prm: EqParams
    st: EqState

    def __init__(self, config: EqualizationConfig, pack: PackInfo) -> None:
        super().__init__(config, pack)
        self._groups = tuple(int(g) for g in pack.groups_per_battery)
        channels = status_channels(self.prm.status_groups)
        self._status = np.full((1, pack.n_batteries, len(channels)), np.nan)
        self.strings = [StringView(self, b) for b in range(pack.n_batteries)]

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        put_measurements(self._m, 0, meas)
        clear_commands(self._cmd)
        self._ev.n[0] = 0
        rules.step_packs(
            self.prm, self.st, self.tp, self._m, float(dt_s), self._cmd, self._ev,
            0, self._status, 0,
        )  # fmt: skip
        return ControlOutput(
            commands=commands(self._cmd, 0, self._groups),
            events=tuple(self.events()),
            status=status_of(self._status, 0, 0, self._groups, self.prm.status_groups),
        )


__all__ = [
    "EVENT_RESOLUTION_AH",
    "FORMULAS",
    "MAX_GROUPS",
    "METHOD",
    "REASONS",
    "STATUS",
    "AhUpdate",
    "EqualizationController",
    "SampleResult",
    "StringView",
    "balancing_time_s",
    "build",
    "equalizer_current_a",
    "formula1",
    "formula2",
    "lower_median",
    "method_for",
    "new_state",
    "params",
    "sample_groups",
    "status_channels",
    "status_of",
]
