"""Opening a python-can bus and logging frames with *simulation* timestamps.

On hardware: ``open_bus("socketcan", "can0")``, interface options (a bitrate, socketcand's host
and port) as keywords, from ``--can-arg KEY=VALUE`` (:func:`parse_bus_args`). In tests and
simulations: the in-process ``virtual`` interface, where every
``can.Bus(interface="virtual", channel=X)`` object sees the frames the others on channel ``X``
send (not its own, unless ``receive_own_messages=True``); two processes without vcan share a
channel through ``packpilot can-hub`` (``io/can/hub.py``, python-can's ``socketcand`` client).

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
import logging
import re
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any

import can

from packpilot.errors import ConfigError

LOG_SUFFIXES = (".blf", ".asc")
SIM_EPOCH_S = 946_684_800.0
"""2000-01-01T00:00:00Z: the wall-clock date simulation time 0 is written as."""


RESERVED_BUS_ARGS = frozenset({"interface", "bustype", "channel", "can_filters", "context"})
"""Set by their own options (or by the runtime: receive filters), never by ``--can-arg``."""
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_INT = re.compile(r"[+-]?(?:[0-9]+|0[xX][0-9A-Fa-f]+)")
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.[0-9]*|\.[0-9]+|[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_bus_args(items: Iterable[str]) -> dict[str, Any]:
    """``--can-arg KEY=VALUE`` options as python-can interface keyword arguments (socketcand's
    ``host`` and ``port``, a hardware ``bitrate``): a value that looks like an integer, a
    float or true / false is one, anything else is a string."""
    out: dict[str, Any] = {}
    for item in items:
        key, eq, text = item.partition("=")
        key = key.strip()
        if not eq or not _KEY.fullmatch(key):
            raise ConfigError(f"--can-arg {item!r}: expected KEY=VALUE, e.g. bitrate=500000")
        if key in RESERVED_BUS_ARGS:
            raise ConfigError(f"--can-arg {item!r}: {key} is not an interface option here"
                              " (--can-interface / --can-channel set the bus)")  # fmt: skip
        if key in out:
            raise ConfigError(f"--can-arg {item!r}: {key} given twice")
        out[key] = bus_arg_value(text.strip())
    return out


def bus_arg_value(text: str) -> Any:
    """``500000`` → int, ``0x1F`` → int, ``1.5e3`` → float, ``true`` → True, else the text."""
    if text.lower() in ("true", "false"):
        return text.lower() == "true"
    if _INT.fullmatch(text):
        return int(text, 16) if "x" in text.lower() else int(text)
    if _FLOAT.fullmatch(text):
        return float(text)
    return text


def open_bus(interface: str = "virtual", channel: str = "packpilot", **kw: Any) -> can.BusABC:
    """Open a python-can bus; failures become a one-line :class:`ConfigError`."""
    if interface == "socketcand":
        _quiet_socketcand()
    try:
        return can.Bus(interface=interface, channel=channel, **kw)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError,
            TypeError) as err:  # fmt: skip
        hint = " (interface options: --can-arg KEY=VALUE)" if isinstance(err, TypeError) else ""
        raise ConfigError(
            f"cannot open CAN bus --can-interface {interface} --can-channel {channel}: {err}{hint}"
        ) from None


class _StreamNoise(logging.Filter):
    """python-can's socketcand client warns on every TCP read that ends mid-message (the
    normal case of a stream: the rest comes with the next read) and on every retry of its
    10 s connect loop (thousands of lines): stderr noise, not news. Its other warnings stay."""

    NOISE = ("Got incomplete message", "Failed to connect to server")

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(self.NOISE)


def _quiet_socketcand() -> None:
    log = logging.getLogger("can.interfaces.socketcand.socketcand")
    if not any(isinstance(f, _StreamNoise) for f in log.filters):
        log.addFilter(_StreamNoise())


class FrameLog:
    """Append-only BLF/ASC log of frames, timestamped with the caller's simulation time.

    Flushed to the operating system at least every ``flush_every_s`` of the log's own clock
    (the runtime's seconds for ``run``, simulated seconds for ``simulate``): a BLF gets its
    buffered frames written as one container and its header (start time, object count, file
    size) rewritten, so a process killed with SIGKILL leaves a log that reads back up to the
    last second, as the SQLite recorder's last commit does. The log's clock, not the wall
    clock, decides when, so a simulation writes the same bytes every time."""

    def __init__(self, path: Path | str, flush_every_s: float = 1.0) -> None:
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
        self.flush_every_s = flush_every_s
        self._flushed_s: float | None = None
        self.flushes = 0

    def log(self, msg: can.Message, t_s: float, *, rx: bool) -> None:
        """Record ``msg`` as received (``rx``) or sent at simulation time ``t_s``."""
        entry = copy.copy(msg)
        entry.timestamp = SIM_EPOCH_S + float(t_s)
        entry.is_rx = rx
        self._writer.on_message_received(entry)
        self.count += 1
        if self._flushed_s is None:
            self._flushed_s = float(t_s)
        elif not float(t_s) - self._flushed_s < self.flush_every_s:  # NaN times flush too
            self.flush()
            self._flushed_s = float(t_s)

    def flush(self) -> None:
        """Everything logged so far onto the file (the OS's buffers: survives SIGKILL of this
        process, not a power cut). BLF: the buffered frames as one compressed container and
        the header rewritten with the current start time and counts, which python-can's
        writer otherwise writes only when it is stopped (a killed log read back with times
        from 1970: nothing to replay)."""
        w = self._writer
        if isinstance(w, can.BLFWriter):
            w._flush()  # python-can writes containers only when full or stopped
            out = w.file
            end = out.tell()
            out.seek(0)
            w._write_header(end)
            out.seek(end)
        f = getattr(w, "file", None)  # both writers keep their open file as .file
        if f is not None:
            f.flush()
        self.flushes += 1

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


__all__ = [
    "LOG_SUFFIXES", "RESERVED_BUS_ARGS", "SIM_EPOCH_S", "FrameLog", "bus_arg_value", "open_bus",
    "parse_bus_args",
]  # fmt: skip
