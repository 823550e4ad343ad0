"""A step's events are rendered when read, from the core's one-step buffer: the metrics count
the same kinds the rendered events carry, and a record read too late says so."""

from __future__ import annotations

from collections import Counter

import pytest

from packpilot.config import load_config
from packpilot.sim.loop import ClosedLoop, n_steps
from tests.conftest import EXAMPLES


def _loop(name: str, duration_s: float) -> ClosedLoop:
    cfg = load_config(EXAMPLES / f"{name}.toml")
    sim = cfg.sim.model_copy(update={"duration_s": duration_s, "progress": False})
    return ClosedLoop.of(cfg.model_copy(update={"sim": sim}))


def test_metrics_count_the_kinds_of_the_rendered_events() -> None:
    loop = _loop("uav_mission", 200.0)
    seen: Counter[str] = Counter()
    dt = loop.cfg.sim.dt_s
    for k in range(n_steps(loop.cfg)):
        rec = loop.step(k, dt)
        seen.update(e.kind for e in rec.events[0])
    # The mission's first 200 s emit events (ten since issue #15 removed the hover's
    # join/guard chatter: R1, one R2 join, risk flags, a mode change, balancing).
    assert sum(seen.values()) >= 5
    assert loop.metrics.events[0] == seen
    assert list(loop.metrics.events[0]) == list(seen)  # the same first-seen order
    loop.close()


def test_events_read_after_the_next_step_are_refused() -> None:
    loop = _loop("uav_mission", 10.0)
    dt = loop.cfg.sim.dt_s
    first = loop.step(0, dt)
    loop.step(1, dt)
    with pytest.raises(RuntimeError, match="read after the loop stepped again"):
        _ = first.events
    loop.close()
