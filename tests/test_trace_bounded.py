"""A long run's in-memory trace is bounded (issue #18 §3: ``duration_s = 1e9`` grew without
bound, every sample kept): past ``MAX_TRACE_ROWS`` rows it is decimated, the last step stays,
the recorder still gets every step, and the kept rows are exactly the full run's rows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.record import Result
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.sim import record
from packpilot.sim.runner import Runner
from tests.conftest import dual_pack

STEPS = 301  # 30.1 s at 0.1 s


def _run(tmp_path: Path | None = None) -> Result:
    cfg = parse_config(dual_pack(load={"kind": "current", "value": 10.0}, duration_s=30.1))
    if tmp_path is None:
        return Runner(cfg, progress=False).run()
    with SQLiteRecorder(tmp_path / "run.sqlite") as rec:
        return Runner(cfg, recorder=rec, progress=False).run()


def test_a_long_trace_is_decimated_and_exact(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    full = _run()
    monkeypatch.setattr(record, "MAX_TRACE_ROWS", 64)
    small = _run(tmp_path)
    steps = small.trace.step
    assert len(steps) <= 65  # 64 kept rows and the last step
    assert steps[-1] == STEPS - 1
    stride = int(steps[1] - steps[0])
    assert stride == 8 and np.all(steps[:-1] % stride == 0)
    np.testing.assert_array_equal(small.trace.battery, full.trace.battery[steps])
    for name, rows in small.trace.status.items():
        assert rows == [full.trace.status[name][k] for k in steps]
    assert small.metrics == {**full.metrics, "wall_time_s": small.metrics["wall_time_s"]}
    stored = load_run(tmp_path / "run.sqlite")
    assert stored.trace.t_s.size == STEPS  # the recorder got every step
