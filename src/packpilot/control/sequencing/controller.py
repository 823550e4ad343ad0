"""Parallel-discharge sequencing as a core method, and its one-pack face
:class:`SequencingController`."""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from typing import overload

import numpy as np

from packpilot.config.sequencing import SequencingConfig
from packpilot.contract.bms import BatteryMeasurement
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.control.sequencing import rules
from packpilot.control.sequencing.rules import F64, SequencingParams, SequencingState


class SeqState(enum.StrEnum):
    """Per-battery sequencing state (spec section 3, plus OFF for an absent battery)."""

    DISCHARGING = "DISCHARGING"
    STANDBY = "STANDBY"
    CHARGING = "CHARGING"
    OFF = "OFF"


class SeqMode(enum.StrEnum):
    """Pack-level mode: which set of rules runs this period."""

    DISCHARGE = "discharge"
    CHARGE = "charge"
    FAULT = "fault"


STATES: tuple[SeqState, ...] = tuple(SeqState)
MODES: tuple[SeqMode, ...] = tuple(SeqMode)
assert [STATES.index(s) for s in (SeqState.DISCHARGING, SeqState.OFF)] == [
    rules.DISCHARGING,
    rules.OFF,
]
assert [MODES.index(s) for s in (SeqMode.CHARGE, SeqMode.FAULT)] == [
    rules.MODE_CHARGE,
    rules.MODE_FAULT,
]

REASON_LABELS: tuple[str, ...] = (
    "",
    "fail-safe",
    "removed",
    "inserted",
    "charge mode",
    "inserted while charging",
    "R1 init",
    "R1 no battery discharging",
    "R1 inserted above bus",
    "R2",
    "R3",
    "held open by another layer",
)
"""Why a battery's state changed, by ``rules.R_*``; per-battery reasons follow
(:func:`reason_labels`)."""
assert len(REASON_LABELS) == rules.N_FIXED_REASONS
assert REASON_LABELS[rules.R_R3] == "R3"
assert REASON_LABELS[rules.R_HELD] == "held open by another layer"


def reason_labels(n: int) -> tuple[str, ...]:
    """The reason labels of a pack of ``n`` batteries."""
    return (*REASON_LABELS, *(f"R1 battery {k} inserted" for k in range(n)))


def fault_reason(row: Sequence[float], n: int) -> str:
    """The fail-safe reason ``row`` (``SequencingState.fault[p]``) as the scalar controller
    wrote it ('' for none); ``n`` batteries expected."""
    code = int(row[0])
    x, y = float(row[2]), float(row[3])
    if code == rules.FAULT_COUNT:
        return f"expected {n} batteries in the measurements, got {int(row[1])}"
    if code == rules.FAULT_T:
        return f"t_s is not finite ({x})"
    if code == rules.FAULT_DT:
        return f"dt_s must be a finite number >= 0 (got {x})"
    if code == rules.FAULT_BACKWARDS:
        return f"time went backwards ({x} -> {y})"
    if code == rules.FAULT_VOLTAGE:
        return f"battery {int(row[1])}: voltage {x} is not a finite value >= 0"
    if code == rules.FAULT_CURRENT:
        return f"battery {int(row[1])}: current {x} is not finite"
    return ""


class FaultText(Sequence[str]):
    """The label list of the fail-safe reasons: entry ``p`` is pack ``p``'s last reason,
    formatted from the state when an event is rendered (the step's events are rendered before
    the next step; a pack emits at most one Fault or FaultCleared per step)."""

    def __init__(self, fault: F64, n: int) -> None:
        self._fault = fault
        self._n = n

    def __len__(self) -> int:
        return int(self._fault.shape[0])

    @overload
    def __getitem__(self, i: int) -> str: ...

    @overload
    def __getitem__(self, i: slice) -> Sequence[str]: ...

    def __getitem__(self, i: int | slice) -> str | Sequence[str]:
        if isinstance(i, slice):
            return [self[j] for j in range(len(self))[i]]
        return fault_reason([float(x) for x in self._fault[i]], self._n)


_SET = ("from:l:state", "to:l:state", "reason:l:reason", "_battery:i")
_SET_MSG = "battery {battery}: {from} -> {to} ({reason})"


def _set(kind: str, *data: str) -> Reason:
    return Reason(kind, _SET_MSG, fields(*_SET, *data))


_REVERSE = fields("current_a", "i_rev", "path:l:path", "_battery:i")

REASONS = (
    _set("StateChanged"),
    _set("StateChanged", "v", "v_max"),
    Reason(
        "ReverseCurrent",
        "battery {battery}: charge FET off, {current_a:.2f} A of charging current from a sibling",
        _REVERSE,
    ),
    _set("StateChanged", "v", "v_ref"),
    _set("BatteryJoined", "e_fast_v", "e_ref_v", "de_v"),
    _set("BatteryJoined", "v", "current_a"),
    Reason(
        "DiodeBypassed",
        "battery {battery}: {path} FET on after {conduction_s:.3f} s of diode conduction",
        fields("path:l:path", "conduction_s", "_battery:i"),
    ),
    Reason(
        "ReverseCurrent",
        "battery {battery}: discharging into a sibling while charging",
        _REVERSE,
    ),
    Reason(
        "CrossCurrentRisk",
        "battery {battery}: {predicted_a:.2f} A (near or above its {i_limit_a:.2f} A charge "
        "limit) would flow into it if the load vanished",
        fields("predicted_a", "i_limit_a", "_battery:i"),
    ),
    Reason(
        "ModeChanged",
        "sequencing mode {from} -> {to}",
        fields("from:l:mode", "to:l:mode", "docked:b", "pack_current_a"),
    ),
    Reason(
        "ModeChanged",
        "sequencing mode {from} -> {to}",
        fields("from:l:mode", "to:l:mode", "docked:b", "pack_current_a:i"),
    ),
    Reason(
        "Fault",
        "sequencing fail-safe: {reason}",
        fields("reason:l:fault", "previous_mode:l:mode"),
    ),
    Reason(
        "FaultCleared",
        "sequencing measurements valid again, re-initialising (R1)",
        fields("reason:l:fault"),
    ),
    Reason(
        "ReverseCurrent",
        "battery {battery}: charge FET off, {current_a:.2f} A would flow into it from battery "
        "{source} at the present load",
        fields("current_a", "i_rev", "path:l:path", "_battery:i", "source:i"),
    ),
    Reason(
        "CrossCurrentRisk",
        "battery {battery}: charge FET off, {predicted_a:.2f} A (over its {i_limit_a:.2f} A "
        "charge limit x the open ratio) would flow into it if the load vanished",
        fields("predicted_a", "i_limit_a", "_battery:i"),
    ),
    Reason(
        "CrossCurrentRisk",
        "battery {battery}: charge FET held off, its diode carrying {current_a:.2f} A: "
        "{predicted_a:.2f} A (over its {i_limit_a:.2f} A charge limit x the margin) would "
        "flow into it if it were closed and the load vanished",
        fields("predicted_a", "i_limit_a", "current_a", "_battery:i"),
    ),
)
assert [r.kind for r in REASONS][rules.FAULT_CLEARED] == "FaultCleared"
assert len(REASONS) == rules.DIODE_HOLD + 1
assert [r.kind for r in REASONS][rules.RISK] == "CrossCurrentRisk"

STATUS = (
    StatusChannel("seq_state", "l:state"),
    StatusChannel("seq_chg_on", "b"),
    StatusChannel("seq_dsg_on", "b"),
    StatusChannel("seq_mode", "l:mode"),
    StatusChannel("seq_v_ref_v", "o"),
    StatusChannel("seq_zero_load_into_a", "f"),
    StatusChannel("seq_at_risk", "b"),
    StatusChannel("seq_diode_s", "f"),
)
"""Per battery: its state and FET commands, the pack mode, the bus reference (highest admitted
fast voltage; None outside discharge), the zero-load prediction of the engaged set (0 outside
discharge), whether that exceeds its charge limit, and how long its diode has conducted."""
assert STATUS[rules.ST_DIODE].name == "seq_diode_s"


READS = ("soc_r0_ohm", "soc_observer_ok")
"""The battery observer's channels the zero-load prediction reads (``Method.reads``; the
``[soc]`` layer publishes them): each battery's R0 and whether the observer is trusted."""


def build(
    config: SequencingConfig, infos: Sequence[PackInfo]
) -> tuple[SequencingParams, SequencingState]:
    """Parameters and state (every battery OFF, discharge mode) of ``infos``."""
    info = infos[0]
    n = info.n_batteries
    if n < 1:
        raise ValueError("SequencingController needs at least one battery")
    P = len(infos)
    fault = np.zeros((P, rules.N_FAULT))
    prm = SequencingParams(
        v_th=float(config.v_th),
        v_co=float(config.v_co),
        i_det=float(config.i_det),
        t_on=float(config.t_on),
        t_debounce=float(config.t_debounce),
        i_rev=float(config.i_rev),
        q_rev_as=float(config.q_rev_as),
        t_mode=float(config.t_mode),
        charge_limit_c=float(config.charge_limit_c),
        charge_limit_margin=float(config.charge_limit_margin),
        risk_clear_ratio=float(config.risk_clear_ratio),
        default_capacity_ah=float(config.default_capacity_ah),
        r_batt_ohm=float(config.r_batt_ohm),
        i_step=float(config.i_step),
        zero_load_observer=bool(config.zero_load_observer),
        open_ratio=(
            max(float(config.zero_load_open_ratio), float(config.charge_limit_margin))
            if config.zero_load_open
            else math.inf
        ),
        diode_hold_a=float(config.diode_hold_a),
        hold_ratio=float(config.charge_limit_margin),
        reads_slot=np.full(len(READS), -1, np.int64),
        n_batteries=int(n),
        fault_text=fault,
    )
    pb = (P, n)
    b = (n,)

    def nan(shape: tuple[int, ...]) -> F64:
        return np.full(shape, np.nan)

    def no(shape: tuple[int, ...]) -> rules.B1:
        return np.zeros(shape, np.bool_)

    def idx() -> rules.I64:
        return np.zeros(b, np.int64)

    st = SequencingState(
        state=np.full(pb, rules.OFF, np.int64),
        chg_on=no(pb),
        dsg_on=no(pb),
        conduct_since_s=nan(pb),
        r_ohm=nan(pb),
        last_v_v=nan(pb),
        last_i_a=nan(pb),
        at_risk=no(pb),
        rev_q_as=np.zeros(pb),
        zero_load_into_a=nan(pb),
        mode=np.full(P, rules.MODE_DISCHARGE, np.int64),
        initialized=no((P,)),
        last_t_s=nan((P,)),
        mode_evidence_since_s=nan((P,)),
        v_ref_v=nan((P,)),
        zero_load_valid=no((P,)),
        fault=fault,
        forced_s=nan(pb),
        forced_a=nan(pb),
        zl_open_s=nan(pb),
        diode_held=no(pb),
        held=no(pb),
        ef=nan(b),
        g=nan(b),
        ez=nan(b),
        gz=nan(b),
        zl_obs=no(b),
        i_lim=nan(b),
        pred=np.zeros(b),
        grp=idx(),
        order=idx(),
        cut=no(b),
        skip=no(b),
        inserted=no(b),
        was_c=no(b),
        was_d=no(b),
    )
    return prm, st


def labels(prm: SequencingParams) -> Labels:
    return {
        "state": tuple(s.value for s in STATES),
        "mode": tuple(s.value for s in MODES),
        "reason": reason_labels(prm.n_batteries),
        "path": ("chg", "dsg"),
        "fault": FaultText(prm.fault_text, prm.n_batteries),
    }


METHOD = Method(
    name="sequencing",
    src=1,
    config=SequencingConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=labels,
    max_events=lambda info: rules.max_events(info.n_batteries),
    after=rules.close_out_packs,
    reads=READS,
)


class SequencingController(CompiledController):
    """Parallel-discharge sequencing for ``pack.n_batteries`` MOSFET-pair batteries (one pack).

    Deterministic: the only clock is ``meas.t_s`` (for timers) and ``dt_s`` (the control
    period, used to predict whether waiting one more period would miss the ``t_on``
    deadline). The accessors read the state arrays (pack 0).
    """

    method = METHOD
    config: SequencingConfig
    prm: SequencingParams
    st: SequencingState

    def __init__(self, config: SequencingConfig, pack: PackInfo) -> None:
        super().__init__(config, pack)

    @property
    def mode(self) -> SeqMode:
        return MODES[int(self.st.mode[0])]

    @property
    def states(self) -> tuple[SeqState, ...]:
        """Each battery's state."""
        return tuple(STATES[int(x)] for x in self.st.state[0])

    @property
    def chg_on(self) -> tuple[bool, ...]:
        """The charge FET commands last issued."""
        return tuple(bool(x) for x in self.st.chg_on[0])

    @property
    def dsg_on(self) -> tuple[bool, ...]:
        return tuple(bool(x) for x in self.st.dsg_on[0])

    @property
    def r_ohm(self) -> tuple[float, ...]:
        """Each battery's resistance estimate (ohm; NaN until a current step was seen)."""
        return tuple(float(x) for x in self.st.r_ohm[0])

    @property
    def initialized(self) -> bool:
        return bool(self.st.initialized[0])

    @property
    def fault_reason(self) -> str:
        """Why the pack is in the fail-safe ('' when it is not)."""
        if self.mode is not SeqMode.FAULT:
            return ""
        return fault_reason([float(x) for x in self.st.fault[0]], self.pack.n_batteries)


def battery_measurement(
    voltage_v: float, current_a: float, present: bool = True
) -> BatteryMeasurement:
    """A measurement carrying only what sequencing reads; other fields are unknown (NaN)."""
    nan = math.nan
    return BatteryMeasurement(
        voltage_v=voltage_v,
        current_a=current_a,
        temp_c=nan,
        min_cell_v=nan,
        max_cell_v=nan,
        soc=nan,
        full_capacity_ah=nan,
        remaining_capacity_ah=nan,
        present=present,
    )


__all__ = [
    "METHOD",
    "MODES",
    "REASONS",
    "REASON_LABELS",
    "STATES",
    "STATUS",
    "FaultText",
    "SeqMode",
    "SeqState",
    "SequencingController",
    "battery_measurement",
    "build",
    "fault_reason",
    "labels",
    "reason_labels",
]
