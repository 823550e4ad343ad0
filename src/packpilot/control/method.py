"""What a control method is to the core, and its one-pack face.

Each method (protection, sequencing, charging, equalization) and each safety layer (limits,
plausibility, SOC, the supervisor) is one :class:`Method`: a config model, a ``build`` that
compiles the config into kernel parameters and allocates state for P packs, the compiled
``step_packs`` rule kernel, a reason table for its events and its status channels. The
supervisor's kernel calls every enabled method's per-pack rule in one compiled step; nothing
else runs a rule.

:class:`CompiledController` is the scalar face of a method for one pack (P = 1):
``step(Measurements, dt_s) -> ControlOutput`` converts the scalar measurements into the batch
arrays, runs the same kernel and converts back. Tests, replays and hand-driven use go through
it; it is a thin adapter, not a second implementation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel

from packpilot.contract.arrays import (
    CmdArrays,
    EventBuf,
    MeasArrays,
    PackArrays,
    clear_commands,
    cmd_arrays,
    commands,
    event_buf,
    meas_arrays,
    pack_arrays,
    put_measurements,
)
from packpilot.contract.bms import ControlOutput, Event, Measurements, StatusValue
from packpilot.contract.events import Labels, Reason, Source, render
from packpilot.contract.events import value as field_value
from packpilot.contract.topology import PackInfo

F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class StatusChannel:
    """A per-battery status value a method publishes every step (kinds as event fields:
    ``f``, ``o``, ``i``, ``b``, ``l:NAME``)."""

    name: str
    kind: str = "f"


StepPacks = Callable[
    [Any, Any, PackArrays, MeasArrays, float, CmdArrays, EventBuf, int, F64, int], None
]
"""``step_packs(prm, st, tp, m, dt_s, cmd, ev, src, status, s0)``: run the rules for every
pack of ``m``; write opinions into ``cmd``, events into ``ev`` (source id ``src``) and the
status channels into ``status[:, :, s0:s0 + len(channels)]``."""


@dataclass(frozen=True, slots=True)
class Method:
    """One control method or safety layer, as the core runs it."""

    name: str
    src: int
    """Event source id (index into the renderer's sources)."""
    config: type[BaseModel]
    build: Callable[[Any, Sequence[PackInfo]], tuple[Any, Any]]
    """``build(config, infos)`` -> (parameters, state) for ``len(infos)`` packs."""
    step_packs: StepPacks
    reasons: tuple[Reason, ...]
    status: tuple[StatusChannel, ...]
    labels: Callable[[Any], Labels]
    """Label lists of events and status (``prm`` -> names)."""
    max_events: Callable[[PackInfo], int]
    """Most events one pack can emit in one step (sizes the event buffer)."""
    after: Callable[[Any, Any, PackArrays, MeasArrays, CmdArrays], None] | None = None
    """``after(prm, st, tp, m, cmd)``: sees the step's final, merged commands, in part order
    (sequencing may still turn a path off, "off wins": a charge FET whose discharge FET any layer
    opened; plausibility, after it, compares switch feedback with what was commanded)."""
    reads: tuple[str, ...] = ()
    """Status channels of *other* parts this method reads, by name (methods never import each
    other: a channel's name is the contract). The core writes each one's slot in the status
    array into the parameters' ``reads_slot`` (same order; -1 where no part publishes it)
    before the first step; the kernel reads ``status[p, i, slot]``, which holds the value
    that part wrote in the previous step when it runs later in the order."""


def status_values(
    status: F64, p: int, s0: int, channels: Sequence[StatusChannel], labels: Labels
) -> dict[str, list[StatusValue]]:
    """Status channels of pack ``p`` as the scalar contract has them."""
    out: dict[str, list[StatusValue]] = {}
    for j, ch in enumerate(channels):
        col = status[p, :, s0 + j]
        out[ch.name] = [field_value(float(x), ch.kind, labels) for x in col]
    return out


class CompiledController:
    """The one-pack (P = 1) face of a :class:`Method`; subclasses set ``method``."""

    method: ClassVar[Method]

    def __init__(self, config: Any, pack: PackInfo) -> None:
        if not isinstance(config, self.method.config):
            config = self.method.config.model_validate(config or {})
        self.config = config
        self.pack = pack
        self.prm, self.st = self.method.build(config, [pack])
        n, g = pack.n_batteries, max(pack.groups_per_battery, default=1)
        self.tp = pack_arrays([pack])
        self._m = meas_arrays(1, n, g)
        self._cmd = cmd_arrays(1, n, g)
        self._ev = event_buf(max(self.method.max_events(pack), 1))
        self._status = np.full((1, n, len(self.method.status)), np.nan)
        self._source = Source(self.method.reasons, self.method.labels(self.prm))

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        put_measurements(self._m, 0, meas)
        clear_commands(self._cmd)
        self._ev.n[0] = 0
        self.method.step_packs(
            self.prm, self.st, self.tp, self._m, float(dt_s), self._cmd, self._ev,
            0, self._status, 0,
        )  # fmt: skip
        return ControlOutput(
            commands=commands(self._cmd, 0, self.pack.groups_per_battery),
            events=tuple(self.events()),
            status=status_values(self._status, 0, 0, self.method.status, self._source.labels),
        )

    def events(self) -> list[Event]:
        """The events of the last step."""
        return render(self._ev, [self._source], 1, self.pack.names)[0]


__all__ = ["CompiledController", "Method", "StatusChannel", "StepPacks", "status_values"]
