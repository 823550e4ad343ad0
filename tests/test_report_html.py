"""HTML run report: written by the CLI from a recorded run, self-contained, every section there."""

from __future__ import annotations

import base64
import json
import math
import os
import re
import subprocess
import sys
import time
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.config import load_config
from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Result, StepSample, Trace
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.report.channels import nominal, status_channels
from packpilot.report.charts import FULL_RES_MAX, pack, sample_indices
from packpilot.report.html import (
    SECTION_IDS,
    RunInfo,
    build_html,
    fmt_num,
    run_info_from_db,
    select_events,
)
from packpilot.sim.runner import Runner
from tests.budget import budget

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# A reference that makes a browser fetch something: src/href/url()/@import to another host.
EXTERNAL = re.compile(
    r"""(?:\b(?:src|href|action|poster)\s*=\s*["']?\s*(?:https?:)?//)|(?:url\(\s*["']?\s*(?:https?:)?//)|@import""",
    re.IGNORECASE,
)
DATA_JSON = re.compile(r'<script type="application/json" id="pp-data">(.*?)</script>', re.S)
BANNER = "/*! https://github.com/leeoniya/uPlot (v1.6.32) */"
"""uPlot's own licence banner: a comment, never fetched (the browser test counts requests)."""

RICH_PROTECTION = """
[protection]
parameters = [
  { name = "P1", cutoff_v = 4.0, t_max_s = 4.0 },
  { name = "P2", cutoff_v = 3.9, t_max_s = 6.0 },
  { name = "P3", cutoff_v = 3.8, t_max_s = 8.0 },
]
"""


def rich_toml(tmp: Path) -> Path:
    """The sequencing example with discharge protection added, tuned to trip within 30 s."""
    text = (EXAMPLES / "sequencing_dual_hover.toml").read_text(encoding="utf-8")
    text = text.replace('controller = ["sequencing"]', 'controller = ["protection", "sequencing"]')
    assert 'controller = ["protection", "sequencing"]' in text
    path = tmp / "rich.toml"
    path.write_text(text + RICH_PROTECTION, encoding="utf-8")
    return path


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true", "MPLBACKEND": "Agg"}
    return subprocess.run(
        [sys.executable, "-m", "packpilot.cli", *args],
        capture_output=True,
        text=True,
        timeout=180,
        env=env,
        cwd=ROOT,
    )


def section(page: str, sid: str) -> str:
    m = re.search(rf'<section id="{sid}">(.*?)</section>', page, re.DOTALL)
    assert m, f"section {sid} missing"
    return m.group(1)


def page_data(page: str) -> dict[str, Any]:
    m = DATA_JSON.search(page)
    assert m, "no chart data"
    data: dict[str, Any] = json.loads(m.group(1))
    return data


def unpack(rec: dict[str, Any]) -> np.ndarray:
    """What report.js does: inflate, cumulative sum, times the quantum, gaps as NaN."""
    d = np.frombuffer(zlib.decompress(base64.b64decode(rec["z"])), dtype="<i4")
    out = np.cumsum(d.astype(np.int64)) * rec["q"]
    for a, b in rec.get("nan", []):
        out[a:b] = np.nan
    return out


def chart_ids(page: str) -> list[str]:
    return re.findall(r'data-chart="([^"]+)"', page)


def no_external(page: str) -> None:
    text = page.replace(BANNER, "")
    assert not EXTERNAL.search(text), EXTERNAL.search(text)
    assert "http://" not in text and "https://" not in text


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Result]:
    """A real 30 s closed-loop run of the UAV dual-parallel example, recorded to SQLite."""
    db = tmp_path_factory.mktemp("run") / "run.sqlite"
    cfg = load_config(EXAMPLES / "uav_dual_parallel.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 30.0, "progress": False})}
    )
    with SQLiteRecorder(db) as rec:
        result = Runner(cfg, recorder=rec, progress=False).run()
    return db, result


def test_report_cli_writes_a_self_contained_page(
    recorded: tuple[Path, Result], tmp_path: Path
) -> None:
    db, result = recorded
    out = tmp_path / "report.html"
    r = cli("report", str(db), "--out", str(out))
    assert r.returncode == 0, r.stderr
    assert "wrote" in r.stdout and str(out) in r.stdout
    page = out.read_text(encoding="utf-8")
    for sid in SECTION_IDS:
        assert f'<section id="{sid}">' in page
    no_external(page)
    assert 20_000 < out.stat().st_size < 3_000_000
    ids = chart_ids(page)  # batteries and switches (this run has no events or controllers)
    assert {"voltage", "current", "soc", "cells", "temp", "switches"} <= set(ids)
    assert set(ids) == set(page_data(page)["charts"])
    # Facts of this run, in readable form.
    summary = section(page, "summary")
    assert "uav_dual_parallel" in summary
    assert ">ok<" in summary  # run status
    assert "energy_out_wh" in summary and fmt_num(result.metrics["energy_out_wh"]) in summary
    assert "<th>A</th>" in summary and "<th>B</th>" in summary
    soc_end = [fmt_num(100 * float(x)) for x in result.trace.channel("soc")[-1]]
    assert all(s in summary for s in soc_end)
    assert '<section id="protection">' not in page  # no method enabled, no method section
    assert "No events" in section(page, "events")
    assert "data-chart" in section(page, "batteries") and "data-chart" in section(page, "switches")


@pytest.mark.long(cpu_s=44)
def test_simulate_report_in_one_go(tmp_path: Path) -> None:
    """simulate --report from the in-memory Result: protection, events and controllers shown."""
    out = tmp_path / "sim.html"
    r = cli(
        "simulate",
        str(rich_toml(tmp_path)),
        "--duration",
        "30",
        "--report",
        str(out),
        "--no-progress",
        "--json",
    )
    assert r.returncode == 0, r.stderr
    assert '"energy_out_wh"' in r.stdout
    page = out.read_text(encoding="utf-8")
    no_external(page)
    events = section(page, "events")
    assert "ProtectionTripped" in events and "StateChanged" in events
    prot = section(page, "protection")
    assert "not recorded" not in prot and "data-chart" in prot
    assert re.search(r"P\d: [\d.]+ s", prot)  # time per parameter
    assert re.search(r"<td>at [\d.]+ s \(P\d\)</td>", prot)  # the trip, with its parameter
    seq = section(page, "sequencing")
    assert "co-discharge share" in seq and "switch changes" in seq and "cross-charge" in seq
    data = page_data(page)
    assert data["charts"]["st-seq_state"]["categories"][:1] and "STANDBY" in str(data["charts"])
    assert '<section id="charging">' not in page and '<section id="equalization">' not in page


def test_report_from_database_equals_report_from_memory(tmp_path: Path) -> None:
    """``report`` (load_run) and ``simulate --report`` (Result) describe a run identically."""
    cfg = load_config(rich_toml(tmp_path))
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 30.0, "progress": False})}
    )
    db = tmp_path / "rich.sqlite"
    with SQLiteRecorder(db) as rec:
        mem = Runner(cfg, recorder=rec, progress=False).run()
    info = run_info_from_db(db, mem.run_id)
    assert info.status == "ok" and info.config_name == "sequencing_dual_hover"
    a = build_html(mem, info)
    b = build_html(load_run(db, mem.run_id), info)
    for sid in (*SECTION_IDS, "sequencing", "protection"):
        assert section(a, sid) == section(b, sid), sid
    assert page_data(a) == page_data(b)
    assert len(chart_ids(a)) >= 8


def synthetic(
    n: int, events: list[Event] | None = None, **status: list[tuple[object, ...]]
) -> Result:
    samples = []
    col = {c: i for i, c in enumerate(BATTERY_CHANNELS)}
    for k in range(n):
        bat = np.zeros((2, len(BATTERY_CHANNELS)))
        bat[:, col["voltage_v"]] = (24.0 - 0.001 * k, 23.0 - 0.001 * k)
        bat[:, col["current_a"]] = (10.0, 5.0)
        bat[:, col["soc"]] = 0.8
        bat[:, col["dsg_on"]] = 1.0
        st_k = {name: seqs[k] for name, seqs in status.items()}
        samples.append(
            StepSample(k, float(k), 23.5, 15.0, 15.0, 0.0, 0.0, bat, np.full((2, 1), 3.9), st_k)
        )
    return Result(["left", "right"], Trace.from_samples(samples), events or [], {}, run_id=None)


def test_untrusted_text_is_escaped() -> None:
    """Battery names, messages and event data land in the page as text, never as markup."""
    ev = Event(1.0, "Fault", 0, "<script>alert(1)</script>", {"x": "<img src=x onerror=1>"})
    page = build_html(synthetic(20, [ev]), RunInfo(config_name="<b>pack</b>", status="ok"))
    assert "<script>alert(1)</script>" not in page
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in page
    assert "<img src=x" not in page and "&lt;b&gt;pack&lt;/b&gt;" in page
    assert page.count("<script") == 3  # uPlot, the chart data, the chart script
    data = DATA_JSON.search(page)
    assert data and "<" not in data.group(1)  # a name cannot close the data block


def test_status_channels_are_classified_and_aligned() -> None:
    n = 30
    res = synthetic(
        n,
        mode=[("discharge", "discharge")] * 10 + [("charge", "charge")] * 20,
        seq_state=[("ON", "OFF")] * 15 + [("ON", "ON")] * 15,
        eq_ah_g0=[(0.1 * (k // 10), None) for k in range(n)],
        flag=[(k >= 5, False) for k in range(n)],
    )
    # A channel that starts late (telemetry keeps channels from their first step on).
    res.trace.status["late_v"] = [(1.0, 2.0)] * 12
    ch = status_channels(res)
    assert ch["mode"].kind == "label" and ch["mode"].pack_level
    assert ch["seq_state"].kind == "label" and not ch["seq_state"].pack_level
    assert list(ch["mode"].rows) == [0, 10]  # compressed to its changes
    assert ch["eq_ah_g0"].columns == (0,) and ch["eq_ah_g0"].kind == "numeric"
    assert ch["flag"].kind == "bool"
    late = ch["late_v"]
    assert list(late.rows) == [0, n - 12] and late.values[0, 0] is None
    assert nominal(ch["mode"]) is None and nominal(ch["flag"]) is None
    page = build_html(res)
    ctrl = section(page, "controllers")
    for family in ("Supervisor", "Parallel discharge sequencing", "Equalization", "Other"):
        assert family in ctrl, family
    assert '<section id="protection">' not in page


def test_nominal_channels_are_one_line_and_busy_ones_charts() -> None:
    """A limit that stayed ok and a flat setting say so in a line; a limit that warned and a
    moving value get charts (folded) — the rule is the value set, not the channel name."""
    n = 40
    res = synthetic(
        n,
        lim_over_voltage=[("ok", "ok")] * n,
        lim_over_temp=[("ok", "ok")] * 30 + [("warn", "ok")] * 10,
        limit_dsg_a=[(20.0, 20.0)] * n,
        soc_est=[(0.8 - 0.001 * k, 0.7) for k in range(n)],
        eq_fault=[(False, False)] * n,
        plaus_faults=[("", "")] * 20 + [("stale", "")] * 20,
    )
    ch = status_channels(res)
    assert nominal(ch["lim_over_voltage"]) == "ok throughout"
    assert nominal(ch["limit_dsg_a"]) == "constant 20 A"
    assert nominal(ch["eq_fault"]) == "no fault throughout"
    for busy in ("lim_over_temp", "soc_est", "plaus_faults"):
        assert nominal(ch[busy]) is None, busy
    page = build_html(res)
    ctrl = section(page, "controllers")
    assert "<code>lim_over_voltage</code>: nominal (ok throughout)" in ctrl
    assert "<code>limit_dsg_a</code>: nominal (constant 20 A)" in ctrl
    ids = set(chart_ids(page))
    assert {"st-lim_over_temp", "st-soc_est", "st-plaus_faults"} <= ids
    assert not {"st-lim_over_voltage", "st-limit_dsg_a", "st-eq_fault"} & ids
    folded = ctrl[ctrl.index("<details>") :]
    assert 'data-chart="st-lim_over_temp"' in folded


@budget(200)
@given(
    y=st.lists(
        st.one_of(st.floats(-1e4, 1e4, allow_nan=False), st.just(math.nan)),
        min_size=1,
        max_size=300,
    )
)
def test_packed_series_unpack_to_the_values(y: list[float]) -> None:
    """What the page carries decodes (as report.js does) to the series within half a quantum,
    with every gap where it was."""
    arr = np.array(y)
    rec = pack(arr)
    got = unpack(rec)
    assert len(got) == len(arr) == rec["n"]
    assert np.array_equal(np.isnan(got), np.isnan(arr))
    ok = ~np.isnan(arr)
    assert np.all(np.abs(got[ok] - arr[ok]) <= rec["q"] / 2 * (1 + 1e-9) + 1e-12 * np.abs(arr[ok]))


def test_large_run_is_downsampled_and_small() -> None:
    """10 h at 0.1 s: thinned to about FULL_RES_MAX samples, a one-sample spike kept, the page
    under 3 MB and built in seconds."""
    n = 360_000
    t = np.arange(n) * 0.1
    bat = np.zeros((n, 2, len(BATTERY_CHANNELS)))
    col = {c: i for i, c in enumerate(BATTERY_CHANNELS)}
    rng = np.random.default_rng(1)
    bat[:, :, col["voltage_v"]] = 24.0 - t[:, None] / 7200.0 + 0.02 * rng.standard_normal((n, 2))
    bat[:, :, col["current_a"]] = 10.0 + rng.standard_normal((n, 2))
    bat[123_457, 1, col["current_a"]] = 95.0  # a single-sample spike
    bat[:, :, col["soc"]] = 0.9 - 0.8 * t[:, None] / t[-1]
    bat[:, :, col["chg_on"]] = (np.sin(t / 600.0)[:, None] > 0).astype(float)
    bat[:, :, col["dsg_on"]] = 1.0
    status = {
        "protection_param": [("P1", "P2")] * (n // 2) + [("P2", "P3")] * (n - n // 2),
        "protection_fraction": [(k / n, k / n / 2) for k in range(n)],
    }
    trace = Trace(
        t_s=t,
        bus_v=bat[:, 0, 0].copy(),
        load_demand_a=np.full(n, 20.0),
        load_a=np.full(n, 20.0),
        charger_v=np.zeros(n),
        charger_a=np.zeros(n),
        battery=bat,
        group_v=np.full((n, 2, 1), 3.9),
        status=status,
    )
    events = [Event(float(k), "StateChanged", k % 2, "x") for k in range(0, 36_000, 3)]
    events.append(Event(5000.0, "ProtectionTripped", 1, "P2 exhausted"))
    res = Result(["A", "B"], trace, events, {"sim_time_s": 36_000.0})
    idx = sample_indices(res)
    assert len(idx) <= 1.2 * FULL_RES_MAX and 123_457 in idx  # thinned, the spike kept
    t0 = time.perf_counter()
    page = build_html(res, RunInfo(config_name="long", status="ok"))
    elapsed = time.perf_counter() - t0
    size = len(page.encode())
    assert size < 3_000_000, size
    assert elapsed < 30.0, elapsed
    ev = section(page, "events")
    assert "ProtectionTripped" in ev and "Listing 1,000 of 12,001 events" in ev
    current_b = unpack(page_data(page)["store"]["current_a/1"])
    assert np.nanmax(current_b) == pytest.approx(95.0, abs=0.01)


@budget(200)
@given(
    counts=st.dictionaries(
        st.sampled_from(["A", "B", "C", "D", "E"]), st.integers(1, 400), min_size=1
    ),
    limit=st.integers(1, 300),
)
def test_event_selection_shares_the_budget(counts: dict[str, int], limit: int) -> None:
    events = [
        Event(float(i), kind, None) for i, (kind, n) in enumerate(counts.items()) for _ in range(n)
    ]
    events.sort(key=lambda e: e.t_s)
    chosen = select_events(events, limit)
    total = sum(counts.values())
    assert len(chosen) == min(total, limit)
    assert chosen == sorted(set(chosen))
    got = {k: sum(1 for i in chosen if events[i].kind == k) for k in counts}
    fair = limit // len(counts)
    for k, n in counts.items():
        assert got[k] >= min(n, fair)  # a rare kind is never crowded out


def test_cli_report_errors_are_one_line(recorded: tuple[Path, Result], tmp_path: Path) -> None:
    db, _ = recorded
    bogus = tmp_path / "notes.sqlite"
    bogus.write_text("not a database", encoding="utf-8")
    cases = [
        (("report", str(db), "--out", str(tmp_path / "no" / "r.html")), "does not exist"),
        (("report", str(db), "--out", str(tmp_path / "r.pdf")), "must end in .html"),
        (("report", str(db), "--run-id", "99", "--out", str(tmp_path / "r.html")), "no run"),
        (("report", str(tmp_path / "missing.sqlite"), "--out", str(tmp_path / "r.html")), "not"),
        (("report", str(bogus), "--out", str(tmp_path / "r.html")), "telemetry database"),
    ]
    for args, msg in cases:
        r = cli(*args)
        assert r.returncode == 2, (args, r.stderr)
        assert msg in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "r.html").exists()


def test_number_formatting() -> None:
    assert fmt_num(0.0) == "0"
    assert fmt_num(3.14159) == "3.142"
    assert fmt_num(147_574.3) == "147,574"
    assert fmt_num(12) == "12"
    assert fmt_num(math.nan) == "nan"
    assert fmt_num(1.5e-5) == "1.500e-05"


def test_unfinished_runs_still_report(tmp_path: Path) -> None:
    """A run whose process died (status 'running', no metrics) gives a report that says so."""
    from packpilot.report.html import report_from_db

    db = tmp_path / "crash.sqlite"
    rec = SQLiteRecorder(db, flush_every=5)
    rec.start({"pack": {"name": "crashy"}}, ["A", "B"])
    rec.close()  # nothing recorded, never finished
    rec = SQLiteRecorder(db, flush_every=5)
    rec.start({"pack": {"name": "crashy"}}, ["A", "B"])
    for k in range(12):
        bat = np.ones((2, len(BATTERY_CHANNELS)))
        status = {"seq_state": ("ON", "OFF") if k < 6 else ("ON", "ON")}
        rec.record(StepSample(k, float(k), 24.0, 1, 1, 0, 0, bat, np.ones((2, 1)), status))
    rec.close()
    for run_id, n_charts in ((1, 0), (2, 7)):  # 5 battery, switches, seq_state
        out = report_from_db(db, tmp_path / f"r{run_id}.html", run_id)
        page = out.read_text(encoding="utf-8")
        assert all(f'<section id="{sid}">' in page for sid in SECTION_IDS)
        assert "status <strong>running</strong>" in page and "No metrics recorded" in page
        assert len(chart_ids(page)) == n_charts
    assert "No samples were recorded" in (tmp_path / "r1.html").read_text(encoding="utf-8")


def test_run_info_reads_roles_switches_and_event_numbering() -> None:
    """Events number traction batteries only; an aux battery listed first shifts the names."""
    cfg = {
        "pack": {
            "name": "mixed",
            "switch": {"kind": "relay"},
            "batteries": [
                {"name": "AUX", "role": "aux", "switch": None},
                {"name": "T1", "role": "traction", "switch": {"kind": "mosfet_pair"}},
                {"name": "T2"},
            ],
        },
        "controller": ["charging"],
        "limits": {},
    }
    info = RunInfo.from_config(cfg, status="ok")
    names = ["AUX", "T1", "T2"]
    assert info.config_name == "mixed"
    assert info.roles(names) == ["aux", "traction", "traction"]
    assert info.switch_kinds(names) == ["relay", "mosfet_pair", "relay"]
    assert info.event_names(names) == ["T1", "T2"] and info.event_batteries(names) == [1, 2]
    assert info.controllers() == ["charging", "limits"]
    assert RunInfo().event_names(["a", "b"]) == ["a", "b"]
