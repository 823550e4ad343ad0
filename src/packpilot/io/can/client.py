"""BMS-side charger client: sends the request heartbeat, reads the charger's status.

Driven by *simulation time* from the supervised control loop: ``poll(t_s)`` sends the request
once per second of ``t_s`` and drains the receive queue without blocking. Because the heartbeat
is sent from the loop itself (no background thread), a hung loop stops the heartbeat and the
charger switches its output off after its own timeout, which is the point of a heartbeat.

Bad traffic never raises: frames with a wrong DLC, an unknown ID, the wrong ID format, remote
or error frames, or content that does not decode are counted and ignored.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import can

from packpilot.contract.charger import (
    CHARGER_OFF,
    ChargerCommand,
    ChargerStatus,
    status_in_range,
)
from packpilot.io.can.bus import FrameLog
from packpilot.io.can.codec import (
    PERIOD_S,
    STATUS_ID,
    FrameError,
    decode_status,
    encode_request,
)

MAX_FRAMES_PER_POLL = 1000
"""Bound on frames drained per poll, so a flooded bus cannot stall the control loop; the rest
wait for the next poll."""


@dataclass(slots=True)
class FrameCounters:
    """What a node has seen on the bus; exported to telemetry and asserted on in tests."""

    sent: int = 0
    received: int = 0
    """Valid frames of the expected kind."""
    malformed: int = 0
    """Expected ID, but wrong DLC or undecodable/out-of-protocol content."""
    unexpected: int = 0
    """Unknown ID, standard instead of extended ID, remote or error frame, or the other
    direction's frame."""
    send_errors: int = 0
    recv_errors: int = 0
    implausible: int = 0
    """Status frames that decoded but reported more than the charger can deliver (ignored)."""


def received(
    bus: can.BusABC, counters: FrameCounters, log: FrameLog | None, t_s: float
) -> Iterator[can.Message]:
    """The frames waiting on ``bus`` now (at most :data:`MAX_FRAMES_PER_POLL`, never
    blocking), each logged as received at ``t_s``; a receive error is counted and ends the
    drain. Every node that polls a bus drains it this one way."""
    for _ in range(MAX_FRAMES_PER_POLL):
        try:
            msg = bus.recv(timeout=0.0)
        except can.CanError:
            counters.recv_errors += 1
            return
        if msg is None:
            return
        if log is not None:
            log.log(msg, t_s, rx=True)
        yield msg


def transmit(
    bus: can.BusABC, counters: FrameCounters, log: FrameLog | None, msg: can.Message, t_s: float
) -> bool:
    """Send ``msg``, counted and logged as sent at ``t_s``; a send error is counted, never
    raised (a full or absent bus must not stop the loop). Returns whether it went out."""
    try:
        bus.send(msg)
    except can.CanError:
        counters.send_errors += 1
        return False
    counters.sent += 1
    if log is not None:
        log.log(msg, t_s, rx=False)
    return True


class ChargerClient:
    """The BMS end of the TC/Elcon protocol."""

    def __init__(
        self,
        bus: can.BusABC,
        *,
        period_s: float = PERIOD_S,
        status_timeout_s: float = 5.0,
        log: FrameLog | None = None,
        rating: tuple[float, float] = (math.inf, math.inf),
    ) -> None:
        """``rating``: the charger's rated (volts, amperes); a status beyond it is rejected."""
        if not (period_s > 0.0 and status_timeout_s > 0.0):
            raise ValueError("period_s and status_timeout_s must be positive")
        self.bus = bus
        self.period_s = period_s
        self.status_timeout_s = status_timeout_s
        self.log = log
        self.rating = rating
        self.counters = FrameCounters()
        self.request: ChargerCommand = CHARGER_OFF
        self.last_status: ChargerStatus | None = None
        self._last_status_t: float | None = None
        self._first_poll_t: float | None = None
        self._next_tx_t: float | None = None

    def set_request(self, cmd: ChargerCommand) -> None:
        """Setpoint for the next heartbeats (the frame goes out on the next due ``poll``)."""
        self.request = cmd

    def poll(self, t_s: float) -> ChargerStatus | None:
        """Send the heartbeat if due, read every pending frame, return the charger's status.

        Returns ``None`` until the first status frame (within ``status_timeout_s`` of the
        first poll), the latest status while status frames keep coming, and a status with
        ``online=False`` and NaN outputs once none arrived for ``status_timeout_s``.
        """
        self._check_time(t_s)
        if self._next_tx_t is None or t_s >= self._next_tx_t - 1e-9:
            self._send(t_s)
            nxt = (self._next_tx_t if self._next_tx_t is not None else t_s) + self.period_s
            # after a stall, restart the cadence from now instead of bursting to catch up
            self._next_tx_t = nxt if nxt > t_s else t_s + self.period_s
        return self.read(t_s)

    def read(self, t_s: float) -> ChargerStatus | None:
        """Only the receive half of :meth:`poll` (no heartbeat): lets a loop read the status
        before its controller runs and send the fresh setpoint after it."""
        self._check_time(t_s)
        self._drain(t_s)
        assert self._first_poll_t is not None
        ref = self._last_status_t if self._last_status_t is not None else self._first_poll_t
        if t_s - ref > self.status_timeout_s:
            return ChargerStatus(output_v=math.nan, output_a=math.nan, online=False)
        return self.last_status

    def _check_time(self, t_s: float) -> None:
        if not math.isfinite(t_s):
            raise ValueError(f"poll: simulation time must be finite, got {t_s}")
        if self._first_poll_t is None:
            self._first_poll_t = t_s

    def _send(self, t_s: float) -> None:
        msg = encode_request(self.request, timestamp=t_s)
        transmit(self.bus, self.counters, self.log, msg, t_s)

    def _drain(self, t_s: float) -> None:
        for msg in received(self.bus, self.counters, self.log, t_s):
            if (
                msg.arbitration_id != STATUS_ID
                or not msg.is_extended_id
                or msg.is_error_frame
                or msg.is_remote_frame
            ):
                self.counters.unexpected += 1
                continue
            try:
                status = decode_status(msg)
            except FrameError:
                self.counters.malformed += 1
                continue
            if not status_in_range(status.output_v, status.output_a, *self.rating):
                self.counters.implausible += 1
                continue
            self.counters.received += 1
            self.last_status = status
            self._last_status_t = t_s


__all__ = ["MAX_FRAMES_PER_POLL", "ChargerClient", "FrameCounters", "received", "transmit"]
