"""A pytest fork server for mutant runs (issue #26 item 4): imports the third-party libraries
once, then forks a fresh child per request, so each mutant pays neither interpreter start nor
the numpy / numba / hypothesis / pytest imports (about 2 s of the 4 s a 1-test run took).

Why this is safe: the server never imports ``packpilot`` or ``tests``; each child imports them
fresh from the private tree after the runner has written the mutated file, so no mutated (or
unmutated) rule survives from one mutant to the next. Run as a script, cwd = the private tree,
``NUMBA_DISABLE_JIT=1`` already in the environment.

Protocol (one JSON object per line): request ``{"args": [...pytest args], "timeout": s,
"log": path}``, reply ``{"state": "passed|failed|timeout|invalid", "seconds": s, "detail":
line}``. A child that outlives ``timeout`` is killed with its process group.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import signal
import sys
import time

for _name in ("numpy", "numpy.typing", "numba", "scipy", "scipy.optimize", "pydantic",
              "hypothesis", "hypothesis.strategies", "pytest", "can", "cantools", "dronecan",
              "pymavlink.mavutil", "typer", "typer.testing", "yaml", "sqlite3", "tomllib",
              "_pytest.python", "_pytest.runner", "xdist"):  # fmt: skip
    with contextlib.suppress(Exception):  # a missing optional library: the child imports it
        importlib.import_module(_name)
assert not any(m == "packpilot" or m.startswith(("packpilot.", "tests")) for m in sys.modules)


def _child(args: list[str], log: str) -> None:
    os.setpgid(0, 0)
    fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    sys.stdin.close()
    import pytest

    code = 3
    try:
        code = int(pytest.main(args))
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _wait(pid: int, timeout: float) -> int | None:
    """The child's exit code, or None after killing it at ``timeout``."""
    end = time.monotonic() + timeout
    while True:
        got, status = os.waitpid(pid, os.WNOHANG)
        if got:
            return os.waitstatus_to_exitcode(status)
        if time.monotonic() > end:
            for sig in (signal.SIGTERM, signal.SIGKILL):
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(pid, sig)
                time.sleep(0.2)
            os.waitpid(pid, 0)
            return None
        time.sleep(0.02)


def _detail(log: str) -> tuple[list[str], str]:
    try:
        with open(log, encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    except OSError:
        return [], ""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    failed = [ln for ln in lines if ln.startswith(("FAILED", "ERROR"))]
    return lines, (failed[0] if failed else (lines[-1] if lines else ""))


_NO_IMPORT = ("during collection", "found no collectors")
"""pytest's words for a test file that failed to import (exit 2 for a file, 4 for a test id)."""


def main() -> None:
    for raw in sys.stdin:
        req = json.loads(raw)
        t0 = time.monotonic()
        pid = os.fork()
        if pid == 0:
            _child(req["args"], req["log"])
        code = _wait(pid, float(req["timeout"]))
        secs = round(time.monotonic() - t0, 2)
        lines, detail = _detail(req["log"])
        if code is None:
            state, detail = "timeout", f"no result after {req['timeout']:.0f} s"
        elif code in (0, 1):
            state = ("passed", "failed")[code]
        elif code in (2, 4) and any(m in "\n".join(lines) for m in _NO_IMPORT):
            state = "invalid"  # the mutated module no longer imports
        else:
            state = "error"  # pytest itself failed (usage, internal error, a crash): look
        print(json.dumps({"state": state, "seconds": secs, "detail": detail[:300],
                          "code": code}), flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
