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


@pytest.fixture
def examples_dir() -> Path:
    return EXAMPLES
