"""The constant-current heat bound that benchmarks/bench_charging.py --breakdown reports."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from types import ModuleType

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_charging.py"


def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_charging", BENCH)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


STAGES = [(33.8 * 3600, 0.0131, 2), (141.0 * 3600, 0.0115, 4), (205.8 * 3600, 0.0124, 6)]


def _schedule(currents: list[float]) -> tuple[float, float]:
    heat = sum(q * i * r / n for (q, r, n), i in zip(STAGES, currents, strict=True))
    time = sum(q / i for (q, _, _), i in zip(STAGES, currents, strict=True))
    return heat, time


def test_equal_heat_rate_schedule_reaches_the_bound() -> None:
    bound = _bench().cc_heat_bound_j
    currents = [90.0 * math.sqrt(n / 6 * 0.0124 / r) for _, r, n in STAGES]
    heat, time = _schedule(currents)
    assert bound(STAGES, time) == pytest.approx(heat, rel=1e-12)


@pytest.mark.parametrize(
    "currents", [[100.0, 100.0, 100.0], [40.0, 80.0, 100.0], [57.7, 81.6, 90.0], [20.0, 90.0, 95.0]]
)
def test_other_schedules_heat_more_in_the_same_time(currents: list[float]) -> None:
    bound = _bench().cc_heat_bound_j
    heat, time = _schedule(currents)
    assert heat >= bound(STAGES, time) * (1.0 - 1e-12)


def test_bound_scales_inversely_with_time_and_ignores_empty_stages() -> None:
    bound = _bench().cc_heat_bound_j
    assert bound(STAGES, 2000.0) == pytest.approx(2.0 * bound(STAGES, 4000.0))
    assert bound([*STAGES, (0.0, 0.02, 3)], 4000.0) == bound(STAGES, 4000.0)
    assert bound(STAGES, 0.0) == math.inf
