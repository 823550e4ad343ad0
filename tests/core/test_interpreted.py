"""The same source runs interpreted: every example under ``NUMBA_DISABLE_JIT=1`` does what the
compiled run does, **to the bit** (trace, status, events, metrics).

A first run starts interpreted while the kernels compile (``packpilot.coldstart``), so a result
must not depend on which of the two ran it. This test once allowed 1e-9 relative: that hid the
cell model's fused multiply-adds (LLVM contracted ``a * b + c`` where the interpreter rounded
twice), which moved every example's golden hashes interpreted; they are explicit ``fma`` calls
now (``packpilot.model.fma``) and the comparison is exact. The golden windows of a few examples
are also run interpreted against ``tests/golden/hashes.json``.
"""

from __future__ import annotations

import json
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


@pytest.fixture(scope="module")
def interpreted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("interpreted")
    # src first: a git worktree whose venv has another checkout installed editable must run
    # its own source interpreted, not the installed one.
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
def test_interpreted_run_is_bit_identical_to_the_compiled_run(name: str, interpreted: Path) -> None:
    arrays, doc = record(run(name))
    other = json.loads((interpreted / f"{name}.json").read_text())
    got = json.loads(json.dumps(doc))
    for key in ("events", "status", "metrics"):
        assert got[key] == other[key], f"{name}: {key} differ interpreted"
    with np.load(interpreted / f"{name}.npz") as npz:
        assert sorted(npz.files) == sorted(arrays)
        for k, a in arrays.items():
            b = npz[k]
            assert a.dtype == b.dtype and a.shape == b.shape, f"{name}.{k}"
            rows = np.nonzero((a != b) & ~(np.isnan(a) & np.isnan(b)) if a.dtype.kind == "f"
                              else a != b)[0]  # fmt: skip
            assert rows.size == 0, f"{name}.{k}: first differing step {rows[:1]}"


GOLDEN_SAMPLE = ("equalization_uav12s", "protection_cold_heavy", "sequencing_hot_insert")
"""Golden windows run interpreted (whole windows, a few seconds each interpreted)."""


def test_golden_windows_interpreted_match_the_pinned_hashes() -> None:
    path = os.pathsep.join([str(ROOT / "src"), str(ROOT)])
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "PYTHONPATH": path}
    done = subprocess.run(
        [sys.executable, "-m", "tests.golden.fingerprint", *GOLDEN_SAMPLE],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count(" same ") == len(GOLDEN_SAMPLE), done.stdout
