"""What a controller sees and says, for one pack: measurements in, commands and events out.

A controller sees only :class:`Measurements` (plain numbers, possibly NaN when a sensor lies)
and the elapsed ``dt_s``; it returns :class:`ControlOutput`. Nothing here knows whether the
numbers came from the simulator, a CAN bus or a replayed log. The compiled core works on the
array form of the same contract (:mod:`packpilot.contract.arrays`) for P packs at once; this
form is its one-pack face (tests, replay, hand-driven use).

Sign convention everywhere: battery current is **positive when discharging**.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from packpilot.contract.charger import ChargerCommand, ChargerStatus


class SwitchKind(enum.StrEnum):
    """How a battery (string) is connected to the shared bus."""

    RELAY = "relay"
    MOSFET_PAIR = "mosfet_pair"


@dataclass(frozen=True, slots=True)
class SwitchState:
    """Gate/coil state of one battery's switch.

    A relay is modelled as *closed iff both* ``chg_on`` and ``dsg_on``: opening either path of a
    relay-switched battery opens the relay, which is the fail-safe reading of "open the
    discharge path" for hardware that cannot block one direction only.
    """

    chg_on: bool
    dsg_on: bool

    @property
    def relay_closed(self) -> bool:
        return self.chg_on and self.dsg_on


OPEN = SwitchState(chg_on=False, dsg_on=False)
CLOSED = SwitchState(chg_on=True, dsg_on=True)


@dataclass(frozen=True, slots=True)
class BatteryMeasurement:
    """What one battery (a string of series groups behind one switch) reports each period.

    Mirrors a smart battery's status block (voltage, current, temperature, relative SOC, full
    and remaining capacity) plus the per-group voltages that equalization needs.
    """

    voltage_v: float
    """Battery terminal voltage, on the battery side of its switch."""
    current_a: float
    """Battery current, positive = discharge."""
    temp_c: float
    """Hottest cell temperature."""
    min_cell_v: float
    max_cell_v: float
    soc: float
    """Relative state of charge, 0..1."""
    full_capacity_ah: float
    remaining_capacity_ah: float
    group_voltages_v: tuple[float, ...] = ()
    switch: SwitchState = CLOSED
    """Switch feedback (gate/coil sense), not the command."""
    min_temp_c: float = math.nan
    present: bool = True
    """False when the battery is not inserted (hot-insertion scenarios)."""
    sample_age_s: float = math.nan
    """Age of the sample when the monitor reports it (a repeated frame grows old); NaN = not
    reported, which is not the same as stale."""
    cycle_count: float = math.nan
    """Charge/discharge cycles the battery has counted (a smart battery's CycleCount); NaN =
    not reported."""


@dataclass(frozen=True, slots=True)
class Measurements:
    """One sample of the whole pack, as the BMS sees it."""

    t_s: float
    batteries: tuple[BatteryMeasurement, ...]
    bus_v: float
    load_current_a: float = 0.0
    charger: ChargerStatus | None = None
    aux: BatteryMeasurement | None = None
    """The low-voltage auxiliary battery that powers the BMS, if the pack has one."""
    docked: bool = False
    """True when a charger is connected to the bus."""


@dataclass(frozen=True, slots=True)
class Commands:
    """What controllers ask of the hardware. ``None`` means "no opinion".

    ``chg_on`` / ``dsg_on`` have one entry per traction battery; several controllers' opinions
    are merged with "off wins" (a path is on only if every controller with an opinion wants it
    on); see :mod:`packpilot.control.commands`.
    """

    chg_on: tuple[bool | None, ...] = ()
    dsg_on: tuple[bool | None, ...] = ()
    charger: ChargerCommand | None = None
    balancer_a: tuple[tuple[float, ...], ...] | None = None
    """Per battery, per series group: equalizer current into the group (A, negative = out)."""
    aux_relay_closed: bool | None = None
    aux_charge_a: float | None = None
    """Current the auxiliary DC/DC should push into the auxiliary battery."""


EventValue = float | int | str | bool | None


@dataclass(frozen=True, slots=True)
class Event:
    """Something worth recording: a trip, a stage change, a fault. Events are data.

    ``battery`` is the traction index the controllers use (``None``: the whole pack); the
    topology turns it into a string index or a display name.
    """

    t_s: float
    kind: str
    battery: int | None = None
    message: str = ""
    data: Mapping[str, EventValue] = field(default_factory=dict)


StatusValue = float | int | str | bool | None


@dataclass(frozen=True, slots=True)
class ControlOutput:
    commands: Commands
    events: tuple[Event, ...] = ()
    status: Mapping[str, Sequence[StatusValue]] = field(default_factory=dict)
    """Per-battery status channels for telemetry (e.g. active protection parameter)."""


class Controller(Protocol):
    """A deterministic BMS function: measurements and elapsed time in, commands out."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput: ...


@dataclass(slots=True)
class NullController:
    """Has no opinion on anything: every switch stays as configured (a plant on its own)."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        return ControlOutput(commands=Commands())


__all__ = [
    "CLOSED",
    "OPEN",
    "BatteryMeasurement",
    "Commands",
    "ControlOutput",
    "Controller",
    "Event",
    "EventValue",
    "Measurements",
    "NullController",
    "StatusValue",
    "SwitchKind",
    "SwitchState",
]
