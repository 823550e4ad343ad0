"""Kernel build time, measured and said aloud.

Numba compiles a kernel at its first call in a process, or loads it from the on-disk cache
(see :mod:`packpilot.jit`). Both take numba's compiler lock, which fires an event; the listeners
here (1) add up how long the lock was held, so a run reports its simulation time apart from the
time spent building kernels (``wall_time_s`` vs ``build_time_s``), and (2) on request say on
stderr that kernels are being compiled, with a heartbeat, so a first run never sits silent for
minutes. This module is not imported by any kernel's file: editing it recompiles nothing.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import IO, Any

from numba.core import event as nb_event


class _BuildClock(nb_event.Listener):
    """Time numba holds its compiler lock: compiling a kernel or loading it from the on-disk
    cache (the first call of a kernel in a process; later calls never take the lock). The
    lock is reentrant and its event fires per entry, so only the outermost entry of each
    thread counts."""

    def __init__(self) -> None:
        self.wall_s = 0.0
        self.cpu_s = 0.0
        self._local = threading.local()

    def on_start(self, event: Any) -> None:
        loc = self._local
        depth = getattr(loc, "depth", 0)
        if depth == 0:
            loc.t0, loc.c0 = time.perf_counter(), time.process_time()
        loc.depth = depth + 1

    def on_end(self, event: Any) -> None:
        loc = self._local
        loc.depth -= 1
        if loc.depth == 0:
            self.wall_s += time.perf_counter() - loc.t0
            self.cpu_s += time.process_time() - loc.c0


_CLOCK = _BuildClock()
nb_event.register("numba:compiler_lock", _CLOCK)  # type: ignore[no-untyped-call]


def build_seconds() -> float:
    """Wall seconds this process has spent compiling kernels or loading them from the cache
    so far (a run reports the difference apart from its simulation time)."""
    return _CLOCK.wall_s


COMPILING = "compiling the BMS core for this machine, first run only"


_HEARTBEAT = r"""
import os, select, sys, time
prefix, every = sys.argv[1], float(sys.argv[2])
t0 = last = time.perf_counter()
state, buf, fd = "", b"", sys.stdin.fileno()
while True:
    ready, _, _ = select.select([fd], [], [], every / 4)
    now = time.perf_counter()
    if ready:
        chunk = os.read(fd, 65536)
        if not chunk:
            break
        *lines, buf = (buf + chunk).split(b"\n")
        for raw in lines:
            text = raw.decode()
            if text.startswith("!"):
                state = text[1:]
                continue
            state = text
            print(f"{prefix}: {text} ({now - t0:.0f} s)", file=sys.stderr, flush=True)
            last = now
    if state and now - last >= every:
        print(f"{prefix}: {state} ({now - t0:.0f} s)", file=sys.stderr, flush=True)
        last = now
"""
"""The heartbeat's own process: numba holds the GIL through long stretches of LLVM work (up to
22 s seen here), which starved a heartbeat thread; a process of its own keeps the beat."""


class _Announcer(nb_event.Listener):
    """Says on ``stream`` that kernels are being compiled (never for a cache load: numba
    fires ``numba:compile`` only for a real compile): a line when a kernel is done (at most
    two per ``every_s``), and a heartbeat naming the kernel being compiled when nothing else
    was said for ``every_s``, so a user never watches more than ``every_s`` of silence. The
    heartbeat runs in a small child process writing to the same stream (a thread when the
    stream has no file descriptor)."""

    def __init__(self, stream: IO[str], every_s: float) -> None:
        self.stream, self.every_s = stream, every_s
        self.done = 0
        self.depth = 0
        self.stack: list[str] = []
        """The kernels being compiled, outermost first (a kernel compiles its callees)."""
        self.t0 = 0.0
        self.last = 0.0
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._beat: threading.Thread | None = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._started = False
        self._state = ""
        """What the heartbeat repeats (thread form; the child process keeps its own)."""

    def _start(self) -> None:
        self._started = True
        self.t0 = time.perf_counter()
        try:
            fd = self.stream.fileno()
        except (AttributeError, OSError, ValueError):
            fd = -1
        if fd >= 0 and os.name == "posix":
            self.stream.flush()
            self._proc = subprocess.Popen(
                [sys.executable, "-c", _HEARTBEAT, COMPILING, str(self.every_s)],
                stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=fd,
            )  # fmt: skip
        else:
            self._beat = threading.Thread(target=self._heartbeat, daemon=True)
            self._beat.start()
        self._say("starting (the compiled kernels are cached for the next runs)")

    def _say(self, text: str, quiet: bool = False) -> None:
        """``text`` said now (or, ``quiet``, only kept as what the heartbeat repeats)."""
        if self._proc is not None and self._proc.stdin is not None:
            try:
                self._proc.stdin.write((("!" if quiet else "") + text + "\n").encode())
                self._proc.stdin.flush()
            except OSError:
                pass
            if not quiet:
                self.last = time.perf_counter()
            return
        self._state = text
        if not quiet:
            self.last = time.perf_counter()
            line = f"{COMPILING}: {text} ({self.last - self.t0:.0f} s)"
            print(line, file=self.stream, flush=True)

    def on_start(self, event: Any) -> None:
        with self._lock:
            if not self._started:
                self._start()
            self.depth += 1
            self.stack.append(_name(event.data["dispatcher"]))
            self._say(f"{self.done} kernels compiled, now {self.stack[-1]}", quiet=True)

    def on_end(self, event: Any) -> None:
        with self._lock:
            self.depth -= 1
            self.done += 1
            if self.stack:
                self.stack.pop()
            name = _name(event.data["dispatcher"])
            loud = self.depth == 0 or time.perf_counter() - self.last >= self.every_s / 2
            where = f", now {self.stack[-1]}" if self.stack else ""
            self._say(f"{self.done} kernels compiled, last {name}{where}", quiet=not loud)
            if self.depth == 0:
                self._say("", quiet=True)  # not compiling any more: no heartbeat

    def _heartbeat(self) -> None:
        while not self._stop.wait(self.every_s / 4):
            with self._lock:
                if self.depth > 0 and time.perf_counter() - self.last >= self.every_s:
                    self._say(self._state)

    def close(self) -> None:
        self._stop.set()
        if self._beat is not None:
            self._beat.join()
        if self._proc is not None:
            if self._proc.stdin is not None:
                with contextlib.suppress(OSError):
                    self._proc.stdin.close()
            self._proc.wait()


def _name(dispatcher: Any) -> str:
    fn = getattr(dispatcher, "py_func", None)
    module = str(getattr(fn, "__module__", None) or "")
    name = str(getattr(fn, "__qualname__", None) or "?").replace("<locals>.", "")
    return f"{module.removeprefix('packpilot.')}.{name}" if module else name


@contextmanager
def announce_compiles(stream: IO[str], every_s: float = 1.0) -> Iterator[None]:
    """While the block runs, say on ``stream`` whenever a kernel is compiled (see
    :class:`_Announcer`); silent when everything comes from the cache."""
    ann = _Announcer(stream, every_s)
    nb_event.register("numba:compile", ann)  # type: ignore[no-untyped-call]
    try:
        yield
    finally:
        nb_event.unregister("numba:compile", ann)  # type: ignore[no-untyped-call]
        ann.close()


__all__ = ["COMPILING", "announce_compiles", "build_seconds"]
