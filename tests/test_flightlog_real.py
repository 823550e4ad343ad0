"""Real flight logs written by real autopilots (examples/logs/real, provenance in its
MANIFEST.md): every one imports or is refused in one line naming what is missing or damaged,
never with a traceback or "malformed"."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.errors import InputError
from packpilot.io.flightlog import read_flight_log
from packpilot.io.flightlog.dataflash import _interval_from_counter

REAL = Path(__file__).resolve().parents[1] / "examples" / "logs" / "real"
RUNNER = CliRunner()

IMPORTS = {
    # file: (rows at least, columns that must be there)
    "ardupilot_3x_mechanical_fail.log": (100, {"A_voltage_v", "A_current_a"}),
    "ardupilot_3x_nan.log": (15, {"A_voltage_v", "A_current_a"}),
    "ardupilot_3x_robert_lefebvre_octo_PM.log": (60, {"A_voltage_v", "A_current_a"}),
    "ardupilot_3x_tradheli_brownout.log": (100, {"A_voltage_v", "A_current_a"}),
    "ardupilot_3x_underpowered.log": (400, {"A_voltage_v", "A_current_a"}),
    "ardupilot_4.6.2_whole_messages.bin": (4, {"A_voltage_v", "A_current_a", "A_soc"}),
    "px4_sample_log_small.ulg": (40, {"A_voltage_v", "B_voltage_v", "A_soc", "B_current_a"}),
    "px4_sample_logging_tagged_and_default_params.ulg": (50, {"A_voltage_v", "A_soc"}),
    "px4_sample_px4_events.ulg": (150, {"A_voltage_v", "A_soc"}),
    "arducopter_dronekit_flight_battery.tlog": (2800, {"A_voltage_v", "A_current_a", "A_soc"}),
}
REFUSED = {
    "ardupilot_4.6.2_truncated.bin": "truncated",
    "px4_sample_appended_multiple.ulg": "no battery_status topic",
}


def test_every_real_log_is_listed_in_the_manifest() -> None:
    manifest = (REAL / "MANIFEST.md").read_text()
    files = {p.name for p in REAL.iterdir() if p.suffix in (".ulg", ".bin", ".log", ".tlog")}
    assert files == set(IMPORTS) | set(REFUSED)
    assert len(IMPORTS) >= 6
    for name in files:
        assert f"`{name}`" in manifest, name


@pytest.mark.parametrize("name", sorted(IMPORTS))
def test_real_log_imports(name: str, tmp_path: Path) -> None:
    out = tmp_path / "t.csv"
    res = RUNNER.invoke(app, ["import", str(REAL / name), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert "malformed" not in res.output and "Traceback" not in res.output
    rows, cols = IMPORTS[name]
    header = out.read_text().splitlines()[0].split(",")
    assert cols <= set(header), header
    assert len(out.read_text().splitlines()) - 1 >= rows
    log = read_flight_log(REAL / name)
    for b in log.batteries:
        assert np.all(np.diff(b.t_s) > 0)
    assert log.autopilot is not None and ("Ardu" in log.autopilot or "PX4" in log.autopilot)


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_real_log_refused_in_one_line(name: str, tmp_path: Path) -> None:
    res = RUNNER.invoke(app, ["import", str(REAL / name), "--out", str(tmp_path / "t.csv")])
    assert res.exit_code == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and REFUSED[name] in lines[0], lines
    assert "malformed" not in res.stderr


def test_curr_without_time_field_takes_time_from_gps() -> None:
    """ArduCopter 3.1: ``FMT, 9, 19, CURR, hIhhhf`` has no time; the GPS clock gives it, and
    the charge counter agrees with that clock (1 s logging interval, within 1 %)."""
    b = read_flight_log(REAL / "ardupilot_3x_mechanical_fail.log").batteries[0]
    assert b.time_derived is not None and "GPS" in b.time_derived
    assert b.discharged_mah is not None and b.current_a is not None
    rows = [{"mah": m, "curr": c} for m, c in zip(b.discharged_mah, b.current_a, strict=True)]
    by_counter = _interval_from_counter(rows)
    assert by_counter is not None
    assert float(np.median(np.diff(b.t_s))) == pytest.approx(by_counter, rel=0.01)


def test_curr_without_time_or_gps_takes_the_charge_counters_interval() -> None:
    log = read_flight_log(REAL / "ardupilot_3x_underpowered.log")
    b = log.batteries[0]
    assert b.time_derived is not None and "CurrTot" in b.time_derived
    assert float(np.median(np.diff(b.t_s))) == pytest.approx(1.0, abs=0.01)
    assert log.autopilot == "ArduCopter V3.0.1"
    assert [m for _, m in log.modes][:2] == ["ALT_HOLD", "STABILIZE"]
    notes = log.table().notes
    assert any("time derived" in n for n in notes)
    assert any("2276 mAh discharged" in n for n in notes)


def test_gps_without_week_does_not_break_the_reader() -> None:
    """pymavlink's own clock raises on 3.0.1 GPS messages (no Week); PackPilot does not use it."""
    log = read_flight_log(REAL / "ardupilot_3x_robert_lefebvre_octo_PM.log")
    assert log.batteries[0].t_s[-1] == pytest.approx(157.3, abs=1.0)
    assert any("LOITER" in m for _, m in log.modes)


def test_px4_fill_from_the_filtered_voltage_is_not_taken_for_cells() -> None:
    """PX4 fills voltage_cell_v with voltage_filtered_v / n: ~50 mV from voltage_v / n here,
    far beyond the 2 mV tolerance; both are checked, so no 'lowest cell' is claimed."""
    log = read_flight_log(REAL / "px4_sample_log_small.ulg")
    a, b = log.batteries
    assert a.cells_v is None and a.cell_count == 6 and b.cell_count == 12
    assert any("voltage_filtered_v" in n for n in a.notes)
    assert a.discharged_mah is not None and a.warning is not None
    table = log.table()
    assert any("average cell" in n for n in table.notes)


def test_px4_modes_and_remaining_are_carried() -> None:
    log = read_flight_log(REAL / "px4_sample_px4_events.ulg")
    names = [m for _, m in log.modes]
    assert "AUTO_TAKEOFF" in names and "AUTO_RTL" in names
    notes = log.table().notes
    assert any("remaining went from 100 % to 90 % (lowest 77 %)" in n for n in notes), notes


def test_corrupt_and_cut_copies_are_one_line(tmp_path: Path) -> None:
    src = (REAL / "px4_sample_log_small.ulg").read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(src[: len(src) // 2 + 1])
    with pytest.raises(InputError, match="truncated"):
        read_flight_log(cut)
    text = (REAL / "ardupilot_3x_underpowered.log").read_bytes()
    cut_log = tmp_path / "cut.log"
    cut_log.write_bytes(text[:100_001])
    res = RUNNER.invoke(app, ["import", str(cut_log), "--out", str(tmp_path / "x.csv")])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1
    junk = tmp_path / "junk.bin"
    junk.write_bytes(bytes(range(256)) * 10)
    res = RUNNER.invoke(app, ["import", str(junk), "--out", str(tmp_path / "y.csv")])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1


def test_binary_3x_curr_without_time_takes_gps_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The same 3.0 layout as a binary log (``CURR hIhhhf`` without time, GPS ``Time`` in ms
    of the GPS week without ``Week``): one CURR every 2 s, between GPS fixes 0.5 s apart."""
    from packpilot.io.flightlog import dataflash

    old = {"CURR": (9, "hIhhhf", "Thr,ThrInt,Volt,Curr,Vcc,CurrTot"),
           "GPS": (130, "BIB", "Status,Time,NSats")}  # fmt: skip
    monkeypatch.setattr(dataflash, "FORMATS", {**dataflash.FORMATS, **old})
    msgs: list[tuple[str, list[float]]] = []
    for k in range(40):
        msgs.append(("GPS", [3, 500_000_000 + 1000 * k, 9]))
        if k % 2 == 1:
            msgs.append(("GPS", [3, 500_000_000 + 1000 * k + 500, 9]))
            msgs.append(("CURR", [300, 0, 1180 - k, 1500, 5000, 4.17 * k]))
    msgs.append(("GPS", [3, 500_040_000, 9]))
    path = tmp_path / "old.bin"
    dataflash.write_bin(path, msgs)
    b = read_flight_log(path).batteries[0]
    assert b.time_derived is not None and "GPS" in b.time_derived
    np.testing.assert_allclose(np.diff(b.t_s), 2.0, atol=1e-9)
    assert b.voltage_v[0] == pytest.approx(11.79) and b.current_a[0] == pytest.approx(15.0)
