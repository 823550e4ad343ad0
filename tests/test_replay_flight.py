"""`packpilot replay flight` (#17 §5): what PackPilot would have done on the shipped flights,
through protection and (two batteries) sequencing, as a summary and a self-contained HTML
report checked in headless Chromium; the column vocabulary across methods; option errors."""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.control.protection import ProtectionConfig
from packpilot.control.sequencing import SequencingConfig
from packpilot.replay.common import LogOptions
from packpilot.replay.equalization import replay as eq_replay
from packpilot.replay.flight import replay_flight
from packpilot.replay.flight_report import flight_html
from packpilot.replay.sequencing import replay as seq_replay
from tests.cdp import CHROMIUM, chromium, open_page
from tests.conftest import EXAMPLES

LOGS = EXAMPLES / "logs"
RUNNER = CliRunner()


def _flight(*args: str) -> dict[str, object]:
    res = RUNNER.invoke(app, ["replay", "flight", *args, "--json"])
    assert res.exit_code == 0, res.output
    out: dict[str, object] = json.loads(res.stdout)
    return out


def test_one_battery_flight_would_have_tripped() -> None:
    s = _flight(str(LOGS / "px4_one_battery.ulg"))
    prot = s["protection"]["A"]  # type: ignore[index]
    assert prot["tripped"] is True and prot["param_at_trip"] == "P1"
    # The flight without protection: the closed loop with it tripped at 525 s; 1 Hz samples.
    assert 524.0 <= prot["trip_time_s"] <= 528.0
    assert s["headlines"][0].startswith("A: the protection would have opened")  # type: ignore[index]
    assert s["log_facts"]["A"]["lowest_min_cell_v"] < 2.5  # type: ignore[index]
    assert s["sequencing"] is None and s["assumed"] == []


def test_the_same_flight_from_ardupilot_needs_a_stated_temperature() -> None:
    log = str(LOGS / "ardupilot_one_battery.bin")
    s = _flight(log)
    assert s["protection"] == {} and "--assume-temp-c" in s["not_replayed"]["A"]  # type: ignore[index]
    s = _flight(log, "--assume-temp-c", "-10")
    assert s["protection"]["A"]["tripped"] is True  # type: ignore[index]
    assert any("-10 degC" in a for a in s["assumed"])  # type: ignore[attr-defined]


def test_two_batteries_sequencing_would_have_blocked_the_cross_charge() -> None:
    s = _flight(str(LOGS / "px4_two_batteries.ulg"), "--assume-temp-c", "25", "--parallel", "A,B")
    heads = s["headlines"]
    assert isinstance(heads, list)
    line = next(
        h for h in heads if h.startswith("B: sequencing would have kept its charge FET off")
    )
    assert "from 0.0 s" in line and "39.5 A flowing into B" in line
    assert not any(h.startswith("A: sequencing") for h in heads)
    seq = s["sequencing"]
    assert isinstance(seq, dict) and seq["batteries"] == ["A", "B"]
    assert s["log_facts"]["B"]["peak_charge_a"] == pytest.approx(39.5, abs=0.1)  # type: ignore[index]
    assert {p["tripped"] for p in s["protection"].values()} == {False}  # type: ignore[attr-defined]


def test_ardupilot_two_batteries_text_and_binary_give_one_answer() -> None:
    opts = ("--cells", "6", "--assume-temp-c", "25", "--parallel", "A,B")
    a = _flight(str(LOGS / "ardupilot_two_batteries.bin"), *opts)
    b = _flight(str(LOGS / "ardupilot_two_batteries.log"), *opts)
    assert a["headlines"] == b["headlines"]
    assert any("--cells" in n for n in a["assumed"])  # type: ignore[attr-defined]


def test_batteries_are_independent_unless_said_parallel() -> None:
    """A real PX4 log with a 6S and a 12S battery (23 V and 50 V): no sequencing and no
    cross-current unless --parallel, and --parallel on that pair is refused with the reason."""
    log = str(LOGS / "real" / "px4_sample_log_small.ulg")
    s = _flight(log, "--assume-temp-c", "25")
    assert s["sequencing"] is None
    assert not any("cross-current" in h for h in s["headlines"])  # type: ignore[attr-defined]
    assert any("independent" in h for h in s["headlines"])  # type: ignore[attr-defined]
    res = RUNNER.invoke(app, ["replay", "flight", log, "--assume-temp-c", "25",
                              "--parallel", "A,B"])  # fmt: skip
    assert res.exit_code == 2
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "23.37 V" in err[0] and "49.74 V" in err[0], err
    res = RUNNER.invoke(app, ["replay", "flight", log, "--parallel", "A,C"])
    assert res.exit_code == 2 and "no battery C" in res.stderr


def test_flight_text_summary_and_report(tmp_path: Path) -> None:
    out = tmp_path / "flight.html"
    res = RUNNER.invoke(app, ["replay", "flight", str(LOGS / "px4_two_batteries.ulg"),
                              "--report", str(out), "--parallel", "A,B"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "headlines:" in res.stdout and "  - B: sequencing would have kept" in res.stdout
    # the sequencing summary names B as the headlines do (#29: it said "battery 1")
    assert re.search(r"cross_current_risk \(t_s [\d.]+, battery B, index 1", res.stdout)
    assert f"wrote {out}" in res.stdout
    page = out.read_text()
    # the run report's zoomable charts (#29): none for a battery without temperature, the
    # pack's three (voltage, current, FETs)
    charts = re.findall(r'data-chart="([^"]+)"', page)
    assert charts == ["seq-voltage", "seq-current", "seq-fets"], charts
    assert "not replayed" in page and "--assume-temp-c" in page
    assert not re.search(r"""(src|href)=["']?https?:""", page), "no network"
    bad = RUNNER.invoke(app, ["replay", "flight", str(LOGS / "px4_two_batteries.ulg"),
                              "--report", str(tmp_path / "r.txt")])  # fmt: skip
    assert bad.exit_code == 2 and "--report" in bad.stderr


@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium not installed")
def test_report_renders_in_chromium(tmp_path: Path) -> None:
    fr = replay_flight(LOGS / "px4_two_batteries.ulg", ProtectionConfig(), SequencingConfig(),
                       LogOptions(assume_temp_c=25.0), ("A", "B"))  # fmt: skip
    page = tmp_path / "f.html"
    page.write_text(flight_html(fr))
    with chromium(tmp_path / "profile", 1100, 900) as cdp:
        open_page(cdp, page.resolve().as_uri())
        assert cdp.requests == [page.resolve().as_uri()], "the page loads nothing but itself"
        # A, B, the pack (the pilot section's voltage-against-current scatters are class sag)
        assert cdp.eval("document.querySelectorAll('svg:not(.sag)').length") == 3
        assert cdp.eval("document.querySelectorAll('svg.sag').length") == 2
        heads = cdp.eval("[...document.querySelectorAll('#verdict li')].map(e => e.textContent)")
        assert any("39.5 A flowing into B" in h for h in heads)
        lacks = cdp.eval("document.getElementById('lacks').textContent")
        assert "assumed (--assume-temp-c)" in lacks and "PX4 fills it so" in lacks
        # Every figure is laid out at a readable size inside the page's width.
        boxes = cdp.eval(
            "[...document.querySelectorAll('svg:not(.sag)')].map(e => {"
            "const r = e.getBoundingClientRect();"
            " return [r.width, r.height, r.right];})"
        )
        width = cdp.eval("document.documentElement.clientWidth")
        assert all(w > 500 and h > 250 and right <= width for w, h, right in boxes), boxes
        shot = tmp_path / "f.png"
        cdp.screenshot(shot, full_page=True)
    raw = shot.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    w, h = struct.unpack(">II", raw[16:24])
    assert w == 1100 and h > 1500 and len(raw) > 60_000  # figures and text, not a blank page


# ----------------------------------------------------------------- vocabulary and options


def test_sequencing_named_and_numbered_columns_agree(tmp_path: Path) -> None:
    rows = [[0.1 * k, 24.0 - 0.1 * k, 23.0, 20.0, 0.0] for k in range(30)]
    named = tmp_path / "named.csv"
    named.write_text("t_s,A_voltage_v,B_voltage_v,A_current_a,B_current_a,A_stage\n" + "".join(
        f"{r[0]:g},{r[1]:g},{r[2]:g},{r[3]:g},{r[4]:g},cc\n" for r in rows))  # fmt: skip
    numbered = tmp_path / "numbered.csv"
    numbered.write_text(
        "t_s,v_0,v_1,i_0,i_1\n" + "".join(",".join(f"{x:g}" for x in r) + "\n" for r in rows)
    )
    a, b = seq_replay(named, SequencingConfig()), seq_replay(numbered, SequencingConfig())
    assert a.rows == b.rows and a.summary["batteries"] == ["A", "B"]


def test_equalization_reads_the_trace_group_names(tmp_path: Path) -> None:
    body = "".join(f"{k},1.0,{3.30 + 0.001 * k},3.31,3.32\n" for k in range(20))
    named = tmp_path / "g.csv"
    named.write_text("t_s,main_current_a,main_g0_v,main_g1_v,main_g2_v\n" + body)
    old = tmp_path / "v.csv"
    old.write_text("t_s,current_a,v_0,v_1,v_2\n" + body)
    from packpilot.config.equalization import EqualizationConfig

    a, b = eq_replay(named, EqualizationConfig()), eq_replay(old, EqualizationConfig())
    assert a.rows == b.rows and a.summary["battery"] == "main" and a.summary["groups"] == 3


def test_several_batteries_need_battery_and_options_that_do_not_apply(tmp_path: Path) -> None:
    log = tmp_path / "two.csv"
    log.write_text("t_s,A_current_a,A_temp_c,A_min_cell_v,B_current_a,B_temp_c,B_min_cell_v\n"
                   "0,10,25,3.1,10,25,3.3\n1,10,25,3.1,10,25,3.3\n")  # fmt: skip
    res = RUNNER.invoke(app, ["replay", "protection", str(log)])
    assert res.exit_code == 2 and "batteries A, B: choose one with --battery" in res.stderr
    res = RUNNER.invoke(app, ["replay", "protection", str(log), "--battery", "B", "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["battery"] == "B"
    res = RUNNER.invoke(app, ["replay", "protection", str(log), "--battery", "C"])
    assert res.exit_code == 2 and "--battery C: not in the log (A, B)" in res.stderr
    res = RUNNER.invoke(app, ["replay", "sequencing", str(log), "--assume-temp-c", "20"])
    assert res.exit_code == 2 and "--assume-temp-c does not apply" in res.stderr


def test_protection_without_temperature_is_refused_unless_stated(tmp_path: Path) -> None:
    log = tmp_path / "nt.csv"
    log.write_text("t_s,current_a,min_cell_v\n" + "".join(f"{k},10,3.1\n" for k in range(8)))
    res = RUNNER.invoke(app, ["replay", "protection", str(log)])
    assert res.exit_code == 2 and "temp_c" in res.stderr and "--assume-temp-c" in res.stderr
    res = RUNNER.invoke(app, ["replay", "protection", str(log), "--assume-temp-c", "25", "--json"])
    s = json.loads(res.stdout)
    assert s["trip_time_s"] == 5.0 and "25 degC" in s["assumed"][0]
    res = RUNNER.invoke(app, ["replay", "protection", str(log), "--assume-temp-c", "500"])
    assert res.exit_code == 2 and "-60..100" in res.stderr


def test_cells_derive_min_cell_v_only_where_missing_and_say_so(tmp_path: Path) -> None:
    log = tmp_path / "v.csv"
    log.write_text(
        "t_s,voltage_v,current_a,temp_c\n" + "".join(f"{k},18.6,10,25\n" for k in range(8))
    )
    res = RUNNER.invoke(app, ["replay", "protection", str(log)])
    assert res.exit_code == 2 and "--cells N" in res.stderr
    s = json.loads(
        RUNNER.invoke(app, ["replay", "protection", str(log), "--cells", "6", "--json"]).stdout
    )
    assert s["trip_time_s"] == 5.0  # 18.6 V / 6 = 3.1 V < P3's 3.2 V at 10 A
    assert any("voltage_v / 6 (--cells)" in a for a in s["assumed"])
    res = RUNNER.invoke(app, ["replay", "protection", str(log), "--cells", "0"])
    assert res.exit_code == 2 and "--cells 0" in res.stderr
    # Given where the log has the column, the option is reported unused, not silently ignored.
    full = tmp_path / "f.csv"
    full.write_text("t_s,current_a,temp_c,min_cell_v\n0,10,25,3.1\n1,10,25,3.1\n")
    s = json.loads(RUNNER.invoke(app, ["replay", "protection", str(full), "--cells", "6",
                                       "--assume-temp-c", "0", "--json"]).stdout)  # fmt: skip
    assert s["assumed"] == ["--assume-temp-c not used: the log has temp_c",
                            "--cells not used: the log has min_cell_v"]  # fmt: skip
    t = _flight(str(LOGS / "px4_one_battery.ulg"), "--cells", "6", "--assume-temp-c", "0")
    assert any("--cells 6 not used" in n for n in t["notes"])  # type: ignore[attr-defined]
    assert any("--assume-temp-c 0 not used" in n for n in t["notes"])  # type: ignore[attr-defined]


def test_the_autopilots_own_judgement_is_carried(tmp_path: Path) -> None:
    """A PX4 battery that reports warning = emergency in every sample, remaining falling to 0:
    the headlines say so next to PackPilot's verdict, with the autopilot's mAh."""
    from packpilot.io.flightlog.ulog import write_ulog

    samples = [
        {"timestamp": 1_000_000 * k, "voltage_v": 22.0 - 0.01 * k, "current_a": 10.0,
         "current_average_a": 10.0, "discharged_mah": 10.0 / 3.6 * k,
         "remaining": max(0.0, 0.2 - 0.002 * k), "temperature": 20.0,
         "voltage_cell_v": [0.0] * 14, "cell_count": 6, "connected": True, "id": 0,
         "warning": 3}
        for k in range(120)
    ]  # fmt: skip
    log = tmp_path / "warned.ulg"
    write_ulog(log, [samples], start_us=0)
    s = _flight(str(log))
    heads = s["headlines"]
    assert isinstance(heads, list)
    warned = [h for h in heads if "the autopilot warned" in h]
    assert warned == [
        "A: the autopilot warned from 0.0 s, worst level emergency (120 of 120 samples)"
    ]
    notes = s["notes"]
    assert isinstance(notes, list)
    assert any("331 mAh discharged" in n for n in notes), notes  # 10 A for 119 s
    assert any("remaining went from 20 % to 0 %" in n for n in notes), notes
