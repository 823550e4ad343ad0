"""The supervisor: one BMS that runs the enabled methods together and keeps the pack safe.

The rules are in :mod:`.rules` and run inside :class:`~packpilot.control.core.Core` after every
part; :class:`Supervisor` is the one-pack face with today's constructor
(``Supervisor(config, pack, methods=[...], safety=[...])``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.bms import Controller, ControlOutput, Measurements
from packpilot.contract.events import Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.method import CompiledController, StatusChannel
from packpilot.control.supervisor import rules
from packpilot.control.supervisor.rules import MODES, SupParams, SupState

if TYPE_CHECKING:
    from packpilot.control.core import Core


class Mode(enum.StrEnum):
    INIT = "init"
    IDLE = "idle"
    DISCHARGE = "discharge"
    CHARGE = "charge"
    FAULT = "fault"
    SHUTDOWN = "shutdown"


assert tuple(m.value for m in Mode) == MODES

REASONS = (
    Reason("ModeChanged", "{from} → {to}", fields("from:l:mode", "to:l:mode")),
    Reason(
        "CommandRefused",
        "relay close refused: battery too far from the bus group",
        fields("voltage_v", "spread_v", "join_limit_v"),
    ),
)
STATUS = (StatusChannel("mode", "l:mode"),)
LABELS = {"mode": MODES}


def max_events(info: PackInfo) -> int:
    return info.n_batteries + 1


def build_supervisor(
    config: SupervisorConfig, infos: Sequence[PackInfo], ev_class: NDArray[np.int64]
) -> tuple[SupParams, SupState]:
    prm = SupParams(
        init_time_s=float(config.init_time_s),
        discharge_current_a=float(config.discharge_current_a),
        idle_after_s=float(config.idle_after_s),
        join_limit_v=float(config.join_limit_v),
        fault_hold_s=float(config.fault_hold_s),
        shutdown_when_all_tripped=bool(config.shutdown_when_all_tripped),
        ev_class=ev_class,
    )
    P, n = len(infos), infos[0].n_batteries
    st = SupState(
        mode=np.full(P, rules.INIT, np.int64),
        t_in_mode_s=np.zeros(P),
        quiet_s=np.zeros(P),
        since_fault_s=np.full(P, math.inf),
        tripped=np.zeros((P, n), np.bool_),
        refused=np.zeros((P, n), np.bool_),
        accepted=np.zeros((P, n), np.int64),
        order=np.zeros((P, n), np.int64),
    )
    return prm, st


class Supervisor:
    """Composes method controllers and safety layers under one mode machine (one pack).

    ``methods`` and ``safety`` are compiled controllers (their state is shared with the core,
    so their accessors keep working) or plain Python controllers.
    """

    def __init__(
        self,
        config: SupervisorConfig,
        pack: PackInfo,
        methods: Sequence[Any] = (),
        safety: Sequence[Any] = (),
    ) -> None:
        from packpilot.control.core import Core, Part

        self.config = config
        self.pack = pack
        self.methods = list(methods)
        self.safety = list(safety)
        parts: list[Part | Controller] = [
            Part.of(x) if isinstance(x, CompiledController) else x
            for x in (*self.methods, *self.safety)
        ]
        self.core: Core = Core([pack], parts, supervisor=config)

    @property
    def _sup(self) -> tuple[SupParams, SupState]:
        sup = self.core.supervisor
        assert sup is not None
        return sup.prm, sup.st

    @property
    def mode(self) -> Mode:
        return Mode(MODES[int(self._sup[1].mode[0])])

    @property
    def tripped(self) -> set[int]:
        return {int(i) for i in np.nonzero(self._sup[1].tripped[0])[0]}

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        return self.core.step(meas, dt_s)


__all__ = [
    "LABELS",
    "REASONS",
    "STATUS",
    "Mode",
    "Supervisor",
    "SupervisorConfig",
    "build_supervisor",
    "max_events",
]
