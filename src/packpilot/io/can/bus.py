"""Opening a python-can bus and logging frames with *simulation* timestamps.

On hardware: ``open_bus("socketcan", "can0")``. In tests and simulations: the in-process
``virtual`` interface, where every ``can.Bus(interface="virtual", channel=X)`` object sees the
frames the others on channel ``X`` send (not its own, unless ``receive_own_messages=True``).

:class:`FrameLog` writes BLF or ASC directly through python-can's writers, without a
``can.Notifier`` thread: the node that sends or receives a frame logs it itself, stamped with
the simulation time, so a log of a 10-hour simulated charge that ran in 20 s reads back with
the simulated times (and is identical from run to run, apart from the ASC header's date line).

BLF and ASC store a start date plus offsets, and BLF drops start dates before 1990, so frame
times are written as ``SIM_EPOCH_S + t_s``: simulation time 0 is 2000-01-01 00:00:00 UTC.
``can.LogReader`` on a BLF returns those absolute times; on an ASC it returns times relative to
the first frame unless read with ``can.ASCReader(path, relative_timestamp=False)``.
"""

from __future__ import annotations

import copy
from pathlib import Path
from types import TracebackType
from typing import Any

import can

from packpilot.errors import ConfigError

LOG_SUFFIXES = (".blf", ".asc")
SIM_EPOCH_S = 946_684_800.0
"""2000-01-01T00:00:00Z: the wall-clock date simulation time 0 is written as."""


def open_bus(interface: str = "virtual", channel: str = "packpilot", **kw: Any) -> can.BusABC:
    """Open a python-can bus; failures become a one-line :class:`ConfigError`."""
    try:
        return can.Bus(interface=interface, channel=channel, **kw)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as err:
        raise ConfigError(
            f"cannot open CAN bus --can-interface {interface} --can-channel {channel}: {err}"
        ) from None


class FrameLog:
    """Append-only BLF/ASC log of frames, timestamped with the caller's simulation time."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        suffix = self.path.suffix.lower()
        if suffix not in LOG_SUFFIXES:
            raise ConfigError(
                f"--can-log {self.path}: unsupported log format {suffix!r}, use .blf or .asc"
            )
        try:
            self._writer: can.io.generic.MessageWriter = (
                can.BLFWriter(self.path) if suffix == ".blf" else can.ASCWriter(self.path)
            )
        except OSError as err:
            raise ConfigError(f"--can-log {self.path}: cannot write ({err})") from None
        self.count = 0

    def log(self, msg: can.Message, t_s: float, *, rx: bool) -> None:
        """Record ``msg`` as received (``rx``) or sent at simulation time ``t_s``."""
        entry = copy.copy(msg)
        entry.timestamp = SIM_EPOCH_S + float(t_s)
        entry.is_rx = rx
        self._writer.on_message_received(entry)
        self.count += 1

    def close(self) -> None:
        self._writer.stop()

    def __enter__(self) -> FrameLog:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


__all__ = ["LOG_SUFFIXES", "SIM_EPOCH_S", "FrameLog", "open_bus"]
