"""One CAN bus shared by several receivers of one process, each frame read and logged once.

Two python-can bus objects on one channel hear each other's frames (``virtual`` always;
``socketcan`` unless kernel filters part them), so a charger client and the battery port on
the same bus would each log the other's traffic and count it as unexpected. A
:class:`SharedBus` owns the one real bus: :meth:`pump` reads every pending frame once, logs it
once, and hands it to the first :class:`Port` whose ``accept`` takes it (the last port takes
whatever nobody else does); a port's ``send`` goes out on the real bus and is logged once.
A port is a python-can bus to its user (``recv(timeout=0)``, ``send``), so the existing
charger client runs on it unchanged.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable

import can

from packpilot.io.can.bus import FrameLog
from packpilot.io.can.client import MAX_FRAMES_PER_POLL


class Port(can.BusABC):
    """One receiver's share of a :class:`SharedBus`."""

    def __init__(self, shared: SharedBus, accept: Callable[[can.Message], bool]) -> None:
        super().__init__(channel=f"port-of-{shared.bus.channel_info}")
        self.shared = shared
        self.accept = accept
        self.inbox: deque[can.Message] = deque()

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.popleft() if self.inbox else None), True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.shared.send(msg)

    def shutdown(self) -> None:
        self.inbox.clear()
        super().shutdown()


class SharedBus:
    """The real bus, its frame log, and the ports it feeds."""

    def __init__(self, bus: can.BusABC, log: FrameLog | None = None) -> None:
        self.bus = bus
        self.log = log
        self.ports: list[Port] = []
        self.t_s = 0.0
        """The time frames are logged at (set by the owner before each period)."""
        self.recv_errors = 0

    def port(self, accept: Callable[[can.Message], bool] = lambda m: True) -> Port:
        p = Port(self, accept)
        self.ports.append(p)
        return p

    def pump(self) -> int:
        """Read every pending frame (at most :data:`MAX_FRAMES_PER_POLL`) into the ports."""
        n = 0
        for _ in range(MAX_FRAMES_PER_POLL):
            try:
                msg = self.bus.recv(timeout=0.0)
            except can.CanError:
                self.recv_errors += 1
                break
            if msg is None:
                break
            n += 1
            if self.log is not None:
                self.log.log(msg, self.t_s, rx=True)
            port = next((p for p in self.ports if p.accept(msg)), self.ports[-1])
            port.inbox.append(msg)
        return n

    def send(self, msg: can.Message) -> None:
        self.bus.send(msg)  # a CanError reaches the sender, which counts it
        if self.log is not None:
            self.log.log(msg, self.t_s, rx=False)

    def shutdown(self) -> None:
        for p in self.ports:
            p.shutdown()
        self.bus.shutdown()


__all__ = ["Port", "SharedBus"]
