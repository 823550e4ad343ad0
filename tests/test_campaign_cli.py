"""``packpilot campaign`` end to end in a subprocess: JSON, Parquet, PNG, resume, a real kill."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq

CLI = [sys.executable, "-m", "packpilot.cli", "campaign"]

SCENARIO = """
controller = ["sequencing"]
[pack]
cell = "ecm_example"
[pack.switch]
kind = "mosfet_pair"
on_ohm = 0.0001
[[pack.batteries]]
name = "A"
cells_per_group = 6
ocv0_v = 24.2
resistance_ohm = 0.02
[[pack.batteries]]
name = "B"
cells_per_group = 6
ocv0_v = 22.2
resistance_ohm = 0.02
[load]
kind = "current"
value = 20.0
[sim]
dt_s = 0.1
duration_s = 4.0
"""


def _env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "PACKPILOT_CAMPAIGN_FAIL_RUNS"}
    env.update(extra)
    return env


def _run(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI, *args], capture_output=True, text=True, timeout=300, env=_env(**env)
    )


def _scenario(tmp_path: Path) -> Path:
    p = tmp_path / "dual.toml"
    p.write_text(SCENARIO)
    return p


def test_campaign_json_parquet_png_and_resume(tmp_path: Path) -> None:
    cfg = _scenario(tmp_path)
    out = tmp_path / "res.parquet"
    common = ["--spread", "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35", "--seed", "5"]
    common += ["--out", str(out), "--json"]
    proc = _run(
        str(cfg), "--runs", "8", "--scheduler", "threads", *common, PACKPILOT_CAMPAIGN_FAIL_RUNS="6"
    )
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(proc.stdout)
    assert (rep["rows"], rep["computed"], rep["skipped"], rep["failures"]) == (8, 8, 0, 1)
    assert rep["scheduler"] == "threads"
    assert rep["summary"]["min_cell_v"]["n"] == 7
    s = rep["summary"]["ambient_c"]
    assert -10 <= s["p5"] <= s["p50"] <= s["p95"] <= 35
    table = pq.read_table(out)
    assert table.num_rows == 8 and table.column("status").to_pylist()[6] == "error"
    # no histograms unless asked for (#29: mc.png was written unasked)
    assert rep["histograms_png"] is None and not out.with_suffix(".png").exists()
    assert not list(tmp_path.glob("*.png"))

    png = tmp_path / "hist.png"
    proc = _run(str(cfg), "--runs", "11", "--resume", *common, "--plot", str(png))
    assert proc.returncode == 0, proc.stderr
    rep = json.loads(proc.stdout)
    assert (rep["rows"], rep["computed"], rep["skipped"]) == (11, 3, 8)
    assert Path(rep["histograms_png"]) == png and png.stat().st_size > 10_000
    assert rep["scheduler"] == "sync"  # auto: a few seconds of work stays in-process
    # The failed run stays recorded (with its error) after the resume.
    assert pq.read_table(out).column("status").to_pylist().count("error") == 1


def test_table_output_without_json(tmp_path: Path) -> None:
    cfg = _scenario(tmp_path)
    proc = _run(
        str(cfg), "--runs", "3", "--scheduler", "sync", "--out", str(tmp_path / "t.parquet")
    )
    assert proc.returncode == 0, proc.stderr
    assert "P50" in proc.stdout and "min_cell_v" in proc.stdout
    assert "failed to compute: 0" in proc.stdout and "wrote" in proc.stdout
    assert "verdicts: OK" in proc.stdout and "over-discharged at the end:" in proc.stdout
    assert "\x1b[" not in proc.stdout  # no progress bar / colours when not a terminal


def test_bad_input_is_one_line_exit_2(tmp_path: Path) -> None:
    cfg = _scenario(tmp_path)
    for args, needle in (
        (["--runs", "3", "--spread", "capacity=5%,r0=ten"], "'r0=ten'"),
        (["--runs", "0"], "--runs must be >= 1"),
        (["--runs", "2", "--scheduler", "thread"], "--scheduler 'thread'"),
        (["--runs", "2", "--workers", "0"], "--workers must be >= 1"),
    ):
        proc = _run(str(cfg), *args, "--out", str(tmp_path / "x.parquet"))
        assert proc.returncode == 2, (args, proc.stderr)
        assert needle in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
        assert "Traceback" not in proc.stderr


def test_killed_campaign_keeps_its_parts_and_resume_completes_it(tmp_path: Path) -> None:
    cfg = _scenario(tmp_path)
    out = tmp_path / "k.parquet"
    args = [str(cfg), "--runs", "30", "--scheduler", "sync", "--batch", "1", "--out", str(out)]
    args += ["--duration", "12", "--spread", "capacity=5%", "--json"]
    proc = subprocess.Popen([*CLI, *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    parts = Path(str(out) + ".parts")
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline:
            if parts.exists() and len(list(parts.glob("part-*.parquet"))) >= 3:
                break
            assert proc.poll() is None, "campaign finished before it could be interrupted"
            time.sleep(0.01)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    kept = len(list(parts.glob("part-*.parquet")))
    assert 3 <= kept < 30 and not out.exists()
    res = _run(*args, "--resume")
    assert res.returncode == 0, res.stderr
    rep = json.loads(res.stdout)
    assert rep["skipped"] == kept and rep["computed"] == 30 - kept and rep["rows"] == 30
    assert pq.read_table(out).column("run").to_pylist() == list(range(30))
    assert not parts.exists()


def test_ctrl_c_on_the_process_cluster_is_quick_quiet_and_counts_what_it_kept(
    tmp_path: Path,
) -> None:
    """Ctrl-C in a terminal reaches the whole process group (the workers too): the campaign
    stops within a couple of seconds, prints no Dask warnings or tracebacks, and says how many
    finished runs it kept, which is what is on disk (#29)."""
    cfg = _scenario(tmp_path)
    out = tmp_path / "c.parquet"
    args = [str(cfg), "--runs", "40", "--scheduler", "processes", "--workers", "2", "--batch", "1"]
    args += ["--out", str(out), "--duration", "20", "--spread", "capacity=5%", "--json"]
    proc = subprocess.Popen(
        [*CLI, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True, env=_env(),
        # as from a terminal: pytest-xdist's workers ignore SIGINT and a child inherits that
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )  # fmt: skip
    parts = Path(str(out) + ".parts")
    deadline = time.monotonic() + 180
    try:
        while time.monotonic() < deadline:
            if parts.exists() and len(list(parts.glob("part-*.parquet"))) >= 2:
                break
            assert proc.poll() is None, "campaign finished before it could be interrupted"
            time.sleep(0.02)
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    assert proc.returncode == 130, err
    kept = {r for p in parts.glob("part-*.parquet") for r in pq.read_table(p)["run"].to_pylist()}
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines == [
        f"interrupted: {len(kept)} of 40 runs finished and kept; rerun with --resume --out {out}"
        " to compute the rest"
    ], err
    assert took < 3.0, took
