"""The closed loop's charger link over a real python-can bus.

``CanChargerLink`` implements the runner's ``ChargerLink`` (``send(command, t_s)``,
``poll(t_s)``): the controller's :class:`ChargerCommand` goes through :class:`ChargerClient` →
bus → :class:`ChargerEmulator` → the plant's charger, and the plant's output and flags come back
as status frames. Within one control period::

    poll(t)        client reads the status frames queued since the last period
    controller     decides with that status in ``meas.charger``
    send(cmd, t)   client takes the new setpoint and sends the heartbeat when due (every 1 s);
                   the emulator forwards it to the plant (before the plant steps) and sends
                   its status frame when due

so a setpoint reaches the plant in the same period when a heartbeat is due, and the status is
one period old, as on a real bus. With ``charger=None`` no emulator runs: the client talks to
whatever is on the bus (hardware in the loop).

Fault injection for tests and demos: :meth:`hang` stops the client (no heartbeat, no reads:
a hung BMS task) while the charger side keeps running; :meth:`inject` puts arbitrary frames on
the bus from a third node.
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Any

import can

from packpilot.contract.charger import ChargerCommand, ChargerStatus
from packpilot.io.can.bus import FrameLog, open_bus
from packpilot.io.can.client import ChargerClient
from packpilot.io.can.emulator import ChargerEmulator, ChargerPlant

_auto_channel = itertools.count()


class CanChargerLink:
    """Charger setpoints and status over CAN, with an emulated charger node by default."""

    def __init__(
        self,
        charger: ChargerPlant | None,
        *,
        interface: str = "virtual",
        channel: str | None = None,
        log_path: Path | str | None = None,
        status_timeout_s: float = 5.0,
        heartbeat_timeout_s: float = 5.0,
        bus_kwargs: dict[str, Any] | None = None,
        rating: tuple[float, float] = (math.inf, math.inf),
        bus: can.BusABC | None = None,
    ) -> None:
        """``channel=None`` picks a fresh in-process channel, so parallel runs never share a
        virtual bus. ``bus``: the client's bus, opened (and shut down) by the caller, e.g. a
        :class:`~packpilot.io.can.shared.Port` of a bus shared with the batteries."""
        if channel is None:
            channel = f"packpilot-link-{next(_auto_channel)}"
        kw = bus_kwargs or {}
        self._buses: list[can.BusABC] = []
        self.log = FrameLog(log_path) if log_path is not None else None
        self.bms_bus = bus if bus is not None else self._open(interface, channel, kw)
        self.client = ChargerClient(
            self.bms_bus, status_timeout_s=status_timeout_s, log=self.log, rating=rating
        )
        self.emulator: ChargerEmulator | None = None
        if charger is not None:
            charger_bus = self._open(interface, channel, kw)
            self.emulator = ChargerEmulator(
                charger_bus, charger, heartbeat_timeout_s=heartbeat_timeout_s
            )
        self._interface, self._channel, self._kw = interface, channel, kw
        self._intruder: can.BusABC | None = None
        self._hang_until = -float("inf")
        self._hang_from = float("inf")

    def _open(self, interface: str, channel: str, kw: dict[str, Any]) -> can.BusABC:
        bus = open_bus(interface, channel, **kw)
        self._buses.append(bus)
        return bus

    # ------------------------------------------------------------------ ChargerLink
    def poll(self, t_s: float) -> ChargerStatus | None:
        if self.hung(t_s):
            return None
        return self.client.read(t_s)

    def send(self, command: ChargerCommand, t_s: float) -> None:
        if not self.hung(t_s):
            self.client.set_request(command)
            self.client.poll(t_s)
        if self.emulator is not None:
            self.emulator.poll(t_s)

    # ------------------------------------------------------------------ fault injection
    def hang(self, from_s: float, until_s: float) -> None:
        """Stop the BMS side (heartbeat and reads) for ``from_s <= t < until_s``."""
        self._hang_from, self._hang_until = from_s, until_s

    def hung(self, t_s: float) -> bool:
        return self._hang_from <= t_s < self._hang_until

    def inject(self, msg: can.Message) -> None:
        """Send ``msg`` from a third node on the same bus (both ends receive it)."""
        if self._intruder is None:
            self._intruder = self._open(self._interface, self._channel, self._kw)
        self._intruder.send(msg)

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        for bus in self._buses:
            bus.shutdown()
        self._buses.clear()
        if self.log is not None:
            self.log.close()
            self.log = None

    def __enter__(self) -> CanChargerLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = ["CanChargerLink"]
