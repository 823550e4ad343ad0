"""Flight-log import (#17 §5): the shipped sample logs read by the real parsers (pyulog,
pymavlink) on their own, then through PackPilot's importer; what a log lacks is stated and
never filled in; old CURR scaling, BCL's unused cells, PX4's V / n cells and -1 A; damaged
files; the missing-extra message."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st
from pymavlink import DFReader
from pyulog import ULog
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.errors import InputError
from packpilot.io.flightlog import hold, need, read_flight_log
from packpilot.io.flightlog.dataflash import write_bin, write_text
from packpilot.io.flightlog.ulog import write_ulog
from packpilot.replay.common import read_log
from tests.budget import budget
from tests.conftest import EXAMPLES

LOGS = EXAMPLES / "logs"
RUNNER = CliRunner()


def _df(path: Path) -> Any:
    return (
        DFReader.DFReader_text(str(path))
        if path.suffix == ".log"
        else DFReader.DFReader_binary(str(path))
    )


def _messages(path: Path, kind: str) -> list[Any]:
    log = _df(path)
    out = []
    while (m := log.recv_match(type=[kind])) is not None:
        out.append(m.to_dict())
    log.close()
    return out


# ----------------------------------------------------------------- the parsers on their own


@pytest.mark.parametrize(
    ("name", "instances"), [("px4_one_battery.ulg", 1), ("px4_two_batteries.ulg", 2)]
)
def test_pyulog_reads_the_shipped_ulogs(name: str, instances: int) -> None:
    ulog = ULog(str(LOGS / name))
    sets = [d for d in ulog.data_list if d.name == "battery_status"]
    assert sorted(d.multi_id for d in sets) == list(range(instances))
    assert ulog.msg_info_dict["sys_name"] == "PackPilot"
    d = sets[0].data
    assert len(d["timestamp"]) == 600 and np.all(np.diff(d["timestamp"]) > 0)
    assert 20.0 < float(d["voltage_v"][0]) < 25.3
    assert "voltage_cell_v[13]" in d and int(d["cell_count"][0]) == 6


@pytest.mark.parametrize(
    "name",
    ["ardupilot_one_battery.bin", "ardupilot_two_batteries.bin", "ardupilot_two_batteries.log"],
)
def test_pymavlink_reads_the_shipped_dataflash_logs(name: str) -> None:
    bat = _messages(LOGS / name, "BAT")
    inst = {m["Inst"] for m in bat}
    assert inst == ({0} if "one" in name else {0, 1})
    assert len(bat) == 600 * len(inst)
    assert all(m["Temp"] == 0.0 for m in bat)  # no temperature sensor, as ArduPilot logs it
    first = bat[0]
    assert 20.0 < first["Volt"] < 25.3 and first["TimeUS"] == 0
    bcl = _messages(LOGS / name, "BCL")
    if "one" in name:
        assert len(bcl) == 600 and bcl[0]["V7"] == 65535 and 3500 < bcl[0]["V1"] < 4300
    else:
        assert bcl == []


def test_text_and_binary_dataflash_agree() -> None:
    a = read_flight_log(LOGS / "ardupilot_two_batteries.bin").table(cells=6)
    b = read_flight_log(LOGS / "ardupilot_two_batteries.log").table(cells=6)
    assert list(a.columns) == list(b.columns)
    for name in a.columns:
        np.testing.assert_allclose(
            a.columns[name], b.columns[name], rtol=5e-6, atol=1e-6
        )  # text: 6 digits


# ----------------------------------------------------------------- the importer


def test_px4_smart_battery_has_temperature_and_real_cells() -> None:
    log = read_flight_log(LOGS / "px4_one_battery.ulg")
    assert log.format == "PX4 ULog" and [b.name for b in log.batteries] == ["A"]
    t = log.table()
    for col in ("A_voltage_v", "A_current_a", "A_temp_c", "A_min_cell_v", "A_g5_v", "A_soc"):
        assert col in t.columns
    cells = np.column_stack([t.columns[f"A_g{k}_v"] for k in range(6)])
    np.testing.assert_allclose(t.columns["A_min_cell_v"], cells.min(axis=1))
    assert np.ptp(cells[0]) > 1e-4, "measured cells differ; they are not V / 6"
    assert t.columns["t_s"][0] == 0.0 and t.columns["t_s"][-1] == 599.0
    assert t.columns["A_temp_c"][0] == pytest.approx(-10.0, abs=0.5)
    assert t.notes[0] == "PX4 ULog: A = battery_status instance 0"
    assert t.notes[1] == "autopilot: PackPilot"  # the writer's sys_name
    assert all(n.startswith("A: the autopilot") for n in t.notes[2:]), t.notes


def test_px4_analog_batteries_lack_temperature_and_cells_and_say_so() -> None:
    t = read_flight_log(LOGS / "px4_two_batteries.ulg").table()
    assert "A_temp_c" not in t.columns and "B_temp_c" not in t.columns
    text = "\n".join(t.notes)
    assert "temperature is NaN throughout" in text
    assert "PX4 fills it so" in text and "the average cell" in text
    np.testing.assert_allclose(t.columns["B_min_cell_v"], t.columns["B_voltage_v"] / 6)
    assert "--assume-temp-c" in t.hints["A_temp_c"]
    # Stated, the assumption is used and listed, never silently.
    t = read_flight_log(LOGS / "px4_two_batteries.ulg").table(assume_temp_c=15.0)
    assert set(t.columns["A_temp_c"]) == {15.0}
    assert any("15 degC assumed (--assume-temp-c)" in n for n in t.assumed)
    assert not any("assumed" in n for n in t.notes)


def test_ardupilot_without_cells_needs_a_cell_count() -> None:
    log = read_flight_log(LOGS / "ardupilot_two_batteries.bin")
    t = log.table()
    assert "A_min_cell_v" not in t.columns and "--cells" in t.hints["A_min_cell_v"]
    assert any("Temp is 0 throughout" in n for n in t.notes)
    t6 = log.table(cells=6)
    np.testing.assert_allclose(t6.columns["A_min_cell_v"], t6.columns["A_voltage_v"] / 6)
    # B is charged by A at connection: negative current, PackPilot's sign kept.
    assert float(np.min(t6.columns["B_current_a"])) < -30.0
    with pytest.raises(InputError, match="--cells 0"):
        log.table(cells=0)


def test_ardupilot_bcl_cells_are_read(tmp_path: Path) -> None:
    t = read_flight_log(LOGS / "ardupilot_one_battery.bin").table(assume_temp_c=-10.0)
    cells = np.column_stack([t.columns[f"A_g{k}_v"] for k in range(6)])
    assert "A_g6_v" not in t.columns, "65535 marks a cell that does not exist"
    np.testing.assert_allclose(t.columns["A_min_cell_v"], cells.min(axis=1))
    ulg = read_flight_log(LOGS / "px4_one_battery.ulg").table()
    np.testing.assert_allclose(t.columns["A_min_cell_v"], ulg.columns["A_min_cell_v"], atol=6e-4)


def test_old_curr_is_scaled_from_centivolts_and_centiamps(tmp_path: Path) -> None:
    msgs = [("CURR", [k * 1_000_000, 500, 2410 - k, 1250, 5000, 10.0 * k]) for k in range(20)]
    for path, writer in ((tmp_path / "old.bin", write_bin), (tmp_path / "old.log", write_text)):
        writer(path, msgs)
        log = read_flight_log(path)
        assert [b.source for b in log.batteries] == ["CURR"]
        t = log.table(cells=6, assume_temp_c=20.0)
        assert t.columns["A_voltage_v"][:2].tolist() == pytest.approx([24.10, 24.09])
        assert set(t.columns["A_current_a"].tolist()) == {12.5}
        assert any("3.x" in n for n in t.notes)


def test_px4_unknown_current_and_gaps(tmp_path: Path) -> None:
    def sample(k: int, current: float, temp: float) -> dict[str, Any]:
        return {"timestamp": 1000 + k * 100_000, "voltage_v": 24.0 - 0.01 * k, "current_a": current,
                "current_average_a": current, "discharged_mah": 0.0, "remaining": 0.5,
                "temperature": temp, "voltage_cell_v": [0.0] * 14, "cell_count": 6,
                "connected": True, "id": 0, "warning": 0}  # fmt: skip

    temps = [math.nan, 20.0, math.nan, 22.0] * 3
    write_ulog(tmp_path / "x.ulg", [[sample(k, -1.0, temps[k]) for k in range(12)]])
    t = read_flight_log(tmp_path / "x.ulg").table()
    assert "A_current_a" not in t.columns and "no current" in t.hints["A_current_a"]
    assert t.columns["A_temp_c"].tolist()[:4] == [20.0, 20.0, 20.0, 22.0]
    assert any("missing in 6 of 12 samples" in n and "1 leading" in n for n in t.notes)
    assert any("voltage_cell_v is empty" in n for n in t.notes)


def test_hold_fills_forward_and_counts() -> None:
    x, held, lead = hold(np.array([math.nan, 1.0, math.nan, math.nan, 2.0]))
    assert x.tolist() == [1.0, 1.0, 1.0, 1.0, 2.0] and (held, lead) == (2, 1)


def test_two_battery_time_base_holds_each_batterys_latest(tmp_path: Path) -> None:
    msgs = [("BAT", [t, inst, v, v, 1.0, 0, 0, 0, 0, 50, 0])
            for t, inst, v in [(0, 0, 24.0), (500_000, 1, 23.0), (1_000_000, 0, 23.9),
                               (1_500_000, 1, 22.9), (2_000_000, 0, 23.8)]]  # fmt: skip
    write_bin(tmp_path / "t.bin", msgs)
    t = read_flight_log(tmp_path / "t.bin").table(cells=6, assume_temp_c=25.0)
    assert t.columns["t_s"].tolist() == [0.5, 1.0, 1.5, 2.0]
    assert t.columns["A_voltage_v"].tolist() == pytest.approx([24.0, 23.9, 23.9, 23.8])
    assert t.columns["B_voltage_v"].tolist() == pytest.approx([23.0, 23.0, 22.9, 22.9])
    assert any("union of the batteries' sample times" in n for n in t.notes)


# ----------------------------------------------------------------- the CLI and bad input


def test_import_cli_writes_the_vocabulary_and_states_what_lacks(tmp_path: Path) -> None:
    out = tmp_path / "bat.csv"
    res = RUNNER.invoke(
        app,
        ["import", str(LOGS / "ardupilot_two_batteries.bin"), "--out", str(out), "--cells", "6"],
    )
    assert res.exit_code == 0, res.output
    assert "note: A: Temp is 0 throughout" in res.stderr
    assert (
        "assumed: A: no per-cell voltages: min_cell_v = max_cell_v = voltage_v / 6 (--cells)"
        in res.stderr
    )
    header = out.read_text().splitlines()[0].split(",")
    assert header[:3] == ["t_s", "A_voltage_v", "A_current_a"] and "B_min_cell_v" in header
    assert not [h for h in header if h.endswith("temp_c")]
    log = read_log(out, ["t_s", "A_current_a", "B_voltage_v"])
    assert len(log) == 600


def test_shipped_flight_log_csv_is_the_import_of_the_ulog(tmp_path: Path) -> None:
    out = tmp_path / "f.csv"
    res = RUNNER.invoke(app, ["import", str(LOGS / "px4_one_battery.ulg"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert out.read_text() == (LOGS / "flight_log.csv").read_text()


@pytest.mark.parametrize("suffix", [".ulg", ".bin", ".log"])
def test_damaged_or_empty_logs_are_one_line_errors(tmp_path: Path, suffix: str) -> None:
    good = {".ulg": "px4_one_battery.ulg", ".bin": "ardupilot_one_battery.bin",
            ".log": "ardupilot_two_batteries.log"}[suffix]  # fmt: skip
    raw = (LOGS / good).read_bytes()
    for i, body in enumerate((b"", raw[:40], b"\x00" * 700, raw[: len(raw) // 2] + b"\xff" * 3)):
        p = tmp_path / f"bad{i}{suffix}"
        p.write_bytes(body)
        res = RUNNER.invoke(app, ["import", str(p), "--out", str(tmp_path / "o.csv")])
        if res.exit_code == 0:  # a truncated log that still holds battery data is read
            assert i == 3
            continue
        assert res.exit_code == 2, res.output
        lines = [ln for ln in res.stderr.splitlines() if ln.startswith("error:")]
        assert len(lines) == 1 and str(p) in lines[0] and "Traceback" not in res.stderr


def test_a_log_without_battery_data(tmp_path: Path) -> None:
    p = tmp_path / "nobat.bin"
    write_bin(p, [])
    with pytest.raises(InputError, match="without battery data: it has no BAT or CURR"):
        read_flight_log(p)


def test_missing_parser_names_the_extra() -> None:
    with pytest.raises(
        InputError, match=r"needs the optional package pyulog: pip install 'packpilot\[logs\]'"
    ):
        need("packpilot_no_such_parser", "pyulog", "a PX4 ULog")


SAMPLES = sorted(p for p in LOGS.iterdir() if p.suffix in (".ulg", ".bin", ".log"))


@budget(60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    sample=st.sampled_from(SAMPLES),
    cut=st.integers(0, 4000),
    junk=st.binary(max_size=64),
    at=st.integers(0, 4000),
)
def test_fuzzed_flight_logs_read_or_refuse(
    tmp_path: Path, sample: Path, cut: int, junk: bytes, at: int
) -> None:
    """A sample cut short and with junk bytes spliced in: read, or one clean InputError."""
    raw = sample.read_bytes()[: max(0, len(sample.read_bytes()) - cut)]
    body = raw[:at] + junk + raw[at:]
    p = tmp_path / f"f{sample.suffix}"
    p.write_bytes(body)
    try:
        table = read_flight_log(p).table(cells=6, assume_temp_c=20.0)
    except InputError as err:
        assert "\n" not in str(err) and str(err).startswith(str(p))
        return
    assert np.all(np.diff(table.columns["t_s"]) > 0)
    for name, col in table.columns.items():
        assert np.all(np.isfinite(col)), name


def test_a_damaged_bin_is_one_line_on_the_real_stderr(tmp_path: Path) -> None:
    """pymavlink's compiled indexer writes "bad header …" per stray byte straight to file
    descriptor 2: a subprocess sees the real stderr, which must hold one line."""
    raw = (LOGS / "ardupilot_one_battery.bin").read_bytes()
    p = tmp_path / "damaged.bin"
    p.write_bytes(raw[:300] + bytes(range(256)) * 4 + raw[300:1200])
    proc = subprocess.run(
        [sys.executable, "-m", "packpilot.cli", "import", str(p), "--out", str(tmp_path / "o.csv")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    if proc.returncode == 0:  # the records after the junk still read: notes only
        assert all(ln.startswith(("note:", "assumed:")) for ln in lines), lines
    else:
        assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error:"), lines
