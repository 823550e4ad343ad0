"""Staged charging as a core method, and its one-pack face :class:`ChargingController`."""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from packpilot.config.charging import REFERENCE_SERIES, VOLTAGE_FIELDS, ChargingConfig
from packpilot.contract.charger import CHARGER_FLAGS
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.charging import rules
from packpilot.control.charging.rules import ChargingParams, ChargingState
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.errors import ConfigError


class Stage(enum.StrEnum):
    """Charging stage; ``S20``/``S30``/``S40`` are the spec's steps (in the order of the
    stage indices of :mod:`.rules`)."""

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


STAGES: tuple[Stage, ...] = tuple(Stage)
assert [STAGES.index(Stage(s)) for s in ("idle", "S20", "top_off", "fault")] == [
    rules.IDLE,
    rules.S20,
    rules.TOP_OFF,
    rules.FAULT,
]

DONE_LABELS: tuple[str, ...] = ("", "full", "cell_limit", "overvoltage")
"""Why a battery is out for the session ('' = chargeable), by ``rules.DONE_*``."""

WHY_LABELS: tuple[str, ...] = (
    "",
    "undocked",
    "docked",
    "lost (no status)",
    "offline (status timeout)",
    *(
        ",".join(name for k, name in enumerate(CHARGER_FLAGS) if mask >> k & 1)
        for mask in range(1, 1 << len(CHARGER_FLAGS))
    ),
)
"""Why the stage changed / why the charger is unusable, by ``rules.WHY_*``."""

CONST_LABELS: tuple[str, ...] = ("none", "invalid_measurement", "aux_invalid_measurement")
RELAY_LABELS = cast(Sequence[str], (False, True))
"""The ``chg_relay`` status is ``None`` / ``False`` / ``True`` (no opinion, open, closed): a
label list of the two bools renders it, code -1 being ``None``."""

LABELS: Labels = {
    "stage": tuple(str(s) for s in STAGES),
    "why": WHY_LABELS,
    "done": DONE_LABELS,
    "const": CONST_LABELS,
    "relay": RELAY_LABELS,
}

_CHARGER_FIELDS = tuple(f"{name}:b" for name in CHARGER_FLAGS)
_LIMIT_FIELDS = fields("reason:l:done", "voltage_v", "current_a", "max_cell_v")

REASONS = (
    Reason(
        "StageChanged",
        "{previous} -> {stage}",
        fields(
            "stage:l:stage",
            "previous:l:stage",
            "first:m",
            "second:m",
            "closed:m",
            "vr1_v",
            "vt_v",
            "vr2_v",
            "cmd_v",
            "reason:l:why",
        ),
    ),
    Reason(
        "Fault",
        "non-finite measurement: left out of charging, relay open",
        fields("reason:l:const"),
    ),
    Reason(
        "Fault",
        "aux battery: non-finite measurement, aux charging stopped",
        fields("reason:l:const"),
    ),
    Reason(
        "Fault",
        "charger: {fault}",
        fields("_fault:l:why", "online:b", "output_v", "output_a", *_CHARGER_FIELDS),
    ),
    Reason("Fault", "charger: {fault}", fields("_fault:l:why", "status:l:const")),
    Reason("BatteryFull", "relay opened: {reason}", _LIMIT_FIELDS),
    Reason("Fault", "relay opened: {reason}", _LIMIT_FIELDS),
    Reason("ChargeComplete", "all batteries full, relays opened", fields("session_s", "n_full:i")),
)
assert [r.kind for r in REASONS][rules.CHARGE_COMPLETE] == "ChargeComplete"

STATUS = (
    StatusChannel("chg_stage", "l:stage"),
    StatusChannel("chg_group", "i"),
    StatusChannel("chg_relay", "l:relay"),
    StatusChannel("chg_est_v", "f"),
    StatusChannel("chg_r_ohm", "f"),
    StatusChannel("chg_done", "l:done"),
    StatusChannel("chg_cmd_v", "f"),
    StatusChannel("chg_target_v", "f"),
)
"""Per battery: the stage, the group (-1 out, 0 other, 1 first, 2 second), the relay opinion,
the IR-compensated voltage, the R used, why it is done, the charger voltage (0: off) and the
stage's target voltage."""


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
    s40_hysteresis: float

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


def build(
    config: ChargingConfig, infos: Sequence[PackInfo]
) -> tuple[ChargingParams, ChargingState]:
    """Parameters (the volts resolved for the pack's series count) and state of ``infos``."""
    info = infos[0]
    vs = Volts.resolve(config, info)
    per = config.battery_current_limit_a
    limit = float(config.charger_current_limit_a)
    prm = ChargingParams(
        **{name: float(getattr(vs, name)) for name in Volts.__slots__},
        target_saturation=config.target_mode == "saturation",
        charger_current_limit_a=limit,
        has_battery_limit=per is not None,
        battery_current_limit_a=math.nan if per is None else float(per),
        current_sqrt=config.current_law == "sqrt",
        full_current_a=limit if config.full_current_a is None else float(config.full_current_a),
        termination_current_a=float(config.termination_current_a),
        cell_v_limit_v=float(config.cell_v_limit_v),
        r_comp_initial_ohm=float(config.r_comp_initial_ohm),
        r_comp_adapt=bool(config.r_comp_adapt),
        r_est_min_step_a=float(config.r_est_min_step_a),
        r_est_gain=float(config.r_est_gain),
        r_settle_s=float(config.r_settle_s),
        r_settle_max_ratio=float(config.r_settle_max_ratio),
        r_comp_max_ohm=float(config.r_comp_max_ohm),
        dock_rest_s=float(config.dock_rest_s),
        charger_status_timeout_s=float(config.charger_status_timeout_s),
        charger_fault_clear_s=float(config.charger_fault_clear_s),
        aux_soc_floor=float(config.aux_soc_floor),
        aux_soc_target=float(config.aux_soc_target),
        aux_soc_hysteresis=float(config.aux_soc_hysteresis),
        aux_charge_current_a=float(config.aux_charge_current_a),
        aux_cv_v=float(config.aux_cv_v),
        aux_cv_band_v=float(config.aux_cv_band_v),
        aux_charge_from_bus=bool(config.aux_charge_from_bus),
    )
    P, n = len(infos), info.n_batteries
    pb = (P, n)

    def nan(shape: tuple[int, ...]) -> np.ndarray:
        return np.full(shape, np.nan)

    def no(shape: tuple[int, ...]) -> np.ndarray:
        return np.zeros(shape, np.bool_)

    st = ChargingState(
        stage=np.full(P, rules.IDLE, np.int64),
        members=no(pb),
        first=no(pb),
        second=no(pb),
        cmd_v=nan((P,)),
        vr1_v=nan((P,)),
        vt_v=nan((P,)),
        vr2_v=nan((P,)),
        r_ohm=np.full(pb, float(config.r_comp_initial_ohm)),
        r_kind=np.zeros(pb, np.int64),
        ref_on=no(pb),
        ref_v0=nan(pb),
        ref_i0=nan(pb),
        ref_i1=nan(pb),
        ref_t1=nan(pb),
        ref_r_step=nan(pb),
        ref_v_mid=nan(pb),
        clock_s=np.zeros(P),
        prev_v=nan(pb),
        prev_i=nan(pb),
        done=np.zeros(pb, np.int64),
        invalid=no(pb),
        no_status_s=np.zeros(P),
        fault_clear_s=np.zeros(P),
        charger_fault=np.zeros(P, np.int64),
        session_s=np.zeros(P),
        rested=no((P,)),
        aux_charging=no((P,)),
        aux_invalid=no((P,)),
        valid=no(pb),
        est=nan(pb),
        r_use=nan(pb),
        elig=no(pb),
        new_members=no(pb),
        new_first=no(pb),
        new_second=no(pb),
        sort_v=nan(pb),
        sort_i=np.zeros(pb, np.int64),
        order=np.zeros(pb, np.int64),
        level=np.zeros(pb, np.int64),
    )
    return prm, st


def _labels(prm: ChargingParams) -> Labels:
    return LABELS


METHOD = Method(
    name="charging",
    src=2,
    config=ChargingConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=_labels,
    max_events=lambda info: 2 * info.n_batteries + 4,
)


class ChargingController(CompiledController):
    """Staged charging: S20 → S30 per level pair, S40 steps, CV top-off, relays per battery
    (one pack).

    ``step`` is deterministic and never raises on bad measurements: a battery with a
    non-finite reading is left out of the sort with its relay open (``Fault`` event once);
    charger faults stop the charger and open every relay until the charger has reported
    healthy for ``charger_fault_clear_s``. The accessors read the state arrays (pack 0).
    """

    method = METHOD
    config: ChargingConfig
    prm: ChargingParams
    st: ChargingState

    def __init__(self, config: ChargingConfig, pack: PackInfo) -> None:
        super().__init__(config, pack)
        self.volts = Volts.resolve(self.config, pack)
        self.series = series_cells(pack) or [1] * pack.n_batteries

    @property
    def stage(self) -> Stage:
        """The latched stage."""
        return STAGES[int(self.st.stage[0])]

    @property
    def r_ohm(self) -> tuple[float, ...]:
        """Each battery's own resistance estimate (Ω)."""
        return tuple(float(x) for x in self.st.r_ohm[0])

    @property
    def r_kind(self) -> tuple[int, ...]:
        """Per battery: 0 = no estimate yet, 1 = from a step, 2 = settled."""
        return tuple(int(x) for x in self.st.r_kind[0])

    @property
    def done(self) -> tuple[str, ...]:
        """Per battery: '' (chargeable) or why it is out for this session."""
        return tuple(DONE_LABELS[int(x)] for x in self.st.done[0])

    @property
    def invalid(self) -> tuple[bool, ...]:
        """Per battery: left out for a non-finite reading."""
        return tuple(bool(x) for x in self.st.invalid[0])


__all__ = [
    "LABELS",
    "METHOD",
    "REASONS",
    "REFERENCE_SERIES",
    "STATUS",
    "ChargingController",
    "Stage",
    "Volts",
    "build",
    "series_cells",
]
