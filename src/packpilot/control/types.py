"""The contract between the pure BMS core and whatever shell runs it.

A controller sees only :class:`Measurements` (plain numbers, possibly NaN when a sensor lies)
and the elapsed ``dt_s``; it returns :class:`ControlOutput` (commands + events). Nothing here
knows whether the numbers came from the simulator, a CAN bus or a replayed log.

Sign convention everywhere: battery current is **positive when discharging**.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Protocol


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

    def is_finite(self) -> bool:
        """True when every numeric field a controller relies on is a finite number."""
        core = (
            self.voltage_v,
            self.current_a,
            self.temp_c,
            self.min_cell_v,
            self.max_cell_v,
            self.soc,
        )
        return all(math.isfinite(x) for x in core) and all(
            math.isfinite(v) for v in self.group_voltages_v
        )


@dataclass(frozen=True, slots=True)
class ChargerStatus:
    """What the charger reports (over CAN or from the simulated dock)."""

    output_v: float
    output_a: float
    hardware_failure: bool = False
    over_temperature: bool = False
    input_voltage_fault: bool = False
    battery_not_detected: bool = False
    communication_timeout: bool = False
    online: bool = True
    """False when no status has been received for longer than the timeout."""

    @property
    def faulted(self) -> bool:
        return (
            self.hardware_failure
            or self.over_temperature
            or self.input_voltage_fault
            or self.battery_not_detected
        )


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
class ChargerCommand:
    """Setpoint for a CC/CV charger: output enabled, voltage limit, current limit."""

    voltage_v: float
    current_a: float
    enable: bool = True


CHARGER_OFF = ChargerCommand(voltage_v=0.0, current_a=0.0, enable=False)


@dataclass(frozen=True, slots=True)
class Commands:
    """What controllers ask of the hardware. ``None`` means "no opinion".

    ``switches`` has one entry per battery, each field optional so that several controllers
    can be merged by :func:`merge_commands`: a path is on only if every controller that has an
    opinion wants it on (off wins, the fail-safe choice).
    """

    chg_on: tuple[bool | None, ...] = ()
    dsg_on: tuple[bool | None, ...] = ()
    charger: ChargerCommand | None = None
    balancer_a: tuple[tuple[float, ...], ...] | None = None
    """Per battery, per series group: equalizer current into the group (A, negative = out)."""
    aux_relay_closed: bool | None = None
    aux_charge_a: float | None = None
    """Current the auxiliary DC/DC should push into the auxiliary battery."""


@dataclass(frozen=True, slots=True)
class Event:
    """Something worth recording: a trip, a stage change, a fault. Events are data."""

    t_s: float
    kind: str
    battery: int | None = None
    message: str = ""
    data: Mapping[str, float | int | str | bool | None] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class ControlOutput:
    commands: Commands
    events: tuple[Event, ...] = ()
    status: Mapping[str, Sequence[float | int | str | bool | None]] = field(default_factory=dict)
    """Per-battery status channels for telemetry (e.g. active protection parameter)."""


@dataclass(frozen=True, slots=True)
class PackInfo:
    """Static facts about the pack a controller is built for (from the pack config)."""

    n_batteries: int
    groups_per_battery: tuple[int, ...]
    cells_per_group: tuple[int, ...]
    switch_kind: tuple[SwitchKind, ...]
    has_aux: bool = False
    has_charger: bool = False
    has_balancers: bool = False
    capacity_ah: tuple[float, ...] = ()
    """Nominal capacity of each battery."""


class Controller(Protocol):
    """A deterministic BMS function: measurements and elapsed time in, commands out."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput: ...


def _merge_flags(a: tuple[bool | None, ...], b: tuple[bool | None, ...]) -> tuple[bool | None, ...]:
    n = max(len(a), len(b))
    out: list[bool | None] = []
    for i in range(n):
        x = a[i] if i < len(a) else None
        y = b[i] if i < len(b) else None
        if x is None:
            out.append(y)
        elif y is None:
            out.append(x)
        else:
            out.append(x and y)
    return tuple(out)


def merge_commands(first: Commands, second: Commands) -> Commands:
    """Combine two controllers' commands: switch paths AND-ed, later charger/balancer win.

    The charger is disabled if either side disables it, so a safety layer can always stop it.
    """
    charger = second.charger if second.charger is not None else first.charger
    both = first.charger is not None and second.charger is not None
    if both and not (first.charger.enable and second.charger.enable):  # type: ignore[union-attr]
        charger = CHARGER_OFF
    return Commands(
        chg_on=_merge_flags(first.chg_on, second.chg_on),
        dsg_on=_merge_flags(first.dsg_on, second.dsg_on),
        charger=charger,
        balancer_a=second.balancer_a if second.balancer_a is not None else first.balancer_a,
        aux_relay_closed=(
            second.aux_relay_closed
            if second.aux_relay_closed is not None
            else first.aux_relay_closed
        ),
        aux_charge_a=second.aux_charge_a if second.aux_charge_a is not None else first.aux_charge_a,
    )


@dataclass(slots=True)
class NullController:
    """Leaves every switch as configured; the runner works before any method exists."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        return ControlOutput(commands=Commands())


@dataclass(slots=True)
class ComposedController:
    """Runs several controllers on the same measurements and merges their commands."""

    parts: Sequence[Controller]

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        commands = Commands()
        events: list[Event] = []
        status: dict[str, Sequence[float | int | str | bool | None]] = {}
        for part in self.parts:
            out = part.step(meas, dt_s)
            commands = merge_commands(commands, out.commands)
            events.extend(out.events)
            status.update(out.status)
        return ControlOutput(commands=commands, events=tuple(events), status=status)


__all__ = [
    "CHARGER_OFF",
    "CLOSED",
    "OPEN",
    "BatteryMeasurement",
    "ChargerCommand",
    "ChargerStatus",
    "Commands",
    "ComposedController",
    "ControlOutput",
    "Controller",
    "Event",
    "Measurements",
    "NullController",
    "PackInfo",
    "SwitchKind",
    "SwitchState",
    "merge_commands",
    "replace",
]
