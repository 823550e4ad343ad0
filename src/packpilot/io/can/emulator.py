"""Charger-side CAN node: turns request frames into calls on a plant charger, and the plant's
output and flags into status frames.

The emulator is the protocol only. The physics and the heartbeat timeout (no request for 5 s →
output off, restarting when requests resume) belong to the plant charger behind
:class:`ChargerPlant`, so the same timeout applies with or without CAN in the loop. The
emulator additionally raises the ``communication_timeout`` status bit itself when it has not
seen a valid request for ``heartbeat_timeout_s``, as a real charger reports it, whatever the
plant does with its own flags.
"""

from __future__ import annotations

import math
from typing import Protocol

import can

from packpilot.io.can.bus import FrameLog
from packpilot.io.can.client import FrameCounters, received, transmit
from packpilot.io.can.codec import (
    PERIOD_S,
    REQUEST_ID,
    ChargerFlags,
    FaultFlags,
    FrameError,
    decode_request,
    encode_status,
)


class ChargerPlant(Protocol):
    """The plant's charging dock as the CAN emulator drives it.

    ``model/charger.py`` implements this without importing ``io`` (the plant must not): the
    flags may be any mapping with the five :data:`~packpilot.io.can.codec.FLAG_NAMES` keys or
    an object with those five boolean attributes.
    """

    def request(self, voltage_v: float, current_a: float, enable: bool, t_s: float) -> None:
        """A valid request frame arrived at ``t_s`` (this is the heartbeat)."""
        ...

    def output(self) -> tuple[float, float]:
        """Present output voltage (V) and current (A, positive = delivered)."""
        ...

    @property
    def fault_flags(self) -> FaultFlags:
        """The five status bits."""
        ...


class ChargerEmulator:
    """The charger's CAN node, driven by simulation time like the client."""

    def __init__(
        self,
        bus: can.BusABC,
        charger: ChargerPlant,
        *,
        period_s: float = PERIOD_S,
        heartbeat_timeout_s: float = 5.0,
        log: FrameLog | None = None,
    ) -> None:
        if not (period_s > 0.0 and heartbeat_timeout_s > 0.0):
            raise ValueError("period_s and heartbeat_timeout_s must be positive")
        self.bus = bus
        self.charger = charger
        self.period_s = period_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self.log = log
        self.counters = FrameCounters()
        self.last_request_t: float | None = None
        self._first_poll_t: float | None = None
        self._next_tx_t: float | None = None

    def heartbeat_lost(self, t_s: float) -> bool:
        """No valid request for longer than the timeout (counting from the first poll)."""
        ref = self.last_request_t if self.last_request_t is not None else self._first_poll_t
        return ref is not None and t_s - ref > self.heartbeat_timeout_s

    def poll(self, t_s: float) -> None:
        """Forward pending valid requests to the plant; send a status frame when due."""
        if not math.isfinite(t_s):
            raise ValueError(f"poll: simulation time must be finite, got {t_s}")
        if self._first_poll_t is None:
            self._first_poll_t = t_s
        self._drain(t_s)
        if self._next_tx_t is None or t_s >= self._next_tx_t - 1e-9:
            self._send_status(t_s)
            nxt = (self._next_tx_t if self._next_tx_t is not None else t_s) + self.period_s
            self._next_tx_t = nxt if nxt > t_s else t_s + self.period_s

    def _drain(self, t_s: float) -> None:
        for msg in received(self.bus, self.counters, self.log, t_s):
            if (
                msg.arbitration_id != REQUEST_ID
                or not msg.is_extended_id
                or msg.is_error_frame
                or msg.is_remote_frame
            ):
                self.counters.unexpected += 1
                continue
            try:
                req = decode_request(msg)
            except FrameError:
                self.counters.malformed += 1
                continue
            self.counters.received += 1
            self.last_request_t = t_s
            self.charger.request(req.voltage_v, req.current_a, req.enable, t_s)

    def _send_status(self, t_s: float) -> None:
        out_v, out_a = self.charger.output()
        try:
            flags = ChargerFlags.of(self.charger.fault_flags)
        except ValueError:
            flags = ChargerFlags(hardware_failure=True)  # a plant we cannot read is not healthy
        if self.heartbeat_lost(t_s) and not flags.communication_timeout:
            flags = ChargerFlags(
                hardware_failure=flags.hardware_failure,
                over_temperature=flags.over_temperature,
                input_voltage_fault=flags.input_voltage_fault,
                battery_not_detected=flags.battery_not_detected,
                communication_timeout=True,
            )
        msg = encode_status(out_v, out_a, flags, timestamp=t_s)
        transmit(self.bus, self.counters, self.log, msg, t_s)


__all__ = ["ChargerEmulator", "ChargerPlant"]
