"""Ctrl-C on a campaign stays quiet even when it lands inside distributed's ``sync`` before
its coroutine has started (an upstream race: ``cancel`` then raises a NameError on the client's
loop and tornado logs it with a traceback; CI at e219e17 saw it once in
``test_ctrl_c_on_the_process_cluster_is_quick_quiet_and_counts_what_it_kept``).

The race is made deterministic with the real parts: distributed's own ``sync`` on a real
tornado loop in its own thread, the loop held busy so the coroutine has not run, and a real
signal delivering the KeyboardInterrupt into ``sync``'s wait."""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections.abc import Iterator

import pytest

distributed = pytest.importorskip("distributed")
from distributed.utils import LoopRunner, sync  # noqa: E402

from packpilot.campaign.schedule import _CANCEL_RACE_FILTER, quiet_upstream_cancel_race  # noqa: E402


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@pytest.fixture
def tornado_records() -> Iterator[_Records]:
    log = logging.getLogger("tornado.application")
    h = _Records()
    log.addHandler(h)
    try:
        yield h
    finally:
        log.removeHandler(h)
        log.removeFilter(_CANCEL_RACE_FILTER)


def _interrupt_sync_before_its_coroutine_runs() -> None:
    runner = LoopRunner(asynchronous=False)
    runner.start()
    loop = runner.loop
    try:
        loop.add_callback(time.sleep, 0.5)  # the loop is busy: sync's coroutine waits behind it

        async def work() -> int:
            return 1

        def interrupt(signum: int, frame: object) -> None:
            raise KeyboardInterrupt

        old = signal.signal(signal.SIGALRM, interrupt)
        signal.setitimer(signal.ITIMER_REAL, 0.1)
        try:
            with pytest.raises(KeyboardInterrupt):
                sync(loop, work)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
        done = threading.Event()
        time.sleep(0.7)  # the busy callback ends; sync's f and then cancel run
        loop.add_callback(done.set)
        assert done.wait(5)
    finally:
        runner.stop()


def _race_records(records: list[logging.LogRecord]) -> list[logging.LogRecord]:
    return [
        r for r in records
        if r.exc_info and isinstance(r.exc_info[1], NameError) and "cancel" in r.getMessage()
    ]  # fmt: skip


def test_the_upstream_race_is_real_and_logs_a_traceback(tornado_records: _Records) -> None:
    """Without the filter the race shows (so the filter test below can fail)."""
    _interrupt_sync_before_its_coroutine_runs()
    assert _race_records(tornado_records.records)


def test_a_ctrl_c_inside_sync_before_it_starts_logs_nothing(tornado_records: _Records) -> None:
    quiet_upstream_cancel_race()
    _interrupt_sync_before_its_coroutine_runs()
    assert not _race_records(tornado_records.records)


def test_other_errors_on_the_loop_still_show(tornado_records: _Records) -> None:
    quiet_upstream_cancel_race()
    runner = LoopRunner(asynchronous=False)
    runner.start()
    try:
        done = threading.Event()

        def boom() -> None:
            raise NameError("something else")

        runner.loop.add_callback(boom)
        runner.loop.add_callback(done.set)
        assert done.wait(5)
    finally:
        runner.stop()
    assert any(r.exc_info and isinstance(r.exc_info[1], NameError) for r in tornado_records.records)
