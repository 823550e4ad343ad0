"""Issue #17 §1 and §4 at the command line, as a user meets them (a real subprocess): the verdict
and --fail-on, Ctrl-C, option checks, help text, --version, named examples, report defaults,
campaign output checks, progress on stderr, and the Makefile's split of demo and test installs.
"""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import EXAMPLES, ROOT

CLI = [sys.executable, "-m", "packpilot.cli"]
ENV = {**os.environ, "COLUMNS": "80", "PYTHONPATH": os.pathsep.join(sys.path)}


def cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*CLI, *args], capture_output=True, text=True, timeout=600, cwd=cwd, env=ENV
    )


def one_error_line(proc: subprocess.CompletedProcess[str]) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    return lines[0]


# --------------------------------------------------------------------------- verdict, --fail-on


def test_summary_starts_with_the_verdict_and_the_alarms() -> None:
    proc = cli("simulate", str(EXAMPLES / "uav_dual_parallel.toml"), "--duration", "5")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.lstrip().startswith("verdict: ALARM")
    assert out.index("alarms") < out.index("run summary")
    assert "CrossCharge" in out and "charge limit" in out
    assert "{" not in out  # the event counts are text, not a Python dict


def test_fail_on_exits_3_only_for_the_listed_categories() -> None:
    path = str(EXAMPLES / "uav_dual_parallel.toml")
    hit = cli("simulate", path, "--duration", "5", "--json", "--fail-on", "trip,crosscharge")
    assert hit.returncode == 3, hit.stderr
    assert "fail-on: crosscharge" in hit.stderr
    data = json.loads(hit.stdout)
    assert data["verdict"]["verdict"] == "ALARM" and data["sim_time_s"] == 5.0
    assert any(a["category"] == "crosscharge" for a in data["verdict"]["alarms"])
    miss = cli("simulate", path, "--duration", "5", "--json", "--fail-on", "trip,fault")
    assert miss.returncode == 0, miss.stderr
    bad = one_error_line(cli("simulate", path, "--fail-on", "trips"))
    assert "unknown category trips" in bad and "overdischarge" in bad


def test_fail_on_overdischarge_on_smart_battery() -> None:
    proc = cli("simulate", "smart_battery", "--fail-on", "overdischarge", "--json", cwd=ROOT)
    assert proc.returncode == 3, proc.stderr
    assert json.loads(proc.stdout)["verdict"]["verdict"] == "WARNING"


# --------------------------------------------------------------------------- Ctrl-C


def samples_in(db: Path) -> int:
    try:
        with sqlite3.connect(db) as conn:
            return int(conn.execute("SELECT COUNT(*) FROM pack_samples").fetchone()[0])
    except sqlite3.Error:
        return 0


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_exits_130_and_marks_the_run_interrupted(tmp_path: Path) -> None:
    db = tmp_path / "run.sqlite"
    report, plot = tmp_path / "r.html", tmp_path / "r.png"
    proc = subprocess.Popen(
        # ten missions long: the whole 5,400 s mission runs in ~8 s, short enough that the
        # signal could arrive after the loop on a loaded machine (it did)
        [*CLI, "simulate", str(EXAMPLES / "uav_mission.toml"), "--db", str(db), "--no-progress",
         "--duration", "54000", "--report", str(report), "--plot", str(plot)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
        # as from a terminal: pytest-xdist's workers ignore SIGINT and a child inherits that
        # (Python then installs no KeyboardInterrupt handler): in CI every Ctrl-C was ignored
        # and the run finished with exit 0
        preexec_fn=_default_sigint,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 540.0  # a cold kernel cache compiles first
        while samples_in(db) < 500 and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGINT)
        # generous: with a cold kernel cache (CI) the end-of-run path compiles on first use
        out, err = proc.communicate(timeout=540)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, (out, err)
    assert "Traceback" not in err
    assert re.search(r"interrupted at t = [\d.]+ s", err), err
    # the outputs asked for are named as not written (#29: the report's absence went unsaid)
    assert f"not written: {report}, {plot} (the run did not finish)" in err, err
    assert not report.exists() and not plot.exists()
    with sqlite3.connect(db) as conn:
        (status,) = conn.execute("SELECT status FROM runs").fetchone()
    assert status == "interrupted"


# --------------------------------------------------------------------------- option checks


def test_can_options_need_a_charger_and_a_known_interface() -> None:
    no_charger = one_error_line(
        cli("simulate", str(EXAMPLES / "smart_battery.toml"), "--can-interface", "bogus")
    )
    assert "no charger" in no_charger
    bogus = one_error_line(
        cli("simulate", str(EXAMPLES / "uav_mission.toml"), "--can-interface", "bogus")
    )
    assert "'bogus': not a python-can interface" in bogus and "socketcan" in bogus


def test_campaign_refuses_a_csv_out_before_any_run(tmp_path: Path) -> None:
    out = tmp_path / "c.csv"
    line = one_error_line(cli("campaign", "smart_battery", "--runs", "2", "--out", str(out)))
    assert "Parquet" in line and ".parquet" in line
    assert not out.exists()


def test_campaign_without_spread_warns(tmp_path: Path) -> None:
    out = tmp_path / "c.parquet"
    proc = cli(
        "campaign", str(EXAMPLES / "smart_battery.toml"), "--runs", "2", "--duration", "2",
        "--scheduler", "sync", "--out", str(out), "--json",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "warning: no --spread: the 2 runs share every parameter" in proc.stderr
    assert out.exists()


def test_unknown_config_key_suggests_the_right_one(tmp_path: Path) -> None:
    p = tmp_path / "typo.toml"
    p.write_text('[pack]\ncell = "uav_5ah"\n[[pack.batteries]]\nname = "A"\nserie_groups = 6\n')
    line = one_error_line(cli("simulate", str(p)))
    assert "pack.batteries.0.serie_groups: unknown key (did you mean 'series_groups'?)" in line


# --------------------------------------------------------------------------- help, version


def test_help_text_is_whole() -> None:
    camp = cli("campaign", "--help")
    assert camp.returncode == 0
    text = " ".join(camp.stdout.split())
    assert "run i draws from [seed, i]" in text
    assert "capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35" in text
    sim = cli("simulate", "--help")
    assert "--fail-on" in sim.stdout and "130 interrupted" in " ".join(sim.stdout.split())
    for proc in (camp, sim):
        assert "<bool>" not in proc.stdout and "…" not in proc.stdout


def test_version() -> None:
    proc = cli("--version")
    assert proc.returncode == 0
    assert re.fullmatch(r"packpilot \S+\n", proc.stdout)


# --------------------------------------------------------------------------- names, defaults


def test_examples_can_be_named_from_anywhere(tmp_path: Path) -> None:
    proc = cli("simulate", "smart_battery", "--duration", "1", "--json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["sim_time_s"] == 1.0
    line = one_error_line(cli("simulate", "uav_misson", cwd=tmp_path))
    assert "no example of that name (did you mean 'uav_mission'?)" in line


def test_report_without_out_writes_next_to_the_database(tmp_path: Path) -> None:
    db = tmp_path / "run.sqlite"
    sim = cli("simulate", str(EXAMPLES / "smart_battery.toml"), "--duration", "2", "--db", str(db))
    assert sim.returncode == 0, sim.stderr
    rep = cli("report", str(db))
    assert rep.returncode == 0, rep.stderr
    assert (tmp_path / "run.html").stat().st_size > 10_000
    rep1 = cli("report", str(db), "--run-id", "1")
    assert rep1.returncode == 0 and (tmp_path / "run_1.html").exists()


# --------------------------------------------------------------------------- make demo


def test_progress_goes_to_stderr_and_json_stays_clean() -> None:
    proc = cli(
        "simulate", str(EXAMPLES / "smart_battery.toml"), "--duration", "60", "--progress",
        "--json",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    json.loads(proc.stdout)
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("simulating:")]
    assert len(lines) >= 5 and "100 %" in lines[-1], proc.stderr


def test_make_demo_installs_only_the_package_and_test_adds_the_extras() -> None:
    make = (ROOT / "Makefile").read_text()
    blocks = {m[0]: (m[1], m[2]) for m in re.findall(r"^(\S+):(.*)\n((?:\t.*\n)*)", make, re.M)}
    stamp_recipe = blocks["$(STAMP)"][1]
    assert "install --progress-bar off -e .\n" in stamp_recipe and "[test]" not in stamp_recipe
    assert "--quiet" not in stamp_recipe  # pip names what it installs: no minutes of silence
    assert blocks["demo"][0].split() == ["$(STAMP)"]
    assert "$(TEST_STAMP)" in blocks["test"][0] and "$(TEST_STAMP)" in blocks["lint"][0]
    assert '-e ".[test]"' in blocks["$(TEST_STAMP)"][1]
    demo = blocks["demo"][1]
    assert "--progress" in demo and ">&2" in demo  # progress and what is going on, on stderr
    # a second `make demo` starts a fresh database: its report is "run 1" again, not "run 2"
    fresh = demo.index("rm -f $(OUT)/demo.sqlite $(OUT)/demo.sqlite-wal $(OUT)/demo.sqlite-shm")
    assert fresh < demo.index("--db $(OUT)/demo.sqlite")


def test_installed_examples_are_found_by_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A wheel installs the examples under <prefix>/share/packpilot/examples (pyproject's
    data-files); a name resolves there when neither ./examples nor a checkout has it."""
    from packpilot.cli import scenario_path

    shared = tmp_path / "share" / "packpilot" / "examples"
    shared.mkdir(parents=True)
    (shared / "only_installed.toml").write_text("")
    monkeypatch.setattr(sys, "prefix", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert scenario_path(Path("only_installed")) == shared / "only_installed.toml"
    assert 'data-files]\n' in (ROOT / "pyproject.toml").read_text()


def test_the_cross_charge_figure_is_the_same_in_the_docs_and_the_run() -> None:
    """README and docs/replay.md quote uav_dual_parallel's cross-charge: the figure the run
    prints (#29: they said 50 A and 40 A, the run 39.5 A)."""
    proc = cli("simulate", str(EXAMPLES / "uav_dual_parallel.toml"), "--json", "--no-progress")
    assert proc.returncode == 0, proc.stderr
    peak = json.loads(proc.stdout)["peak_cross_current_a"]
    figure = f"{peak:.1f} A cross-charge"
    for doc in (ROOT / "README.md", ROOT / "docs" / "replay.md"):
        text = doc.read_text(encoding="utf-8")
        found = set(re.findall(r"(\d+(?:\.\d)?) A cross-charge", text))
        assert found == {f"{peak:.1f}"}, (doc.name, found, figure)


def test_the_tours_commands_name_files_a_step_creates() -> None:
    """Every file the README's tour reads (a --can-log or a report's database) is written by
    an earlier step of the tour or by `make demo` (#29: `--can-log run.blf` named a file no
    step creates)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    tour = text[text.index("## A short tour") : text.index("## On a real pack")]
    made = {"out/demo.sqlite", "out/demo_can.blf", "out/report.html"}  # make demo
    for line in tour.splitlines():
        cmd = line.split("#", 1)[0]  # a hint in a comment counts too: it is read as advice
        for read in re.findall(r"--can-log (\S+)", line) + re.findall(r"report (\S+\.sqlite)", cmd):
            assert read in made, (read, line)
        made.update(re.findall(r"--(?:db|out|plot|report) (\S+)", cmd))
