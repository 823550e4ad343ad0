"""ORACLE: the scalar equalization controller as it was before the compiled core (tests only;
deleted once the golden and equivalence tests pass). The passive top balancer it also held is a
benchmark baseline now (``benchmarks/baselines.py``).

Equalization of series battery groups by the Newton-iterated unit balancing Ah.

Method of CN102255114A (spec: ``/work/shared/spec/equalization.md``). Per string (one
:class:`~packpilot.contract.bms.BatteryMeasurement` = one string of series groups), every
sample period:

* ΔV_g = V_avg − V_g (positive = group g lags the string average);
* ΔV_g > ``dv_set_v`` for ``t1_s`` → AH_g ← (AH_g + N)/2 (formula 1), repeated every further
  ``t1_s`` while the condition persists; ΔV_g < ``dv_set_v`` for ``t2_s`` → AH_g ← AH_g/2
  (formula 2), likewise; equality resets both timers and updates nothing;
* if every AH_g > 0, the minimum is subtracted from all (S41/S42);
* at every AH update of group g (formula 1 or 2 applied, even when the value does not change,
  or the subtraction) its balancing time is recomputed, replacing what remained:
  t_g = 3600·AH_g/I with I the current the equalizer will carry (the string current clamped to
  ``equalizer_max_a``, or the fixed ``fixed_current_a``), clamped to ``max_balance_time_s``.

While t_g > 0 and the gate is open (|I_string| ≥ ``min_current_a``, or always in fixed-current
mode with ``balance_at_rest``) group g's equalizer pushes that current into the group and t_g
counts down. So AH_g is "the extra charge group g gets, relative to the least needy group,
until its next AH update" — the only reading under which subtracting a common minimum (S42)
changes nothing physical but the converter throughput.

The core is pure: :func:`sample_groups` and :func:`balancing_time_s` are plain functions that the
controller, the replay and the tests share.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

from packpilot.config.equalization import EqualizationConfig
from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
)
from packpilot.contract.topology import PackInfo

Formula = Literal["formula1", "formula2", "subtract_min"]

EVENT_MIN_CHANGE_AH = 1e-6
"""AH changes smaller than 1 µAh are applied and counted but not emitted as events: halving an
already negligible AH every ``t2_s`` would otherwise flood telemetry for hours."""

_SAMPLE_TOL = 1e-9


# --------------------------------------------------------------------------- pure functions


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


def formula1(ah: float, n_ah: float) -> float:
    """Newton-style averaging toward N: AH ← (AH + N)/2."""
    return (ah + n_ah) / 2.0


def formula2(ah: float) -> float:
    """Decay: AH ← AH/2."""
    return ah / 2.0


def sample_groups(
    voltages_v: Sequence[float],
    ah: Sequence[float],
    hi_timer_s: Sequence[float],
    lo_timer_s: Sequence[float],
    ts_s: float,
    config: EqualizationConfig,
) -> SampleResult:
    """Steps S1-S42 for one string: ΔV, persistence timers, formula 1/2, subtract-the-minimum.

    ``ts_s`` is the time this sample stands for (zero-order hold). A timer that reaches its set
    time fires and is reduced by it, so the update repeats every T1/T2 while the condition
    persists, and a long sample (ts_s ≥ k·T) applies the formula k times.
    """
    n = len(voltages_v)
    v_avg = math.fsum(voltages_v) / n
    new_ah = list(ah)
    hi = list(hi_timer_s)
    lo = list(lo_timer_s)
    dv = [v_avg - v for v in voltages_v]
    updates: list[AhUpdate] = []
    for g in range(n):
        if dv[g] > config.dv_set_v:
            hi[g] += ts_s
            lo[g] = 0.0
            while hi[g] >= config.t1_s - _SAMPLE_TOL:
                old = new_ah[g]
                new_ah[g] = formula1(old, config.n_ah)
                hi[g] = max(0.0, hi[g] - config.t1_s)
                updates.append(AhUpdate(g, "formula1", old, new_ah[g]))
        elif dv[g] < config.dv_set_v:
            lo[g] += ts_s
            hi[g] = 0.0
            while lo[g] >= config.t2_s - _SAMPLE_TOL:
                old = new_ah[g]
                new_ah[g] = formula2(old)
                lo[g] = max(0.0, lo[g] - config.t2_s)
                updates.append(AhUpdate(g, "formula2", old, new_ah[g]))
        else:
            hi[g] = 0.0
            lo[g] = 0.0
    subtracted = False
    if n > 0 and all(a > 0.0 for a in new_ah):
        m = min(new_ah)
        subtracted = True
        for g in range(n):
            old = new_ah[g]
            new_ah[g] = old - m
            updates.append(AhUpdate(g, "subtract_min", old, new_ah[g]))
    return SampleResult(
        ah=tuple(new_ah),
        hi_timer_s=tuple(hi),
        lo_timer_s=tuple(lo),
        dv_v=tuple(dv),
        updates=tuple(updates),
        subtracted_min=subtracted,
    )


def equalizer_current_a(string_current_a: float, config: EqualizationConfig) -> float:
    """Current one equalizer carries while balancing, or 0 when the gate is closed."""
    mag = abs(string_current_a)
    if config.time_mode == "fixed_current":
        if mag >= config.min_current_a or config.balance_at_rest:
            return config.fixed_current_a
        return 0.0
    if mag < config.min_current_a or mag == 0.0:
        return 0.0
    return min(mag, config.equalizer_max_a)


def balancing_time_s(ah: float, string_current_a: float, config: EqualizationConfig) -> float:
    """S43: seconds of balancing that deliver ``ah`` Ah at the equalizer current.

    The current is the one the equalizer will actually carry (string current clamped to its
    rating, or I_eq), so time × current = AH whenever the clamp to ``balance_time_clamp_s``
    does not bite. Zero when the gate is closed ("skip below a minimum current").
    """
    i_eq = equalizer_current_a(string_current_a, config)
    if ah <= 0.0 or i_eq <= 0.0:
        return 0.0
    return min(3600.0 * ah / i_eq, config.balance_time_clamp_s)


def lower_median(values: Sequence[float]) -> float:
    """The lower of the two middle values: ties favour not drawing charge from groups."""
    s = sorted(values)
    return s[(len(s) - 1) // 2]


# --------------------------------------------------------------------------- controller


@dataclass(slots=True)
class StringEqualizerState:
    """Mutable state of one string's equalizer: AH, timers, remaining times, ledger."""

    ah: list[float]
    hi_timer_s: list[float]
    lo_timer_s: list[float]
    remaining_s: list[float]
    dv_v: list[float]
    since_sample_s: float = 0.0
    faulted: bool = False
    ledger_time_s: list[float] = field(default_factory=list)
    """Seconds each group's balancing was active (prorated on the last partial step)."""
    ledger_gross_ah: list[float] = field(default_factory=list)
    """Charge the AH rule commanded into each group: Σ I_eq·time/3600."""
    ledger_net_ah: list[float] = field(default_factory=list)
    """Charge actually commanded (after the bidirectional median shift): Σ balancer_a·dt/3600."""
    counts: dict[str, int] = field(default_factory=dict)

    @classmethod
    def empty(cls, n_groups: int) -> StringEqualizerState:
        z = [0.0] * n_groups
        return cls(
            ah=list(z),
            hi_timer_s=list(z),
            lo_timer_s=list(z),
            remaining_s=list(z),
            dv_v=[math.nan] * n_groups,
            ledger_time_s=list(z),
            ledger_gross_ah=list(z),
            ledger_net_ah=list(z),
            counts={"formula1": 0, "formula2": 0, "subtract_min": 0},
        )

    def hold(self) -> None:
        """Forget persistence and pending balancing (sensor fault or battery removed)."""
        n = len(self.ah)
        self.hi_timer_s = [0.0] * n
        self.lo_timer_s = [0.0] * n
        self.remaining_s = [0.0] * n
        self.dv_v = [math.nan] * n
        self.since_sample_s = 0.0


def _input_problem(bm: BatteryMeasurement, n_groups: int) -> str | None:
    """Why this battery's inputs cannot drive the equalizer, or None. Only checks what the
    method uses (group voltages and string current): a NaN temperature must not stop it."""
    if len(bm.group_voltages_v) != n_groups:
        return f"expected {n_groups} group voltages, got {len(bm.group_voltages_v)}"
    for g, v in enumerate(bm.group_voltages_v):
        if not math.isfinite(v) or v <= 0.0:
            return f"group {g} voltage {v} is not a positive finite number"
    if not math.isfinite(bm.current_a):
        return f"string current {bm.current_a} is not finite"
    return None


class EqualizationController:
    """One Newton-iterated equalizer per string; commands ``Commands.balancer_a``.

    Fail-safe: a string whose group voltages or current are NaN/non-positive/missing gets all
    its equalizers at 0 A, its timers and remaining times cleared (AH is kept) and one
    ``Fault`` event; ``FaultCleared`` is emitted when valid data returns. An absent battery is
    idled silently.
    """

    def __init__(self, config: EqualizationConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.strings = [StringEqualizerState.empty(m) for m in pack.groups_per_battery]

    def _sample(
        self, b: int, st: StringEqualizerState, bm: BatteryMeasurement, ts_s: float, t_s: float
    ) -> list[Event]:
        res = sample_groups(
            bm.group_voltages_v, st.ah, st.hi_timer_s, st.lo_timer_s, ts_s, self.config
        )
        st.ah = list(res.ah)
        st.hi_timer_s = list(res.hi_timer_s)
        st.lo_timer_s = list(res.lo_timer_s)
        st.dv_v = list(res.dv_v)
        events: list[Event] = []
        updated: set[int] = set()
        for u in res.updates:
            if u.formula != "subtract_min":
                st.counts[u.formula] += 1
            # Every application counts, even one that leaves AH unchanged: formula 1 at
            # AH = N must re-grant the balancing time of a group that still lags.
            updated.add(u.group)
            if abs(u.new_ah - u.old_ah) >= EVENT_MIN_CHANGE_AH:
                events.append(
                    Event(
                        t_s=t_s,
                        kind="BalancingUpdated",
                        battery=b,
                        message=f"group {u.group} AH {u.old_ah:.4f} -> {u.new_ah:.4f} "
                        f"({u.formula})",
                        data={
                            "group": u.group,
                            "formula": u.formula,
                            "old": u.old_ah,
                            "new": u.new_ah,
                            "dv_v": res.dv_v[u.group],
                        },
                    )
                )
        if res.subtracted_min:
            st.counts["subtract_min"] += 1
        for g in updated:
            st.remaining_s[g] = balancing_time_s(st.ah[g], bm.current_a, self.config)
        return events

    def _drive(self, st: StringEqualizerState, current_a: float, dt_s: float) -> list[float]:
        """Equalizer currents for the next ``dt_s``; counts remaining time down, books ledger."""
        n = len(st.ah)
        i_eq = equalizer_current_a(current_a, self.config)
        gross = [0.0] * n
        if i_eq > 0.0 and dt_s > 0.0:
            for g in range(n):
                used = min(st.remaining_s[g], dt_s)
                if used <= 0.0:
                    continue
                # Prorate the last partial step so that charge = time × current exactly.
                gross[g] = i_eq * used / dt_s
                st.remaining_s[g] -= used
                st.ledger_time_s[g] += used
                st.ledger_gross_ah[g] += i_eq * used / 3600.0
        net = list(gross)
        if self.config.equalizer == "bidirectional" and n > 1:
            shift = lower_median(gross)
            net = [x - shift for x in gross]
        for g in range(n):
            st.ledger_net_ah[g] += net[g] * dt_s / 3600.0
        return net

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
        events: list[Event] = []
        currents: list[tuple[float, ...]] = []
        faults: list[bool] = []
        for b, st in enumerate(self.strings):
            n = len(st.ah)
            bm = meas.batteries[b] if b < len(meas.batteries) else None
            if bm is None or not bm.present:
                st.hold()
                currents.append((0.0,) * n)
                faults.append(False)
                continue
            problem = _input_problem(bm, n)
            if problem is not None:
                if not st.faulted:
                    events.append(
                        Event(
                            t_s=meas.t_s,
                            kind="Fault",
                            battery=b,
                            message=f"equalization stopped: {problem}",
                            data={"source": "equalization"},
                        )
                    )
                st.faulted = True
                st.hold()
                currents.append((0.0,) * n)
                faults.append(True)
                continue
            if st.faulted:
                st.faulted = False
                events.append(
                    Event(
                        t_s=meas.t_s,
                        kind="FaultCleared",
                        battery=b,
                        message="equalization resumed: group voltages valid again",
                        data={"source": "equalization"},
                    )
                )
            st.since_sample_s += dt
            if n > 0 and st.since_sample_s >= self.config.sample_period_s * (1.0 - _SAMPLE_TOL):
                ts = st.since_sample_s
                st.since_sample_s = 0.0
                events.extend(self._sample(b, st, bm, ts, meas.t_s))
            currents.append(tuple(self._drive(st, bm.current_a, dt)))
            faults.append(False)
        status = self._status(currents, faults)
        balancer = tuple(currents) if self.pack.has_balancers else None
        return ControlOutput(
            commands=Commands(balancer_a=balancer), events=tuple(events), status=status
        )

    def _status(
        self, currents: list[tuple[float, ...]], faults: list[bool]
    ) -> dict[str, list[float | int | str | bool | None]]:
        """Channels ``eq_dv_mv_g{k}``, ``eq_ah_g{k}``, ``eq_time_s_g{k}``, ``eq_i_a_g{k}``,
        ``eq_fault``; None for a group a battery does not have. ``eq_time_s`` is the remaining
        balancing time after this step."""
        m = max((len(s.ah) for s in self.strings), default=0)
        out: dict[str, list[float | int | str | bool | None]] = {"eq_fault": list(faults)}
        for k in range(m):
            dv: list[float | int | str | bool | None] = []
            ah: list[float | int | str | bool | None] = []
            tm: list[float | int | str | bool | None] = []
            cur: list[float | int | str | bool | None] = []
            for b, s in enumerate(self.strings):
                if k < len(s.ah):
                    dv.append(s.dv_v[k] * 1000.0)
                    ah.append(s.ah[k])
                    tm.append(s.remaining_s[k])
                    cur.append(currents[b][k])
                else:
                    dv.append(None)
                    ah.append(None)
                    tm.append(None)
                    cur.append(None)
            out[f"eq_dv_mv_g{k}"] = dv
            out[f"eq_ah_g{k}"] = ah
            out[f"eq_time_s_g{k}"] = tm
            out[f"eq_i_a_g{k}"] = cur
        return out


__all__ = [
    "EVENT_MIN_CHANGE_AH",
    "AhUpdate",
    "EqualizationConfig",
    "EqualizationController",
    "SampleResult",
    "StringEqualizerState",
    "balancing_time_s",
    "equalizer_current_a",
    "formula1",
    "formula2",
    "lower_median",
    "sample_groups",
]
