"""Charger command and status, with the one list of charger flags, and the link that carries
them between the BMS and the dock (written straight into the plant, or over CAN)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

CHARGER_FLAGS: tuple[str, ...] = (
    "hardware_failure",
    "over_temperature",
    "input_voltage_fault",
    "battery_not_detected",
    "communication_timeout",
)
"""The charger's status bits, in the order of the TC/Elcon status frame (bits 0..4). Every
other list of flags (plant model, CAN codec, fault injection) is this one."""

FAULT_FLAGS: tuple[str, ...] = CHARGER_FLAGS[:4]
"""Flags that mean the charger itself is faulted (a timeout is the link's problem)."""

STATUS_MARGIN = 0.1
"""How far above its rating a charger's reported output may be before the report is absurd."""


def status_in_range(output_v: float, output_a: float, rated_v: float, rated_a: float) -> bool:
    """Whether a charger's reported output is physically possible for the configured charger:
    0..rated (+10 %) volts and amperes. A status frame is 16-bit counts, so a corrupted one
    reads as up to 6,553.5 V / 6,553.5 A; such a report is rejected, never a measurement.
    The one implementation: the python-can client calls it, the compiled link model
    (``sim/elcon.py``) compiles this same function."""
    top_v = rated_v * (1.0 + STATUS_MARGIN)
    top_a = rated_a * (1.0 + STATUS_MARGIN)
    return 0.0 <= output_v <= top_v and 0.0 <= output_a <= top_a


@dataclass(frozen=True, slots=True)
class ChargerCommand:
    """Setpoint for a CC/CV charger: output enabled, voltage limit, current limit."""

    voltage_v: float
    current_a: float
    enable: bool = True


CHARGER_OFF = ChargerCommand(voltage_v=0.0, current_a=0.0, enable=False)


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
        return any(getattr(self, name) for name in FAULT_FLAGS)

    def flags(self) -> tuple[bool, ...]:
        """The status bits in :data:`CHARGER_FLAGS` order."""
        return tuple(bool(getattr(self, name)) for name in CHARGER_FLAGS)


class ChargerLink(Protocol):
    """How charger setpoints reach the dock and its status comes back (direct or CAN)."""

    def send(self, command: ChargerCommand, t_s: float) -> None: ...

    def poll(self, t_s: float) -> ChargerStatus | None: ...

    def close(self) -> None: ...


__all__ = [
    "CHARGER_FLAGS",
    "CHARGER_OFF",
    "FAULT_FLAGS",
    "ChargerCommand",
    "ChargerLink",
    "ChargerStatus",
]
