"""ORACLE: the scalar staged-charging controller as it was before the compiled core (tests
only; deleted once the golden and equivalence tests pass).

Staged charging of a multi-battery pack on one busbar (``spec/staged_charging.md``).

Tying unequally discharged batteries to the charging busbar at once makes the emptiest one draw
a large current (and the fuller ones discharge into it). Instead, every control period the
traction batteries are sorted and grouped into voltage *levels*; only the lowest level (the
"first batteries") is charged up to just below the next level (S20), then the two lowest levels
are charged together (S30), and so on until all batteries sit on one level, which is then
charged in bounded steps (S40) and finally topped off to V_sat at constant voltage.

Design decisions (the spec's [I]/[REC] points, see ``docs/staged_charging.md``):

* **Voltages "while charging" (spec §7.7)** include the I·R rise, and batteries connected in
  parallel all show the same terminal voltage. Decisions therefore use an IR-compensated
  voltage ``v_est = v + i·R`` (``i`` positive = discharge), with ``R`` learned online from
  current steps (relay closing/opening, setpoint changes): ``R = -ΔV/ΔI`` between consecutive
  samples, filtered. The "battery is full" test uses the raw terminal voltage and the
  termination current, as a CC/CV charger does.
* **Levels** are built on the sorted ``v_est``: a new level starts when a voltage exceeds the
  current level's lowest voltage by more than ``eps_eq``, so a level never spans more than
  ``eps_eq`` (a level closed in parallel circulates at most ``eps_eq / R``).
* **Latching**: each stage keeps its members and setpoints until its own exit condition
  (S20: first batteries reach Vr1; S30: the connected levels merge or reach Vt; S40: reach
  Vr2), or until the grouping changes structurally. Only then is a fresh decision taken, so
  measurement noise cannot toggle relays every period.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from packpilot.config.charging import REFERENCE_SERIES, VOLTAGE_FIELDS, ChargingConfig
from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
)
from packpilot.contract.charger import (
    CHARGER_OFF,
    ChargerCommand,
    ChargerStatus,
)
from packpilot.contract.topology import PackInfo
from packpilot.errors import ConfigError


class Stage(enum.StrEnum):
    """Charging stage; ``S20``/``S30``/``S40`` are the spec's steps."""

    IDLE = "idle"
    """Not docked: no opinion on relays, charger off."""
    REST = "rest"
    """Just docked: relays open, charger off, waiting ``dock_rest_s`` for rest voltages."""
    HOLD = "hold"
    """Docked but no battery can be charged right now (all invalid or absent)."""
    S20 = "S20"
    S30 = "S30"
    S40 = "S40"
    TOP_OFF = "top_off"
    COMPLETE = "complete"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class Volts:
    """Battery-level voltage settings resolved from the config and the series count."""

    delta_v1: float
    d1: float
    k1: float
    k2: float
    k3: float
    step: float
    delta_v2: float
    eps_eq: float
    reach_tol: float
    v_sat: float
    overvoltage_margin: float

    @classmethod
    def resolve(cls, cfg: ChargingConfig, pack: PackInfo) -> Volts:
        scale = 1.0
        if cfg.voltage_basis == "cell":
            series = set(series_cells(pack))
            if len(series) != 1:
                raise ConfigError(
                    "charging.voltage_basis = 'cell' needs batteries with one common series "
                    f"cell count, got {series_cells(pack)}"
                )
            scale = float(series.pop())
        return cls(*(getattr(cfg, name) * scale for name in VOLTAGE_FIELDS))


def series_cells(pack: PackInfo) -> list[int]:
    """Cells in series per battery: groups in series, each group ``cells_per_group`` in series."""
    cells = list(pack.cells_per_group) + [1] * (
        len(pack.groups_per_battery) - len(pack.cells_per_group)
    )
    return [g * c for g, c in zip(pack.groups_per_battery, cells, strict=True)]


@dataclass(slots=True)
class Plan:
    """A latched stage: who is connected, the setpoints and why."""

    stage: Stage
    members: frozenset[int] = frozenset()
    first: tuple[int, ...] = ()
    second: tuple[int, ...] = ()
    cmd_v: float = math.nan
    vr1_v: float = math.nan
    vt_v: float = math.nan
    vr2_v: float = math.nan

    @property
    def target_v(self) -> float:
        """The voltage this stage charges towards (for telemetry)."""
        if self.stage is Stage.S20:
            return self.vr1_v
        if self.stage is Stage.S30:
            return self.vt_v
        if self.stage is Stage.S40:
            return self.vr2_v
        if self.stage is Stage.TOP_OFF:
            return self.cmd_v
        return math.nan

    def same_as(self, other: Plan) -> bool:
        return (
            self.stage is other.stage
            and self.members == other.members
            and _same(self.cmd_v, other.cmd_v)
        )


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


@dataclass(slots=True)
class StepRef:
    """A current step being followed for the settled resistance estimate."""

    v0: float
    i0: float
    i1: float
    t1: float
    r_step: float
    v_mid: float = math.nan


@dataclass(slots=True)
class ChargingState:
    """Everything the controller remembers between periods (explicit, for inspection)."""

    plan: Plan = field(default_factory=lambda: Plan(Stage.IDLE))
    r_ohm: list[float] = field(default_factory=list)
    r_kind: list[int] = field(default_factory=list)
    """Per battery: 0 = no estimate yet, 1 = from a step, 2 = settled (incl. polarization)."""
    step_ref: list[StepRef | None] = field(default_factory=list)
    """Per battery: the last current step, followed for the settled R estimate."""
    clock_s: float = 0.0
    prev_v: list[float] = field(default_factory=list)
    prev_i: list[float] = field(default_factory=list)
    done: list[str] = field(default_factory=list)
    """Per battery: '' (chargeable) or why it is out for this session ('full', 'cell_limit',
    'overvoltage'). Cleared on undocking."""
    invalid: list[bool] = field(default_factory=list)
    no_status_s: float = 0.0
    fault_clear_s: float = 0.0
    charger_fault: str = ""
    session_s: float = 0.0
    rested: bool = False
    aux_charging: bool = False
    aux_invalid: bool = False


def cluster_levels(values: Sequence[tuple[int, float]], eps_v: float) -> list[list[int]]:
    """Group ``(index, voltage)`` pairs into levels of span ≤ ``eps_v``, lowest level first.

    Sorting is by voltage then index, so ties are deterministic. A level is anchored at its
    lowest voltage (not single-linkage), so a chain of small gaps cannot grow one level wider
    than ``eps_v``.
    """
    levels: list[list[int]] = []
    anchor = -math.inf
    for idx, v in sorted(values, key=lambda p: (p[1], p[0])):
        if not levels or v - anchor > eps_v:
            levels.append([idx])
            anchor = v
        else:
            levels[-1].append(idx)
    return levels


def stage_current_a(cfg: ChargingConfig, n_connected: int, n_to_charge: int) -> float:
    """Charger current limit for a stage with ``n_connected`` of ``n_to_charge`` batteries.

    Always ``≤ charger_current_limit_a`` and, if set, ``≤ n_connected × battery_current_limit_a``.
    With ``current_law = "sqrt"`` also ``≤ I_full·sqrt(n_connected / n_to_charge)``: a stage
    that delivers charge Q through n similar batteries of resistance R at current I heats them
    by ≈ Q·I·R/n in Q/I seconds, and minimising Σ Q_k·I_k·R/n_k for a fixed Σ Q_k/I_k
    (Lagrange) gives I_k ∝ sqrt(n_k): the same heat rate I_k²·R/n_k in every stage.
    """
    current = cfg.charger_current_limit_a
    n = max(n_connected, 1)
    if cfg.current_law == "sqrt":
        full = cfg.full_current_a if cfg.full_current_a is not None else current
        current = min(current, full * math.sqrt(n / max(n_to_charge, n)))
    if cfg.battery_current_limit_a is not None:
        current = min(current, n * cfg.battery_current_limit_a)
    return current


def _fmt_idx(idx: Iterable[int]) -> str:
    return ",".join(str(i) for i in sorted(idx))


class ChargingController:
    """Staged charging: S20 → S30 per level pair, S40 steps, CV top-off, relays per battery.

    ``step`` is deterministic and never raises on bad measurements: a battery with a
    non-finite reading is left out of the sort with its relay open (``Fault`` event once);
    charger faults stop the charger and open every relay until the charger has reported
    healthy for ``charger_fault_clear_s``.
    """

    def __init__(self, config: ChargingConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.volts = Volts.resolve(config, pack)
        n = pack.n_batteries
        self.series = series_cells(pack) or [1] * n
        self.state = ChargingState(
            r_ohm=[config.r_comp_initial_ohm] * n,
            r_kind=[0] * n,
            step_ref=[None] * n,
            prev_v=[math.nan] * n,
            prev_i=[math.nan] * n,
            done=[""] * n,
            invalid=[False] * n,
        )

    # ----------------------------------------------------------------------------------------
    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        cfg, st, n = self.config, self.state, self.pack.n_batteries
        dt = dt_s if math.isfinite(dt_s) and dt_s > 0.0 else 0.0
        t = meas.t_s
        events: list[Event] = []
        bats = list(meas.batteries[:n])
        valid = [i < len(bats) and bats[i].present and bats[i].is_finite() for i in range(n)]
        self._validity_events(bats, valid, t, events)
        st.clock_s += dt
        self._update_resistance(bats, valid)
        r_use = self._r_for_compensation()
        est = [
            bats[i].voltage_v + bats[i].current_a * r_use[i] if valid[i] else math.nan
            for i in range(n)
        ]
        aux_relay, aux_a = self._aux(meas, dt, events)

        if not meas.docked:
            if st.plan.stage is not Stage.IDLE:
                self._set_plan(Plan(Stage.IDLE), t, events, reason="undocked")
            self._reset_session()
            return self._output((None,) * n, CHARGER_OFF, aux_relay, aux_a, est, events)

        if st.plan.stage is not Stage.IDLE:
            st.session_s += dt  # the first docked period starts the session clock at 0
        fault = self._charger_health(meas.charger, dt)
        if fault:
            if st.plan.stage is not Stage.FAULT or fault != st.charger_fault:
                events.append(
                    Event(t, "Fault", message=f"charger: {fault}", data=_charger_data(meas))
                )
            st.charger_fault = fault
            st.fault_clear_s = 0.0
            self._set_plan(Plan(Stage.FAULT), t, events, reason=fault)
            return self._output((False,) * n, CHARGER_OFF, aux_relay, aux_a, est, events)
        if st.plan.stage is Stage.FAULT:
            st.fault_clear_s += dt
            if st.fault_clear_s < cfg.charger_fault_clear_s:
                return self._output((False,) * n, CHARGER_OFF, aux_relay, aux_a, est, events)
            st.charger_fault = ""  # the fresh decision below is reported as a stage change

        if st.plan.stage is Stage.COMPLETE:
            charger = self._aux_only_charger(aux_relay)
            return self._output((False,) * n, charger, aux_relay, aux_a, est, events)
        if not st.rested:
            if st.plan.stage is not Stage.REST:
                self._set_plan(Plan(Stage.REST), t, events, reason="docked")
            st.rested = st.session_s >= cfg.dock_rest_s
            if not st.rested:
                return self._output((False,) * n, CHARGER_OFF, aux_relay, aux_a, est, events)

        self._battery_limits(bats, valid, t, events)
        eligible = [i for i in range(n) if valid[i] and not st.done[i]]
        plan = self._decide(est, eligible)
        self._set_plan(plan, t, events)
        if plan.stage is Stage.COMPLETE:
            events.append(
                Event(
                    t,
                    "ChargeComplete",
                    message="all batteries full, relays opened",
                    data={
                        "session_s": st.session_s,
                        "n_full": sum(1 for d in st.done if d),
                    },
                )
            )
        closed = tuple(i in plan.members for i in range(n))
        if plan.members:
            current = stage_current_a(cfg, len(plan.members), len(eligible))
            charger = ChargerCommand(voltage_v=plan.cmd_v, current_a=current, enable=True)
        elif plan.stage is Stage.COMPLETE:
            charger = self._aux_only_charger(aux_relay)
        else:
            charger = CHARGER_OFF
        return self._output(closed, charger, aux_relay, aux_a, est, events)

    def _aux_only_charger(self, aux_relay: bool | None) -> ChargerCommand:
        """Traction charging done: the dock stays on (every traction relay open) only while the
        aux battery is still charging, since its DC/DC draws from the dock (spec §2)."""
        if aux_relay:
            return ChargerCommand(
                voltage_v=self.volts.v_sat, current_a=self.config.charger_current_limit_a
            )
        return CHARGER_OFF

    # ----------------------------------------------------------------------------------------
    def _decide(self, est: list[float], eligible: list[int]) -> Plan:
        """Keep the latched plan while its exit condition is unmet, else decide afresh."""
        st = self.state
        if not eligible:
            if any(st.done):
                return Plan(Stage.COMPLETE)
            return Plan(Stage.HOLD)
        if self._keep(st.plan, est, eligible):
            if st.plan.stage is Stage.TOP_OFF:
                return Plan(Stage.TOP_OFF, frozenset(eligible), cmd_v=self.volts.v_sat)
            return st.plan
        return self._fresh(est, eligible)

    def _keep(self, plan: Plan, est: list[float], eligible: list[int]) -> bool:
        vs = self.volts
        if plan.stage not in (Stage.S20, Stage.S30, Stage.S40, Stage.TOP_OFF):
            return False
        elig = set(eligible)
        if plan.stage is Stage.TOP_OFF:
            member_v = [est[i] for i in eligible]
            return max(member_v) - min(member_v) <= vs.delta_v1
        if not plan.members <= elig:
            return False
        member_v = [est[i] for i in plan.members]
        lo, hi = min(member_v), max(member_v)
        others = elig - plan.members
        if any(est[i] <= hi + vs.eps_eq for i in others):
            return False  # another battery is now at or below the connected level: regroup
        if plan.stage is Stage.S20:
            return lo < plan.vr1_v
        if plan.stage is Stage.S30:
            merged = hi - lo <= vs.eps_eq
            reached = lo >= plan.vt_v - vs.reach_tol
            return not (merged or reached)
        # S40
        return lo < plan.vr2_v - vs.reach_tol and hi - lo <= vs.delta_v1

    def _fresh(self, est: list[float], eligible: list[int]) -> Plan:
        cfg, vs = self.config, self.volts
        levels = cluster_levels([(i, est[i]) for i in eligible], vs.eps_eq)
        if len(levels) == 1:
            members = frozenset(levels[0])
            vp = min(est[i] for i in members)
            if vs.v_sat - vp > vs.delta_v2 + vs.reach_tol:
                vr2 = min(vs.v_sat, vp + vs.delta_v2)
                return Plan(
                    Stage.S40,
                    members,
                    first=tuple(sorted(members)),
                    cmd_v=min(vs.v_sat, vr2 + vs.k3),
                    vr2_v=vr2,
                )
            return Plan(Stage.TOP_OFF, members, first=tuple(sorted(members)), cmd_v=vs.v_sat)
        g1, g2 = levels[0], levels[1]
        v1 = max(est[i] for i in g1)
        v2 = min(est[i] for i in g2)
        vr1 = v2 - vs.d1
        if v1 < vr1:
            return Plan(
                Stage.S20,
                frozenset(g1),
                first=tuple(sorted(g1)),
                second=tuple(sorted(g2)),
                cmd_v=min(vs.v_sat, vr1 + vs.k1),
                vr1_v=vr1,
            )
        if len(levels) >= 3:
            vt = min(est[i] for i in levels[2])
        elif cfg.target_mode == "levels":
            vt = v2 + vs.step
        else:
            vt = vs.v_sat
        vt = min(vt, vs.v_sat)
        return Plan(
            Stage.S30,
            frozenset(g1) | frozenset(g2),
            first=tuple(sorted(g1)),
            second=tuple(sorted(g2)),
            cmd_v=min(vs.v_sat, vt + vs.k2),
            vr1_v=vr1,
            vt_v=vt,
        )

    def _set_plan(self, plan: Plan, t: float, events: list[Event], reason: str = "") -> None:
        st = self.state
        if not plan.same_as(st.plan):
            events.append(
                Event(
                    t,
                    "StageChanged",
                    message=f"{st.plan.stage} -> {plan.stage}",
                    data={
                        "stage": str(plan.stage),
                        "previous": str(st.plan.stage),
                        "first": _fmt_idx(plan.first),
                        "second": _fmt_idx(plan.second),
                        "closed": _fmt_idx(plan.members),
                        "vr1_v": plan.vr1_v,
                        "vt_v": plan.vt_v,
                        "vr2_v": plan.vr2_v,
                        "cmd_v": plan.cmd_v,
                        "reason": reason,
                    },
                )
            )
        st.plan = plan

    # ----------------------------------------------------------------------------------------
    def _validity_events(
        self, bats: list[BatteryMeasurement], valid: list[bool], t: float, events: list[Event]
    ) -> None:
        st = self.state
        for i, ok in enumerate(valid):
            bad = not ok and i < len(bats) and bats[i].present
            if bad and not st.invalid[i]:
                events.append(
                    Event(
                        t,
                        "Fault",
                        battery=i,
                        message="non-finite measurement: left out of charging, relay open",
                        data={"reason": "invalid_measurement"},
                    )
                )
            st.invalid[i] = bad

    def _update_resistance(self, bats: list[BatteryMeasurement], valid: list[bool]) -> None:
        """Learn each battery's R from current steps (V = OCV − I·R, I positive = discharge).

        Two estimates of ``R = −ΔV/ΔI``. Across the step itself (one period): mostly the
        ohmic R0, available at once. Settled: if the current then holds steady for two windows
        of ``r_settle_s``, ``R = −(V(T) − V(0) − (V(2T) − V(T))) / ΔI`` — the voltage change to
        the end of the first window includes the RC polarization (what separates a charging
        battery's terminal voltage from its rest voltage) plus the OCV drift of the charge
        delivered meanwhile, and the second window, with the polarization nearly settled,
        measures that drift. The settled value is accepted only within
        ``[1, r_settle_max_ratio] ×`` the step value and, once known, is the one used.
        """
        cfg, st = self.config, self.state
        for i, ok in enumerate(valid):
            if not ok:
                st.prev_v[i] = st.prev_i[i] = math.nan
                st.step_ref[i] = None
                continue
            v, cur = bats[i].voltage_v, bats[i].current_a
            di = cur - st.prev_i[i]
            if cfg.r_comp_adapt and math.isfinite(di) and abs(di) >= cfg.r_est_min_step_a:
                r_step = -(v - st.prev_v[i]) / di
                if 0.0 <= r_step <= cfg.r_comp_max_ohm:
                    if st.r_kind[i] < 2:
                        gain = cfg.r_est_gain if st.r_kind[i] == 1 else 1.0  # first: take it
                        st.r_ohm[i] += gain * (r_step - st.r_ohm[i])
                        st.r_kind[i] = 1
                    st.step_ref[i] = StepRef(st.prev_v[i], st.prev_i[i], cur, st.clock_s, r_step)
                else:
                    st.step_ref[i] = None
            ref = st.step_ref[i]
            if cfg.r_comp_adapt and cfg.r_settle_s > 0.0 and ref is not None:
                self._settle(i, ref, v, cur)
            st.prev_v[i], st.prev_i[i] = v, cur

    def _settle(self, i: int, ref: StepRef, v: float, cur: float) -> None:
        cfg, st = self.config, self.state
        if abs(cur - ref.i1) > max(0.1 * abs(ref.i1 - ref.i0), 0.5 * cfg.r_est_min_step_a):
            st.step_ref[i] = None  # the current moved on: no clean settled response
            return
        elapsed = st.clock_s - ref.t1
        if math.isnan(ref.v_mid):
            if elapsed >= cfg.r_settle_s:
                ref.v_mid = v
            return
        if elapsed < 2.0 * cfg.r_settle_s:
            return
        st.step_ref[i] = None
        r_new = -((ref.v_mid - ref.v0) - (v - ref.v_mid)) / (ref.i1 - ref.i0)
        if ref.r_step <= r_new <= min(cfg.r_settle_max_ratio * ref.r_step, cfg.r_comp_max_ohm):
            gain = cfg.r_est_gain if st.r_kind[i] == 2 else 1.0
            st.r_ohm[i] += gain * (r_new - st.r_ohm[i])
            st.r_kind[i] = 2

    def _r_for_compensation(self) -> list[float]:
        """Own estimate once learned; before that the mean of the learned ones (batteries of
        one pack are alike), else ``r_comp_initial_ohm``. A battery that joins a running group
        may see too small a current step to learn from, yet already carries current."""
        st = self.state
        best = max(st.r_kind)
        learned = [r for r, k in zip(st.r_ohm, st.r_kind, strict=True) if k == best and k > 0]
        fallback = sum(learned) / len(learned) if learned else self.config.r_comp_initial_ohm
        return [
            r if k == best and k > 0 else fallback for r, k in zip(st.r_ohm, st.r_kind, strict=True)
        ]

    def _battery_limits(
        self, bats: list[BatteryMeasurement], valid: list[bool], t: float, events: list[Event]
    ) -> None:
        """Latch out batteries that are full, hit the cell limit or are over-voltage."""
        cfg, vs, st = self.config, self.volts, self.state
        for i, ok in enumerate(valid):
            if not ok or st.done[i]:
                continue
            b = bats[i]
            reason = ""
            if b.max_cell_v >= cfg.cell_v_limit_v:
                reason = "cell_limit"
            elif b.voltage_v >= vs.v_sat + vs.overvoltage_margin:
                reason = "overvoltage"
            elif (
                b.voltage_v >= vs.v_sat - vs.reach_tol and -b.current_a <= cfg.termination_current_a
            ):
                reason = "full"
            if not reason:
                continue
            st.done[i] = reason
            events.append(
                Event(
                    t,
                    "Fault" if reason == "overvoltage" else "BatteryFull",
                    battery=i,
                    message=f"relay opened: {reason}",
                    data={
                        "reason": reason,
                        "voltage_v": b.voltage_v,
                        "current_a": b.current_a,
                        "max_cell_v": b.max_cell_v,
                    },
                )
            )

    def _charger_health(self, status: ChargerStatus | None, dt: float) -> str:
        """'' when the charger is usable, else why not."""
        cfg, st = self.config, self.state
        if status is None:
            st.no_status_s += dt
            if st.no_status_s >= cfg.charger_status_timeout_s:
                return "lost (no status)"
            return ""
        st.no_status_s = 0.0
        if not status.online:
            return "offline (status timeout)"
        flags = [
            name
            for name in (
                "hardware_failure",
                "over_temperature",
                "input_voltage_fault",
                "battery_not_detected",
                "communication_timeout",
            )
            if getattr(status, name)
        ]
        return ",".join(flags)

    def _aux(
        self, meas: Measurements, dt: float, events: list[Event]
    ) -> tuple[bool | None, float | None]:
        """Independent aux channel: charge below the floor always, to the target when docked."""
        cfg, st = self.config, self.state
        aux = meas.aux
        if not self.pack.has_aux or aux is None:
            return None, None
        if not aux.is_finite():
            if not st.aux_invalid:
                events.append(
                    Event(
                        meas.t_s,
                        "Fault",
                        message="aux battery: non-finite measurement, aux charging stopped",
                        data={"reason": "aux_invalid_measurement"},
                    )
                )
            st.aux_invalid = True
            st.aux_charging = False
            return False, 0.0
        st.aux_invalid = False
        stop_at = cfg.aux_soc_target if meas.docked else cfg.aux_soc_floor + cfg.aux_soc_hysteresis
        start_below = (
            cfg.aux_soc_target - cfg.aux_soc_hysteresis if meas.docked else cfg.aux_soc_floor
        )
        if st.aux_charging:
            st.aux_charging = aux.soc < stop_at
        else:
            st.aux_charging = aux.soc < start_below or aux.soc < cfg.aux_soc_floor
        if not st.aux_charging:
            return False, 0.0
        taper = min(1.0, max(0.0, (cfg.aux_cv_v - aux.voltage_v) / cfg.aux_cv_band_v))
        return True, cfg.aux_charge_current_a * taper

    def _reset_session(self) -> None:
        st = self.state
        st.done = [""] * self.pack.n_batteries
        st.no_status_s = 0.0
        st.fault_clear_s = 0.0
        st.charger_fault = ""
        st.session_s = 0.0
        st.rested = False

    def _output(
        self,
        closed: tuple[bool | None, ...],
        charger: ChargerCommand,
        aux_relay: bool | None,
        aux_a: float | None,
        est: list[float],
        events: list[Event],
    ) -> ControlOutput:
        st, n = self.state, self.pack.n_batteries
        plan = st.plan
        group: list[int] = []
        for i in range(n):
            if st.done[i] or st.invalid[i]:
                group.append(-1)
            elif i in plan.first:
                group.append(1)
            elif i in plan.second:
                group.append(2)
            else:
                group.append(0)
        status: dict[str, Sequence[float | int | str | bool | None]] = {
            "chg_stage": [str(plan.stage)] * n,
            "chg_group": group,
            "chg_relay": list(closed),
            "chg_est_v": est,
            "chg_r_ohm": self._r_for_compensation(),
            "chg_done": list(st.done),
            "chg_cmd_v": [charger.voltage_v if charger.enable else 0.0] * n,
            "chg_target_v": [plan.target_v] * n,
        }
        return ControlOutput(
            commands=Commands(
                chg_on=closed,
                dsg_on=closed,
                charger=charger,
                aux_relay_closed=aux_relay,
                aux_charge_a=aux_a,
            ),
            events=tuple(events),
            status=status,
        )


def _charger_data(meas: Measurements) -> dict[str, float | int | str | bool | None]:
    c = meas.charger
    if c is None:
        return {"status": "none"}
    return {
        "online": c.online,
        "output_v": c.output_v,
        "output_a": c.output_a,
        "hardware_failure": c.hardware_failure,
        "over_temperature": c.over_temperature,
        "input_voltage_fault": c.input_voltage_fault,
        "battery_not_detected": c.battery_not_detected,
        "communication_timeout": c.communication_timeout,
    }


__all__ = [
    "REFERENCE_SERIES",
    "ChargingConfig",
    "ChargingController",
    "ChargingState",
    "Plan",
    "Stage",
    "Volts",
    "cluster_levels",
    "stage_current_a",
]
