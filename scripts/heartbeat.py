"""Run a set-up command and never stay silent for more than 1.5 s (issue #25).

``make demo``'s longest silences were in the set-up, not in PackPilot: ``python -m venv``
(2.6 s) and pip's "Installing collected packages" phase (12.7 s on a quiet machine, fresh
clone, 2026-11-28), during which pip prints nothing. This wrapper passes the command's output
through line by line and, whenever the command has said nothing for 1.5 s, prints one line
saying what is still running and for how long. It changes nothing else: same command, same
exit status.

    python3 scripts/heartbeat.py "creating the venv" -- python3 -m venv .venv

Standard library only: it runs before the venv exists.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from typing import IO

BEAT_S = 1.5


def _pump(stream: IO[str], last: list[float], lock: threading.Lock) -> None:
    """Copy the child's merged output to our stdout, remembering when it last spoke."""
    for line in stream:
        with lock:
            sys.stdout.write(line)
            sys.stdout.flush()
            last[0] = time.monotonic()


def main(argv: list[str]) -> int:
    if len(argv) < 3 or argv[1] != "--":
        print("usage: heartbeat.py LABEL -- COMMAND...", file=sys.stderr)
        return 2
    label, command = argv[0], argv[2:]
    start = time.monotonic()
    last = [start]
    lock = threading.Lock()
    child = subprocess.Popen(
        command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1
    )
    assert child.stdout is not None
    pump = threading.Thread(target=_pump, args=(child.stdout, last, lock), daemon=True)
    pump.start()
    while child.poll() is None:
        time.sleep(0.25)
        now = time.monotonic()
        with lock:
            if now - last[0] >= BEAT_S:
                print(f"setup: {label}, still running ({now - start:.0f} s)", flush=True)
                last[0] = now
    pump.join()
    return child.returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
