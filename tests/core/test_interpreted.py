"""The same source runs interpreted: every example under ``NUMBA_DISABLE_JIT=1`` does what the
compiled run does.

The kernels are plain Python over NumPy arrays, so a rule can be stepped through in a debugger
or checked without a compiler. Compiled and interpreted arithmetic may differ in the last bits
(LLVM fuses and reorders a few float operations, and its ``exp``/``log`` are not NumPy's), so
the comparison is: the same events (time, kind, battery, message), the same status text, and
every number within 1e-9 relative.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.golden.fingerprint import ROOT, _norm, events_of, example_names, trace_arrays

STEPS = 400
"""Steps per example: enough to cross each example's first decisions, cheap interpreted."""

_SCRIPT = """
import json, sys
import numpy as np
from pathlib import Path
from tests.core.test_interpreted import run, record
out = Path(sys.argv[1])
for name in sys.argv[2:]:
    res = run(name)
    arrays, doc = record(res)
    np.savez(out / f"{name}.npz", **arrays)
    (out / f"{name}.json").write_text(json.dumps(doc))
"""


def run(name: str) -> Any:
    from packpilot.config import load_config
    from packpilot.sim.runner import simulate

    cfg = load_config(ROOT / "examples" / f"{name}.toml")
    duration = min(cfg.sim.duration_s, STEPS * cfg.sim.dt_s)
    sim = cfg.sim.model_copy(update={"duration_s": duration, "progress": False})
    return simulate(cfg.model_copy(update={"sim": sim}))


def record(res: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    arrays = {k: v for k, v in trace_arrays(res).items() if v is not None}
    doc = {
        "events": _norm(events_of(res)),
        "status": _norm(res.trace.status),
        "metrics": _norm({k: v for k, v in res.metrics.items() if k != "wall_time_s"}),
    }
    return arrays, doc


def _close(a: Any, b: Any, where: str) -> None:
    """Structures equal, numbers within 1e-9 relative (NaN equals NaN)."""
    if isinstance(a, float) or isinstance(b, float):
        assert isinstance(a, int | float) and isinstance(b, int | float), where
        if math.isnan(a) or math.isnan(b):
            assert math.isnan(a) and math.isnan(b), where
        else:
            assert math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9), (where, a, b)
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _close(x, y, f"{where}[{i}]")
    else:
        assert a == b, (where, a, b)


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("interpreted")
    # The checkout's own sources first: an editable install may point at another worktree.
    path = os.pathsep.join([str(ROOT / "src"), str(ROOT)])
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": path}
    subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(out), *example_names()],
        cwd=ROOT,
        env=env,
        check=True,
        timeout=900,
    )
    return out


@pytest.mark.parametrize("name", example_names())
def test_interpreted_run_does_what_the_compiled_run_does(name: str, interpreted: Path) -> None:
    arrays, doc = record(run(name))
    other = json.loads((interpreted / f"{name}.json").read_text())
    got = [e[:4] for e in doc["events"]]
    assert got == [e[:4] for e in other["events"]]  # same time, kind, battery, message
    _close(json.loads(json.dumps(doc)), other, name)
    with np.load(interpreted / f"{name}.npz") as npz:
        assert sorted(npz.files) == sorted(arrays)
        for k, a in arrays.items():
            np.testing.assert_allclose(npz[k], a, rtol=1e-9, atol=1e-9, err_msg=f"{name}.{k}")
