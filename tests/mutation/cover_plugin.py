"""A pytest plugin that records, per test, which lines of the mutated files it executes (the
map ``fast.py`` uses to run a mutant against only the tests that reach it; issue #26 item 4).

Loaded as ``-p tests.mutation.cover_plugin`` with ``MUTATE_COVER_FILES`` (the rules files,
``os.pathsep``-separated) and ``MUTATE_COVER_OUT`` (the JSON written at the end). Why our own
tracer and not coverage.py: it is not installed in the project's environment, and only a few
files matter, so the tracer returns no local trace function for any other frame (cheap).
Lines executed outside a test (at import, during collection) are recorded under ``""``; a test
that starts a subprocess (whose lines this tracer cannot see) is marked ``spawns``; with
``MUTATE_COVER_PARTIAL`` set (the map traced under a smaller Hypothesis budget than the mutant
runs get) every property test is marked ``partial``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import Any

import pytest

_FILES = os.environ.get("MUTATE_COVER_FILES", "")
_TARGETS = {os.path.realpath(p) for p in _FILES.split(os.pathsep) if p}
_KNOWN: dict[str, str | None] = {}
_DATA: dict[str, dict[str, set[int]]] = {"": {}}
_CUR: list[str] = [""]
_TESTS: dict[str, dict[str, Any]] = {}
_PARTIAL = bool(os.environ.get("MUTATE_COVER_PARTIAL"))
"""The map is traced under a smaller Hypothesis budget than the mutant runs: mark every
property test ``partial`` (its lines are a lower bound; the runner selects it always)."""


def _file(name: str) -> str | None:
    got = _KNOWN.get(name, "?")
    if got == "?":
        real = os.path.realpath(name)
        got = _KNOWN[name] = real if real in _TARGETS else None
    return got


def _local(frame: FrameType, event: str, arg: object) -> Any:
    if event == "line":
        f = _file(frame.f_code.co_filename)
        if f is not None:
            _DATA.setdefault(_CUR[0], {}).setdefault(f, set()).add(frame.f_lineno)
    return _local


def _global(frame: FrameType, event: str, arg: object) -> Any:
    f = _file(frame.f_code.co_filename)
    if f is None:
        return None
    _DATA.setdefault(_CUR[0], {}).setdefault(f, set()).add(frame.f_lineno)
    return _local


_POPEN_INIT = subprocess.Popen.__init__


def _popen_init(self: subprocess.Popen[Any], *a: Any, **kw: Any) -> None:
    if _CUR[0]:
        _TESTS.setdefault(_CUR[0], {})["spawns"] = True
    _POPEN_INIT(self, *a, **kw)


def pytest_configure(config: pytest.Config) -> None:
    if _TARGETS:
        subprocess.Popen.__init__ = _popen_init  # type: ignore[method-assign]
        threading.settrace(_global)
        sys.settrace(_global)


def _nodeid(item: pytest.Item) -> str:
    """The test's id relative to the working directory (what a later run is given), whatever
    pytest chose as its rootdir."""
    rel = os.path.relpath(item.path, os.getcwd())
    rest = item.nodeid.split("::", 1)
    return rel + ("::" + rest[1] if len(rest) > 1 else "")


_IDS: dict[str, str] = {}


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    node = _IDS[item.nodeid] = _nodeid(item)
    _CUR[0] = node
    _TESTS.setdefault(node, {})
    if _PARTIAL and getattr(getattr(item, "obj", None), "is_hypothesis_test", False):
        _TESTS[node]["partial"] = True  # traced on fewer examples than a mutant run gives it
    t0 = time.monotonic()
    yield
    _TESTS[node]["seconds"] = round(time.monotonic() - t0, 3)
    _CUR[0] = ""


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.failed:
        _TESTS.setdefault(_IDS.get(report.nodeid, report.nodeid), {})["failed"] = True


def pytest_unconfigure(config: pytest.Config) -> None:
    sys.settrace(None)
    threading.settrace(None)
    out = os.environ.get("MUTATE_COVER_OUT")
    if not out:
        return
    doc = {
        "tests": _TESTS,
        "lines": {ctx: {f: sorted(ls) for f, ls in per.items()} for ctx, per in _DATA.items()},
    }
    Path(out).write_text(json.dumps(doc))
