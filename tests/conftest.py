"""Shared test fixtures: scenario builders on the real plant."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pytest

import tests.budget  # noqa: F401 - registers and loads the Hypothesis profile first

os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"


def dual_pack(
    switch: dict[str, Any] | None = None,
    v_a: float = 24.2,
    v_b: float = 22.2,
    load: dict[str, Any] | None = None,
    duration_s: float = 60.0,
    dt_s: float = 0.1,
    cell: str = "uav_5ah",
) -> dict[str, Any]:
    """Two 6S 5 Ah 20 mOhm batteries, the parallel-discharge spec's example."""
    return {
        "pack": {
            "cell": cell,
            "switch": switch or {"kind": "relay", "on_ohm": 0.0},
            "batteries": [
                {"name": "A", "cells_per_group": 6, "ocv0_v": v_a, "resistance_ohm": 0.02},
                {"name": "B", "cells_per_group": 6, "ocv0_v": v_b, "resistance_ohm": 0.02},
            ],
        },
        "load": load or {"kind": "none"},
        "sim": {"dt_s": dt_s, "duration_s": duration_s, "progress": False},
    }


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        "long(cpu_s): a test measured to take cpu_s CPU seconds; run first (see "
        "pytest_collection_modifyitems)",
    )


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Start the longest tests first, longest first.

    ``make test`` runs pytest-xdist's load scheduling on 2 workers: a worker gets consecutive
    items as it asks for them, so a 390 s test collected near the end runs while the other
    worker has nothing left (the fresh-clone CI of e035b38: workers busy 555 s and 1,065 s).
    Started first, the long tests run beside the rest of the suite. The order is a pure
    function of the collection, so every worker collects the same list, as xdist requires.
    """

    def cpu_s(item: pytest.Item) -> float:
        mark = item.get_closest_marker("long")
        return float(mark.kwargs.get("cpu_s", 0.0)) if mark is not None else 0.0

    items.sort(key=lambda item: -cpu_s(item))  # stable: the rest keep pytest's order


@pytest.fixture
def examples_dir() -> Path:
    return EXAMPLES
