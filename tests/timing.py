"""Where a test run's time goes (#25): a pytest plugin that `make test` loads (``-p tests.timing``).

``--durations`` gives wall seconds per phase; on a shared 2-core machine wall time says more
about the neighbours than about the test. This plugin records, per test (setup + call +
teardown, in the process that ran it): wall seconds, the process's CPU seconds, the CPU seconds
of the subprocesses it waited for (a CLI test's ``packpilot`` child; ``RUSAGE_CHILDREN``, so a
detached grandchild such as a background compile is not counted), and the CPU seconds spent
inside numba compiles (a ``numba:compile`` listener, top-level compiles only: typing a kernel
compiles its callees inside it; fired for a real compile, never for a cache load). With
pytest-xdist the numbers travel to the controller in each report's ``user_properties``.

At the end it prints the totals (the same three CPU figures summed, per worker too) and the
tests with the most wall time and their CPU split: what to read before shortening anything.
"""

from __future__ import annotations

import resource
import time
from collections import defaultdict
from typing import Any

import pytest

KEY = "packpilot_timing"
TOP = 40
"""Tests listed at the end, the longest first."""

_compile = {"depth": 0, "c0": 0.0, "cpu": 0.0}


def _install_listener() -> None:
    """Count the CPU time of numba's top-level compiles in this process."""
    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba is a dependency
        return

    class _Compiles(event.Listener):  # type: ignore[misc]
        def on_start(self, ev: Any) -> None:
            if _compile["depth"] == 0:
                _compile["c0"] = time.process_time()
            _compile["depth"] += 1

        def on_end(self, ev: Any) -> None:
            _compile["depth"] -= 1
            if _compile["depth"] == 0:
                _compile["cpu"] += time.process_time() - _compile["c0"]

    event.register("numba:compile", _Compiles())


_install_listener()


def _snapshot() -> tuple[float, float, float, float]:
    ch = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (time.perf_counter(), time.process_time(), ch.ru_utime + ch.ru_stime,
            _compile["cpu"])  # fmt: skip


_start: dict[str, tuple[float, float, float, float]] = {}


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    _start[item.nodeid] = _snapshot()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Any:
    if call.when == "teardown" and item.nodeid in _start:
        a, b = _start.pop(item.nodeid), _snapshot()
        wall, cpu, child, comp = (y - x for x, y in zip(a, b, strict=True))
        item.user_properties.append((KEY, (wall, cpu, child, comp)))
    yield


class _Totals:
    def __init__(self) -> None:
        self.tests: dict[str, tuple[float, float, float, float]] = {}
        self.worker: dict[str, list[float]] = defaultdict(lambda: [0.0] * 4)
        self.t0 = time.perf_counter()


_totals = _Totals()


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when != "teardown":
        return
    for k, v in report.user_properties:
        if k == KEY:
            _totals.tests[report.nodeid] = tuple(v)  # type: ignore[assignment]
            node = getattr(report, "node", None)  # pytest-xdist: the worker that ran it
            w = _totals.worker[node.gateway.id if node is not None else "main"]
            for i in range(4):
                w[i] += v[i]


def pytest_terminal_summary(terminalreporter: Any) -> None:
    t = _totals
    if not t.tests:
        return
    tr = terminalreporter
    wall = time.perf_counter() - t.t0
    tr.section("where the time went (tests/timing.py)")
    tr.write_line(f"wall since pytest started {wall:.0f} s; per worker: test wall / own CPU / "
                  "waited children's CPU / numba compile CPU (s)")  # fmt: skip
    for name, (w, c, ch, co) in sorted(t.worker.items()):
        tr.write_line(f"  {name}: {w:.0f} / {c:.0f} / {ch:.0f} / {co:.0f}")
    s = [sum(v[i] for v in t.tests.values()) for i in range(4)]
    tr.write_line(f"  all {len(t.tests)} tests: {s[0]:.0f} / {s[1]:.0f} / {s[2]:.0f} / {s[3]:.0f}")
    tr.write_line(f"the {TOP} longest tests (wall / CPU / children's CPU / compile CPU, s):")
    for nodeid, (w, c, ch, co) in sorted(t.tests.items(), key=lambda kv: -kv[1][0])[:TOP]:
        tr.write_line(f"  {w:7.1f} {c:7.1f} {ch:7.1f} {co:7.1f}  {nodeid}")
