"""MAVLink telemetry logs (.tlog): a real ground-station log of a real ArduCopter flight
(SYS_STATUS), and tlogs written with pymavlink's own encoder for what the real one lacks
(BATTERY_STATUS with cells, temperature, the charge counter and charge_state)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.errors import InputError
from packpilot.io.flightlog import read_flight_log
from tests.budget import budget

REAL = Path(__file__).resolve().parents[1] / "examples" / "logs" / "real"
TLOG = REAL / "arducopter_dronekit_flight_battery.tlog"
RUNNER = CliRunner()
T0_US = 1_600_000_000_000_000


def test_real_tlog_battery_modes_and_the_autopilots_own_account() -> None:
    log = read_flight_log(TLOG)
    (b,) = log.batteries
    assert b.source == "SYS_STATUS of system 1"
    # a 3S pack: 12.28 V at rest before take-off, 10.62 V after landing (the log's own values)
    assert b.voltage_v[0] == pytest.approx(12.277) and b.voltage_v[-1] == pytest.approx(10.617)
    assert b.current_a is not None and 50.0 < float(np.max(b.current_a)) < 60.0
    assert b.soc is not None and b.soc[0] == pytest.approx(0.99) and b.soc[-1] == pytest.approx(0.2)
    assert b.temp_c is None and b.cells_v is None and b.discharged_mah is None
    assert np.all(np.diff(b.t_s) > 0) and 1000.0 < b.t_s[-1] < 1100.0
    assert [m for _, m in log.modes][:3] == ["STABILIZE", "LOITER", "AUTO"]
    assert "RTL" in [m for _, m in log.modes]
    assert log.autopilot is not None and log.autopilot.startswith("ArduPilot (quadrotor")
    notes = " ".join(log.notes)
    assert "BATT_CAPACITY parameter: 2650 mAh" in notes and "'Low Battery!' at" in notes
    assert "receive time" in notes  # the time base is said to be the ground station's


def test_real_tlog_imports_and_fits(tmp_path: Path) -> None:
    out = tmp_path / "t.csv"
    res = RUNNER.invoke(app, ["import", str(TLOG), "--out", str(out), "--cells", "3"])
    assert res.exit_code == 0, res.output
    header = out.read_text().splitlines()[0].split(",")
    assert {"t_s", "A_voltage_v", "A_current_a", "A_soc", "A_min_cell_v"} <= set(header)
    res = RUNNER.invoke(app, ["fit", str(TLOG), "--cells", "3", "--json"])
    assert res.exit_code == 0, res.output
    assert '"verdict"' in res.output


def _write(path: Path, packets: list[tuple[float, bytes]]) -> None:
    path.write_bytes(b"".join(struct.pack(">Q", T0_US + round(t * 1e6)) + p for t, p in packets))


def _battery_tlog(path: Path, n: int = 40) -> None:
    """A vehicle (system 1) heartbeat plus BATTERY_STATUS with 4 cells at 1 Hz, encoded by
    pymavlink (a GCS (system 255) heartbeat too, which must not count as a vehicle)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    vehicle = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    packets: list[tuple[float, bytes]] = []
    for k in range(n):
        t = float(k)
        packets.append((t, gcs.heartbeat_encode(6, 8, 0, 0, 0).pack(gcs)))
        mode = 3 if k < n // 2 else 6  # ArduCopter AUTO, then RTL
        packets.append((t + 0.01, vehicle.heartbeat_encode(2, 3, 1, mode, 4).pack(vehicle)))
        cell_mv = 4100 - 10 * k
        cells = [cell_mv, cell_mv - 5, cell_mv + 3, cell_mv] + [65535] * 6
        state = 1 if k < n - 5 else 2  # OK, then LOW
        msg = vehicle.battery_status_encode(
            0, 0, 0, 2500 + 10 * k, cells, 1500, 4 * k, -1, 100 - k, charge_state=state
        )
        packets.append((t + 0.02, msg.pack(vehicle)))
    _write(path, packets)


def test_battery_status_cells_temperature_counter_and_warning(tmp_path: Path) -> None:
    path = tmp_path / "bat.tlog"
    _battery_tlog(path)
    log = read_flight_log(path)
    (b,) = log.batteries
    assert b.source == "BATTERY_STATUS id 0 of system 1"
    assert b.cells_v is not None and b.cells_v.shape[1] >= 4
    assert b.voltage_v[0] == pytest.approx((4100 * 4 - 5 + 3) / 1000.0)
    assert b.current_a is not None and np.all(b.current_a == pytest.approx(15.0))
    assert b.temp_c is not None and b.temp_c[3] == pytest.approx(25.3)
    assert b.discharged_mah is not None and b.discharged_mah[-1] == pytest.approx(156.0)
    assert b.warning is not None and int(b.warning.max()) == 1  # LOW
    assert [m for _, m in log.modes] == ["AUTO", "RTL"]
    table = log.table()
    assert "A_g3_v" in table.columns and "A_temp_c" in table.columns
    assert any("warned from" in n and "low" in n for n in table.notes)


def test_pack_voltage_in_battery_status_is_not_taken_for_cells(tmp_path: Path) -> None:
    """ArduPilot puts the whole pack voltage in voltages[0] when it measures no cells."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    packets = [
        (float(k), mav.battery_status_encode(0, 0, 0, 32767, [24000 - k] + [65535] * 9,
                                             -1, -1, -1, -1).pack(mav))
        for k in range(20)
    ]  # fmt: skip
    path = tmp_path / "pack.tlog"
    _write(path, packets)
    (b,) = read_flight_log(path).batteries
    assert b.cells_v is None and b.voltage_v[0] == pytest.approx(24.0)
    assert b.current_a is None and b.temp_c is None and b.soc is None
    assert any("pack voltage, not cells" in n for n in b.notes)


def test_cut_corrupted_and_battery_less_tlogs_are_one_line(tmp_path: Path) -> None:
    data = TLOG.read_bytes()
    cut = tmp_path / "cut.tlog"
    cut.write_bytes(data[: len(data) // 2 + 7])
    with pytest.raises(InputError, match="truncated: the file ends inside a record"):
        read_flight_log(cut)
    broken = bytearray(data)
    broken[8 + 40 * 1000 : 8 + 40 * 1000 + 64] = b"\x00" * 64
    bad = tmp_path / "bad.tlog"
    bad.write_bytes(bytes(broken))
    res = RUNNER.invoke(app, ["import", str(bad), "--out", str(tmp_path / "x.csv")])
    assert res.exit_code == 2 and len(res.stderr.strip().splitlines()) == 1, res.output
    assert "corrupted" in res.stderr or "truncated" in res.stderr
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 10)
    res = RUNNER.invoke(app, ["import", str(junk), "--out", str(tmp_path / "y.csv")])
    assert res.exit_code == 2 and "not a MAVLink telemetry log" in res.stderr
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    empty = tmp_path / "nobattery.tlog"
    _write(empty, [(float(k), mav.heartbeat_encode(2, 3, 1, 0, 4).pack(mav)) for k in range(5)])
    with pytest.raises(InputError, match="valid MAVLink telemetry log without battery data"):
        read_flight_log(empty)
    for path in (cut, bad, junk, empty):
        res = RUNNER.invoke(app, ["import", str(path), "--out", str(tmp_path / "z.csv")])
        assert res.exit_code == 2 and "Traceback" not in res.output
        assert "malformed" not in res.stderr


def _head(n: int) -> bytes:
    """The real log's first whole records up to about ``n`` bytes."""
    from packpilot.io.flightlog.tlog import records

    data = TLOG.read_bytes()
    recs, _ = records(TLOG, data)
    size = 0
    for _, packet in recs:
        if size >= n:
            break
        size += 8 + len(packet)
    return data[:size]


HEAD = _head(60_000)


def read_flight_log_ok(tmp_path: Path) -> bool:
    """The uncut head itself reads (so the fuzzer starts from a valid log)."""
    p = tmp_path / "whole.tlog"
    p.write_bytes(HEAD)
    return len(read_flight_log(p).batteries) == 1


@budget(60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, 3000), junk=st.binary(max_size=64), at=st.integers(0, 60_000))
def test_fuzzed_tlogs_read_or_refuse(tmp_path: Path, cut: int, junk: bytes, at: int) -> None:
    """The real tlog cut short and with junk spliced in: read, or one clean InputError."""
    if not cut and not junk:
        assert read_flight_log_ok(tmp_path)
    raw = HEAD[: len(HEAD) - cut]
    p = tmp_path / "f.tlog"
    p.write_bytes(raw[:at] + junk + raw[at:])
    try:
        table = read_flight_log(p).table(cells=3, assume_temp_c=20.0)
    except InputError as err:
        assert "\n" not in str(err) and str(err).startswith(str(p))
        return
    assert np.all(np.diff(table.columns["t_s"]) > 0)
    for name, col in table.columns.items():
        assert np.all(np.isfinite(col)), name
