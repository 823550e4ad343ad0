"""A first run starts at once: interpreted while the kernels compile in the background (#25).

What is asserted is what happened (the mode chosen, the progress lines, the results equal to
the compiled run's), never a wall time: speed is measured by ``benchmarks/bench_coldstart.py``.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from packpilot import coldstart
from packpilot.config import load_config
from packpilot.sim.runner import simulate

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "smart_battery.toml"


def _cli(args: list[str], cache: Path, **env: str) -> subprocess.CompletedProcess[str]:
    full = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "NUMBA_CACHE_DIR": str(cache)}
    full.pop("NUMBA_DISABLE_JIT", None)
    full.pop(coldstart.ENV_MODE, None)
    full.update(env)
    return subprocess.run(
        [sys.executable, "-m", "packpilot.cli", *args],
        capture_output=True, text=True, env=full, cwd=ROOT, timeout=600,
    )  # fmt: skip


def _stop_background(cache: Path) -> None:
    """Stop the background compile this test started (by its pid, from its status file)."""
    status = cache / "packpilot-compiled" / "status"
    with contextlib.suppress(OSError, ValueError, IndexError):
        pid = int(status.read_text().split()[3])
        os.kill(pid, signal.SIGTERM)


def test_cold_simulate_runs_interpreted_with_background_progress_and_same_results(
    tmp_path: Path,
) -> None:
    cache = tmp_path / "kernels"  # no cache of any kind: numba's is empty
    cache.mkdir()
    try:
        done = _cli(["simulate", str(EXAMPLE), "--duration", "20", "--json"], cache)
    finally:
        _stop_background(cache)
    assert done.returncode == 0, done.stderr
    err = done.stderr
    assert "running interpreted from the first step" in err
    assert f"{coldstart.BACKGROUND}:" in err  # the background compile's progress
    assert "compiling the BMS core for this machine, first run only" not in err  # no compile here
    status = (cache / "packpilot-compiled" / "status").read_text().split()
    assert len(status) == 4 and int(status[3]) > 0  # the child reported (k n stage pid)
    got = json.loads(done.stdout)
    assert got["build_time_s"] == 0  # nothing compiled in the command itself

    cfg = load_config(EXAMPLE)
    cfg = cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": 20.0})})
    ref = simulate(cfg).metrics  # this process: compiled
    for k, v in ref.items():
        if k != "wall_time_s":
            assert got[k] == (list(v) if isinstance(v, tuple) else v), k


def test_forced_interpreted_start_starts_no_background_compile(tmp_path: Path) -> None:
    cache = tmp_path / "kernels"
    cache.mkdir()
    done = _cli(
        ["simulate", str(EXAMPLE), "--duration", "2", "--json"], cache,
        **{coldstart.ENV_MODE: "interpreted"},
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["build_time_s"] == 0  # nothing compiled
    assert coldstart.BACKGROUND not in done.stderr
    assert not (cache / "packpilot-compiled" / "status").exists()


def test_bad_input_on_a_cold_start_is_one_error_line_and_no_background_compile(
    tmp_path: Path,
) -> None:
    cache = tmp_path / "kernels"
    cache.mkdir()
    bad = tmp_path / "no" / "such" / "dir" / "run.sqlite"
    done = _cli(["simulate", str(EXAMPLE), "--duration", "2", "--db", str(bad)], cache)
    assert done.returncode == 2
    assert len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert done.stderr.startswith("error:")
    assert not (cache / "packpilot-compiled" / "status").exists()


def test_policy_interpreted_when_shorter_than_the_compile_else_compile_first(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # an empty cache of its own: another test's background compile may have left the marker
    # of this example in the suite's cache (then the policy rightly says "compiled")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    short = coldstart.decide(["simulate", str(EXAMPLE), "--duration", "60"], False)
    assert short.mode == "background", short
    assert short.estimates["interpreted_s"] < short.estimates["compile_s"]
    # a run long enough that interpreting it costs more than compiling: compile first
    long = coldstart.decide(["simulate", str(EXAMPLE), "--duration=1e7"], False)
    assert long.mode == "compiled" and "compiling first" in long.reason, long
    # real time never waits for a compile
    rt = coldstart.decide(["run", str(EXAMPLE), "--period", "0.1"], False)
    assert rt.mode == "background", rt
    assert coldstart.decide(["simulate", str(EXAMPLE)], True).mode == "interpreted"
    assert coldstart.decide(["simulate", str(EXAMPLE)], False, "compiled").mode == "compiled"
    assert coldstart.decide(["report", "x.sqlite"], False).mode == "compiled"
    assert coldstart.decide(["simulate", "no_such_example"], False).mode == "compiled"


def test_compiled_kernels_marker_means_compiled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    mark = coldstart.marker(load_config(EXAMPLE))
    assert mark.is_relative_to(tmp_path)
    argv = ["simulate", str(EXAMPLE), "--duration", "60"]
    assert coldstart.decide(argv, False).mode == "background"
    mark.parent.mkdir(parents=True)
    mark.write_text("done\n")
    d = coldstart.decide(argv, False)
    assert d.mode == "compiled" and "compiled for this scenario" in d.reason
