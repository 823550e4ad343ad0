"""Reading a long recorded run back streams (issue #26 §3): the report's figures are folded
block by block and the charts keep a min/max-decimated trace, so what the reader holds does
not grow with the run; the dashboard reads a recording block by block and its scrubber reads
back the one block it needs. Real SQLite files written by the real telemetry writer."""

from __future__ import annotations

import itertools
import math
import re
import tracemalloc
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, StepSample
from packpilot.io.telemetry import SQLiteRecorder, load_run
from packpilot.report.digest import RunDigest
from packpilot.report.html import build_html, run_info_from_db
from packpilot.report.stream import read_run
from packpilot.web.recorded import SCRUB_BLOCK, Recording

COL = {c: i for i, c in enumerate(BATTERY_CHANNELS)}
DT_S = 0.1


def write_run(path: Path, n: int, seed: int = 0, chatter: bool = False) -> None:
    """``n`` samples of two batteries with what a report must not lose: a one-sample current
    spike and a one-sample cell-voltage dip deep inside the run, NaN gaps, switches that toggle
    (one battery's CHG apart from its DSG), a body diode conducting for a moment, status
    channels (one starting half-way), and events (a trip among routine state changes).
    ``chatter``: one more status channel that changes at every sample."""
    rng = np.random.default_rng(seed)
    spike, dip, diode_at = (n * 3) // 7, (n * 5) // 9, (n * 2) // 3
    with SQLiteRecorder(path, flush_every=2000) as rec:
        rec.start({"pack": {"name": "stream_test"}, "sim": {"dt_s": DT_S}}, ["A", "B"])
        for k in range(n):
            t = k * DT_S
            bat = np.zeros((2, len(BATTERY_CHANNELS)))
            bat[:, COL["voltage_v"]] = 24.0 - 2e-5 * k + rng.normal(0, 0.01, 2)
            bat[:, COL["current_a"]] = (10.0 + math.sin(t), 5.0 - math.cos(t / 7))
            bat[:, COL["soc"]] = 0.9 - 0.5 * k / n
            bat[:, COL["min_cell_v"]] = 3.7 - 1e-6 * k
            bat[:, COL["max_cell_v"]] = 3.8 - 1e-6 * k
            bat[:, COL["temp_c"]] = 25.0 + 5 * math.sin(t / 300)
            on = 0.0 if (k // 997) % 5 == 4 else 1.0
            bat[:, COL["dsg_on"]] = on
            bat[:, COL["chg_on"]] = (on, 1.0)
            if k == spike:
                bat[0, COL["current_a"]] = 180.0
            if k == dip:
                bat[1, COL["min_cell_v"]] = 2.1
            if k == diode_at:
                bat[1, COL["dsg_diode_a"]] = 3.0
            if k % 1500 == 700:
                bat[0, COL["voltage_v"]] = math.nan
            state = ("DISCHARGE", "STANDBY")[k // 2500 % 2]
            status: dict[str, list[Any]] = {"seq_state": [state, state]}
            if k >= n // 2:
                status["eq_active"] = [k % 4000 < 50, False]
            if chatter:
                status["lim_margin"] = [float(k % 7), float(k % 5)]
            rec.record(StepSample(k, t, 23.9, 15.0, 15.0, 0.0, 0.0, bat, np.full((2, 3), 3.75),
                                  status))  # fmt: skip
            if k % 500 == 0:
                rec.record_events([Event(t, "StateChanged", k % 2, "state", {"k": k})])
            if k == spike:
                rec.record_events([Event(t, "ProtectionTripped", 0, "over-current", {"i": 180})])
        rec.finish({"energy_out_wh": 1.0})


def tables(page: str) -> dict[str, str]:
    """The parts of a report that count every sample (the charts may be decimated)."""
    out = {}
    for sid in ("verdict", "events"):
        m = re.search(rf'<section id="{sid}">(.*?)</section>', page, re.DOTALL)
        assert m, sid
        out[sid] = m.group(1)
    for cls in ("kpis", "battery", "counts", "metrics", "kv"):
        found = re.findall(rf'<(?:table|div) class="{cls}".*?</(?:table|div)>', page, re.DOTALL)
        assert found, cls
        out[cls] = "".join(found)
    return out


@pytest.fixture(scope="module")
def long_db(tmp_path_factory: pytest.TempPathFactory) -> Path:
    db = tmp_path_factory.mktemp("stream") / "long.sqlite"
    write_run(db, 12_000)
    return db


def test_streamed_report_counts_every_sample_like_the_whole_run(long_db: Path) -> None:
    """A run read in blocks (decimated charts) reports the very figures of the run read
    whole: verdict, KPIs, per-battery table, switch counts, metrics, events."""
    info = run_info_from_db(long_db)
    whole = load_run(long_db)
    streamed, digest = read_run(long_db, full_res_max=1000, block_rows=700)
    assert digest.decimated > 1 and len(streamed.trace.t_s) < len(whole.trace.t_s) // 2
    a, b = build_html(whole, info), build_html(streamed, info, digest)
    ta, tb = tables(a), tables(b)
    assert tb.pop("kv").replace(ta["kv"], "") == ""  # the run table: the same rows
    ta.pop("kv")
    for key in ta:
        assert ta[key] == tb[key], key
    assert "180" in ta["battery"] and "2.1" in ta["battery"]  # the spike and the dip
    assert "ProtectionTripped" in ta["verdict"]
    assert f"decimated: {digest.decimated:,} points per bucket, min/max kept" in b.replace(
        "Charts decimated", "decimated"
    )
    assert "decimated" not in a.split("<script")[0]


def test_decimated_trace_keeps_peaks_gaps_and_every_change(long_db: Path) -> None:
    """The kept samples hold each bucket's extremes (the one-sample spike and dip), a NaN
    of each gap, every switch and diode change and every status change."""
    whole = load_run(long_db).trace
    kept = read_run(long_db, full_res_max=1000, block_rows=700)[0].trace
    cur, cmin = kept.channel("current_a"), kept.channel("min_cell_v")
    assert float(np.nanmax(cur[:, 0])) == 180.0 and float(np.nanmin(cmin[:, 1])) == 2.1
    assert np.isnan(kept.channel("voltage_v")[:, 0]).sum() == np.isnan(
        whole.channel("voltage_v")[:, 0]
    ).sum()  # each gap is one sample here, so each is kept
    for key in ("chg_on", "dsg_on"):
        for b in range(2):
            full, thin = whole.channel(key)[:, b], kept.channel(key)[:, b]
            assert np.count_nonzero(np.diff(full)) == np.count_nonzero(np.diff(thin))
    assert (kept.channel("dsg_diode_a")[:, 1] > 0).sum() == 1
    for name, seqs in whole.status.items():
        assert n_changes(seqs) == n_changes(kept.status[name]) > 0, name
    assert kept.t_s[0] == whole.t_s[0] and kept.t_s[-1] == whole.t_s[-1]


def n_changes(seqs: Sequence[Sequence[object]]) -> int:
    return sum(1 for x, y in itertools.pairwise(seqs) if tuple(x) != tuple(y))


def peak_traced(fn: Callable[[], Any]) -> int:
    """Peak bytes Python and numpy allocated while ``fn`` ran (tracemalloc: deterministic,
    not the process's RSS)."""
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_report_reader_memory_does_not_grow_with_the_run(tmp_path: Path) -> None:
    """Four times the samples: the streamed reader's peak allocation and its kept samples
    stay put, while reading the whole run grows with it (so this test can fail). A status
    channel changes at every sample: its change points are thinned to the bucket's share."""
    short, long = tmp_path / "short.sqlite", tmp_path / "long.sqlite"
    write_run(short, 8_000, seed=1, chatter=True)
    write_run(long, 32_000, seed=1, chatter=True)
    kept: dict[Path, int] = {}

    def stream(db: Path) -> None:
        kept[db] = len(read_run(db, full_res_max=240, block_rows=1000)[0].trace.t_s)

    streamed = {db: peak_traced(lambda db=db: stream(db)) for db in (short, long)}
    whole = {db: peak_traced(lambda db=db: load_run(db)) for db in (short, long)}
    assert whole[long] > 1.8 * whole[short], whole  # the unbounded reader, for contrast
    assert streamed[long] < 1.3 * streamed[short], streamed
    assert kept[long] < 1.3 * kept[short], kept
    # at most 2 extremes of 14 series, a NaN and 16 changes per bucket, 100 buckets
    assert kept[long] <= 100 * (2 * 14 + 1 + 16), kept


def test_digest_of_a_run_in_memory_matches_numpy_on_the_whole_trace(long_db: Path) -> None:
    """The folded figures equal the same numpy expressions over the whole trace, whatever
    the blocks (one block, or ragged ones)."""
    whole = load_run(long_db)
    tr = whole.trace
    one = RunDigest.of_result(whole, None)
    _, blocks = read_run(long_db, full_res_max=1000, block_rows=333)
    for d in (one, blocks):
        assert d.n == len(tr.t_s)
        assert d.dt_median() == float(np.median(np.diff(tr.t_s)))
        cur, cmin = tr.channel("current_a"), tr.channel("min_cell_v")
        assert d.extreme("i_max") == [float(np.nanmax(cur[:, b])) for b in (0, 1)]
        assert d.extreme("cmin") == [float(np.nanmin(cmin[:, b])) for b in (0, 1)]
        assert d.changes("dsg") == [int(np.count_nonzero(np.diff(tr.channel("dsg_on")[:, b])))
                                    for b in (0, 1)]  # fmt: skip
        t = tr.t_s
        dt = np.diff(t, append=t[-1] + (t[-1] - t[-2]))
        out_ah = [float(np.nansum(np.clip(tr.channel("current_a")[:, b], 0, None) * dt)) / 3600
                  for b in (0, 1)]  # fmt: skip
        assert d.charge_ah()[0] == pytest.approx(out_ah, rel=1e-12)
        assert d.same_paths(0) and not d.same_paths(1)
        assert d.diode_conducted("dsg", 1) and not d.diode_conducted("dsg", 0)


def test_dashboard_reads_a_recording_in_blocks_and_scrubs_from_the_file(long_db: Path) -> None:
    """The dashboard's recording holds no trace; the scrubber's sample at any time equals
    the run's full-rate sample there, across block edges."""
    rec = Recording(long_db)
    whole = load_run(long_db).trace
    assert rec.n_samples == len(whole.t_s) and len(rec._blocks) == -(-len(whole.t_s) // SCRUB_BLOCK)
    assert not hasattr(rec, "_traces")
    for k in (0, 1, SCRUB_BLOCK - 1, SCRUB_BLOCK, SCRUB_BLOCK + 1, 7777, len(whole.t_s) - 1):
        got = rec.at(float(whole.t_s[k]))
        assert got["index"] == k and got["t_s"] == float(whole.t_s[k])
        s = rec.sample(k)
        assert np.array_equal(s.battery, whole.battery[k], equal_nan=True)
        assert {c: tuple(v) for c, v in s.status.items()} == {
            c: tuple(seq[k - len(whole.t_s) + len(seq)])
            for c, seq in whole.status.items()
            if k >= len(whole.t_s) - len(seq)
        }
    assert rec.at(-5.0)["index"] == 0 and rec.at(1e9)["index"] == len(whole.t_s) - 1
    assert rec.live.state == "finished" and rec.live.kind == "recorded"


def test_dashboard_recording_memory_does_not_grow_with_the_run(tmp_path: Path) -> None:
    """Four times the samples, about the same peak allocation opening the recording."""
    short, long = tmp_path / "short.sqlite", tmp_path / "long.sqlite"
    write_run(short, 5_000, seed=2)
    write_run(long, 20_000, seed=2)
    peak = {db: peak_traced(lambda db=db: Recording(db, max_points=500)) for db in (short, long)}
    assert peak[long] < 1.5 * peak[short], peak
