"""ORACLE (tests only): the scalar supervisor as it was before the compiled core.

The supervisor: one BMS that runs the enabled methods together and keeps the pack safe.

It owns the operating mode (init → idle → discharge / charge → fault → shutdown), runs every
enabled method controller on the same measurements, then the safety layers (limits,
plausibility). Commands are merged with "off wins" (``merge_commands``), so a safety layer always
overrides a method. Finally it refuses any command that would close a relay between batteries
more than ``join_limit_v`` apart (the cross-charging current of two batteries a few volts apart
behind milliohms is hundreds of amperes) and logs the refusal as an event.

Methods keep running in every mode (their timers and accumulators need continuous time); the
mode decides what the supervisor itself adds: charger off outside CHARGE and in FAULT, every
path open in SHUTDOWN.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

from pydantic import BaseModel, ConfigDict, Field, model_validator

from packpilot.contract.bms import (
    Commands,
    Controller,
    ControlOutput,
    Event,
    Measurements,
    SwitchKind,
)
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo
from tests.compose import merge_commands


class Mode(enum.StrEnum):
    INIT = "init"
    IDLE = "idle"
    DISCHARGE = "discharge"
    CHARGE = "charge"
    FAULT = "fault"
    SHUTDOWN = "shutdown"


FAULT_EVENT_KINDS = frozenset({"Fault", "LimitTripped"})
TRIP_EVENT_KINDS = frozenset({"ProtectionTripped", "LimitTripped"})


class SupervisorConfig(BaseModel):
    """Mode thresholds and the relay join limit (per ~100 V battery; scale with series count)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    init_time_s: float = Field(0.5, ge=0, description="plausible samples needed before IDLE")
    discharge_current_a: float = Field(
        0.5, gt=0, description="pack discharge current that means DISCHARGE mode"
    )
    idle_after_s: float = Field(5.0, ge=0, description="quiet time before DISCHARGE → IDLE")
    join_limit_v: float = Field(
        3.0,
        gt=0,
        description="largest voltage difference across which a relay may join batteries",
    )
    fault_hold_s: float = Field(
        10.0, ge=0, description="FAULT holds this long after the last fault event"
    )
    shutdown_when_all_tripped: bool = Field(
        True, description="open every path once every traction battery has tripped, undocked"
    )

    @model_validator(mode="after")
    def _check(self) -> SupervisorConfig:
        if not math.isfinite(self.join_limit_v):
            raise ValueError("join_limit_v must be finite")
        return self


@dataclass
class Supervisor:
    """Composes method controllers and safety layers under one mode machine."""

    config: SupervisorConfig
    pack: PackInfo
    methods: Sequence[Controller] = ()
    safety: Sequence[Controller] = ()
    mode: Mode = Mode.INIT
    t_in_mode_s: float = 0.0
    quiet_s: float = 0.0
    since_fault_s: float = math.inf
    tripped: set[int] = field(default_factory=set)
    refused: dict[int, bool] = field(default_factory=dict)

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        cmds = Commands()
        events: list[Event] = []
        status: dict[str, Sequence[float | int | str | bool | None]] = {}
        for part in (*self.methods, *self.safety):
            out = part.step(meas, dt_s)
            cmds = merge_commands(cmds, out.commands)
            events.extend(out.events)
            status.update(out.status)
        for ev in events:
            if ev.kind in FAULT_EVENT_KINDS:
                self.since_fault_s = 0.0
            if ev.kind in TRIP_EVENT_KINDS and ev.battery is not None:
                self.tripped.add(ev.battery)
            if ev.kind in ("ProtectionReset", "LimitReset") and ev.battery is not None:
                self.tripped.discard(ev.battery)
        new_mode = self._next_mode(meas, dt_s)
        if new_mode is not self.mode:
            events.append(
                Event(
                    meas.t_s,
                    "ModeChanged",
                    None,
                    f"{self.mode} → {new_mode}",
                    {"from": str(self.mode), "to": str(new_mode)},
                )
            )
            self.mode = new_mode
            self.t_in_mode_s = 0.0
        else:
            self.t_in_mode_s += dt_s
        cmds = self._mode_commands(cmds)
        cmds, refusals = self._enforce_join_limit(meas, cmds)
        events.extend(refusals)
        for part in self.safety:
            note = getattr(part, "note_commands", None)
            if callable(note):
                note(cmds)  # plausibility compares switch feedback with what was commanded
        n = self.pack.n_batteries
        status["mode"] = [str(self.mode)] * n
        return ControlOutput(commands=cmds, events=tuple(events), status=status)

    # ------------------------------------------------------------------ modes
    def _next_mode(self, meas: Measurements, dt_s: float) -> Mode:
        self.since_fault_s += dt_s
        pack_a = sum(
            b.current_a for b in meas.batteries if b.present and math.isfinite(b.current_a)
        )
        if pack_a > self.config.discharge_current_a:
            self.quiet_s = 0.0
        else:
            self.quiet_s += dt_s
        mode = self.mode
        if mode is Mode.INIT:
            if self.t_in_mode_s + dt_s < self.config.init_time_s:
                return Mode.INIT
            mode = Mode.IDLE
        if self.since_fault_s < self.config.fault_hold_s:
            return Mode.FAULT
        all_tripped = len(self.tripped) >= self.pack.n_batteries > 0
        if meas.docked:
            return Mode.CHARGE
        if all_tripped and self.config.shutdown_when_all_tripped:
            return Mode.SHUTDOWN
        if pack_a > self.config.discharge_current_a:
            return Mode.DISCHARGE
        if mode in (Mode.DISCHARGE,) and self.quiet_s < self.config.idle_after_s:
            return Mode.DISCHARGE
        return Mode.IDLE

    def _mode_commands(self, cmds: Commands) -> Commands:
        n = self.pack.n_batteries
        if self.mode is Mode.SHUTDOWN:
            off = (False,) * n
            return merge_commands(cmds, Commands(chg_on=off, dsg_on=off, charger=CHARGER_OFF))
        if self.mode in (Mode.FAULT, Mode.DISCHARGE, Mode.IDLE, Mode.INIT):
            return merge_commands(cmds, Commands(charger=CHARGER_OFF))
        return cmds

    # ------------------------------------------------------------------ join limit
    def _enforce_join_limit(
        self, meas: Measurements, cmds: Commands
    ) -> tuple[Commands, list[Event]]:
        """Refuse closing a relay onto batteries more than ``join_limit_v`` away."""
        n = min(self.pack.n_batteries, len(meas.batteries))
        chg = list(cmds.chg_on) + [None] * (n - len(cmds.chg_on))
        dsg = list(cmds.dsg_on) + [None] * (n - len(cmds.dsg_on))
        relay = [self.pack.switch_kind[i] is SwitchKind.RELAY for i in range(n)]

        def will_close(i: int) -> bool:
            b = meas.batteries[i]
            c = b.switch.chg_on if chg[i] is None else bool(chg[i])
            d = b.switch.dsg_on if dsg[i] is None else bool(dsg[i])
            return relay[i] and c and d and b.present

        closed_now = [relay[i] and meas.batteries[i].switch.relay_closed for i in range(n)]
        closing = [i for i in range(n) if will_close(i) and not closed_now[i]]
        events: list[Event] = []
        if not closing:
            self.refused.clear()
            return cmds, events
        accepted = [i for i in range(n) if closed_now[i] and will_close(i)]
        volts = {i: meas.batteries[i].voltage_v for i in range(n)}
        limit = self.config.join_limit_v
        candidates = sorted((i for i in closing if math.isfinite(volts[i])), key=volts.__getitem__)
        if not accepted and candidates:
            # Nothing on the bus yet: seed it with the largest set of candidates that fit within
            # the limit (ties: the lowest voltages, which is where staged charging starts).
            best: list[int] = []
            for a in range(len(candidates)):
                window = [j for j in candidates[a:] if volts[j] - volts[candidates[a]] <= limit]
                if len(window) > len(best):
                    best = window
            accepted = list(best)
        for i in closing:
            if i in accepted:
                self.refused.pop(i, None)
                continue
            group = [volts[j] for j in accepted]
            v = volts[i]
            spread = max((abs(v - o) for o in group), default=0.0)
            if math.isfinite(v) and max([*group, v]) - min([*group, v]) <= limit:
                accepted.append(i)
                self.refused.pop(i, None)
                continue
            chg[i] = False
            dsg[i] = False
            if not self.refused.get(i):
                events.append(
                    Event(
                        meas.t_s,
                        "CommandRefused",
                        i,
                        "relay close refused: battery too far from the bus group",
                        {"voltage_v": v, "spread_v": spread, "join_limit_v": limit},
                    )
                )
            self.refused[i] = True
        new = Commands(
            chg_on=tuple(chg),
            dsg_on=tuple(dsg),
            charger=cmds.charger,
            balancer_a=cmds.balancer_a,
            aux_relay_closed=cmds.aux_relay_closed,
            aux_charge_a=cmds.aux_charge_a,
        )
        return new, events
