"""Single-point mutants of the dashboard's access rules (#18 §5), each of which a test in
``tests/test_web_security.py`` must kill: ``python -m tests.mutation.web`` (about a minute).

Same idea as ``mutants.py`` (a snippet that occurs exactly once, its replacement, the rule it
breaks), for ``src/packpilot/web/``; the file is restored after each run. Exit code 1 when a
mutant survives or a snippet went stale.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
WEB = "src/packpilot/web/"

# (file, old, new, -k selection of the killing tests, the rule)
MUTANTS: list[tuple[str, str, str, str, str]] = [
    ("guard.py", "        if not self.guard.host_ok(scope):", "        if False:",
     "host", "a foreign Host header is refused"),
    ("guard.py", "return origin.strip().lower() in {", "return True or origin.strip().lower() in {",
     "origin", "a WebSocket Origin must be the page's own"),
    ("guard.py", "return client is not None and is_loopback(str(client[0]))", "return True",
     "without_origin", "no Origin only from a loopback peer"),
    ("app.py", "if app.state.websockets >= rules.max_websockets:",
     "if app.state.websockets > rules.max_websockets:", "cap", "the WebSocket cap"),
    ("guard.py", "            evict_oldest_pending(self.connections)", "            pass",
     "half_open or slow_bodies", "a full server evicts the oldest connection not served"),
    ("guard.py", "    if state is h11.IDLE:\n        return True", "    if state is h11.IDLE:\n"
     "        return False", "half_open", "an idle connection is not being served"),
    ("guard.py", "        if _serving(self) and self.conn.their_state is h11.IDLE:\n"
     "            self.transport.abort()", "        pass", "half_open",
     "the request-head timeout"),
    ("guard.py", "            self._arm_head_timer()\n\n    def connection_lost",
     "            pass\n\n    def connection_lost", "keep_alive",
     "the head timeout restarts after each response"),
    ("guard.py", "        if _serving(self) and self.conn.their_state is h11.SEND_BODY:\n"
     "            self.transport.abort()", "        pass", "trickled",
     "the request-body timeout"),
    ("guard.py", "elif length is not None and not _size_ok(length, self.max_bytes):",
     "elif False:", "oversized", "a body is refused by its declared size before auth"),
    ("app.py", "    app.add_middleware(_BodyLimitMiddleware)", "    pass", "oversized",
     "the body cap runs (outermost)"),
    ("app.py", "if not self.rules.token_ok(request.scope, header_only=True):",
     "if not self.rules.token_ok(request.scope):", "token_on_loopback",
     "controls take the token from the header only"),
    ("app.py",
     'if not self.rules.origin_ok(request.scope):\n            return _error(403, "cross-',
     'if False:\n            return _error(403, "cross-', "token_on_loopback",
     "controls refuse a foreign Origin"),
    ("guard.py", "if self.guard.remote and not self.guard.token_ok(scope):", "if False:",
     "remote_mode", "remote mode needs the token on every request"),
    ("session.py", "return real.is_file() and real.is_relative_to(self.runs_dir)",
     "return real.is_file()", "recordings_only", "recordings only inside --runs-dir"),
    ("session.py", 'if not name or "\\x00" in name', "if not name", "recordings_only",
     "a NUL in a recording name is refused"),
    ("guard.py", "        if not allow_remote:\n", "        if False:\n", "non_loopback",
     "a non-loopback bind needs --allow-remote"),
    ("app.py", '"X-Frame-Options": "DENY",', "", "framed", "the page cannot be framed"),
]  # fmt: skip


def main() -> int:
    bad = 0
    for name, old, new, select, why in MUTANTS:
        path = ROOT / WEB / name
        src = path.read_text(encoding="utf-8")
        if src.count(old) != 1:
            print(f"STALE    {name}: {why}")
            bad += 1
            continue
        path.write_text(src.replace(old, new), encoding="utf-8")
        try:
            r = subprocess.run(
                [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                 "tests/test_web_security.py", "-k", select],
                cwd=ROOT, capture_output=True, text=True, timeout=600,
            )  # fmt: skip
        finally:
            path.write_text(src, encoding="utf-8")
        killed = r.returncode != 0
        bad += not killed
        print(f"{'killed  ' if killed else 'SURVIVED'} {name}: {why}")
    print(f"{len(MUTANTS) - bad}/{len(MUTANTS)} killed")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
