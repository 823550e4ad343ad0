"""Scalar composition of Python controllers for tests and benchmarks that drive a plant with a
harness beside a method (the core composes its own parts by the same "off wins" rule)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from packpilot.contract.bms import Commands, Controller, ControlOutput, Event, Measurements
from packpilot.contract.charger import CHARGER_OFF


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


__all__ = ["ComposedController", "merge_commands"]
