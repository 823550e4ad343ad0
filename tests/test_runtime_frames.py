"""The runtime's frames: the shipped DBCs, the Pylontech golden vectors decoded by cantools,
the smart-battery codec's strictness, DroneCAN BatteryInfo through the ``dronecan`` package."""

from __future__ import annotations

import dataclasses
import math
from importlib import resources

import can
import pytest

from packpilot.io.can import battery as bc
from packpilot.io.can import dronecan_io as dc
from packpilot.io.can import pylon
from packpilot.io.can.codec import FrameError
from packpilot.io.can.dbcgen import MAX_BATTERIES, dbc_text

PACK = pylon.PackAsBattery(
    charge_voltage_v=53.2, charge_current_a=25.0, discharge_current_a=50.0,
    discharge_voltage_v=44.8, soc_pct=75, soh_pct=98, voltage_v=51.20, current_a=10.0,
    temp_c=25.3, protection=pylon.OVER_TEMP, warning=pylon.UNDER_VOLTAGE, modules=2,
)  # fmt: skip

GOLDEN = {
    # hand-packed from the byte layouts in shared/spec/protocols.md (little-endian)
    0x351: "14 02 FA 00 F4 01 C0 01",  # 53.2 V, 25.0 A, 50.0 A, 44.8 V (x0.1)
    0x355: "4B 00 62 00",  # SOC 75 %, SOH 98 %
    0x356: "00 14 9C FF FD 00",  # 51.20 V, -10.0 A (discharging 10 A), 25.3 degC
    0x359: "08 00 04 00 02 50 4E 00",  # over-temp protection, under-voltage warning, 2, 'PN'
    0x35C: "C0 00",  # charge enable, discharge enable
    0x35E: "50 41 43 4B 50 4C 54 20",  # "PACKPLT "
}


def test_shipped_dbc_is_the_generated_one() -> None:
    shipped = resources.files("packpilot.io.can").joinpath("packpilot.dbc").read_text("utf-8")
    assert shipped == dbc_text()
    db = bc.database()
    assert db.get_message_by_frame_id(0x300 + MAX_BATTERIES - 1).name == "BatteryMeas15"


def test_pylontech_golden_vectors() -> None:
    frames = {m.arbitration_id: m for m in pylon.encode_all(PACK)}
    assert sorted(frames) == sorted(GOLDEN)
    for fid, hexdata in GOLDEN.items():
        assert frames[fid].data.hex(" ").upper() == hexdata, hex(fid)
        assert not frames[fid].is_extended_id


def test_pylontech_decoded_by_cantools() -> None:
    """The second decoder: cantools reading the shipped pylon.dbc."""
    db = pylon.database()
    out = {m.arbitration_id: db.decode_message(m.arbitration_id, m.data) for m in
           pylon.encode_all(PACK)}  # fmt: skip
    lim = out[0x351]
    assert lim["ChargeVoltageLimit"] == pytest.approx(53.2)
    assert lim["ChargeCurrentLimit"] == pytest.approx(25.0)
    assert lim["DischargeCurrentLimit"] == pytest.approx(50.0)
    assert lim["DischargeVoltageLimit"] == pytest.approx(44.8)
    assert out[0x356]["Current"] == pytest.approx(-10.0)  # Pylontech: + = charging
    assert out[0x356]["Voltage"] == pytest.approx(51.2)
    assert out[0x356]["Temperature"] == pytest.approx(25.3)
    assert out[0x355] == {"SOC": 75, "SOH": 98}
    assert out[0x359]["ProtOverTemp"] == 1 and out[0x359]["ProtOverVoltage"] == 0
    assert out[0x359]["WarnUnderVoltage"] == 1 and out[0x359]["ModuleCount"] == 2
    assert (out[0x359]["Char5"], out[0x359]["Char6"]) == (ord("P"), ord("N"))
    assert out[0x35C]["ChargeEnable"] == 1 and out[0x35C]["DischargeEnable"] == 1
    charging = pylon.encode_measurements(
        dataclasses.replace(PACK, current_a=-12.3)
    )
    assert db.decode_message(0x356, charging.data)["Current"] == pytest.approx(12.3)


def test_pylontech_zero_limits_drop_enable_flags() -> None:
    tripped = dataclasses.replace(PACK, charge_current_a=0.0, discharge_current_a=0.0)
    assert pylon.encode_limits(tripped).data[2:6] == bytes(4)
    assert pylon.encode_request(tripped).data == bytes(2)
    neg = dataclasses.replace(PACK, charge_current_a=-5.0)
    assert pylon.encode_limits(neg).data[2:4] == bytes(2)  # a limit is never negative


def test_battery_codec_round_trip_and_sentinels() -> None:
    r = bc.BatteryReport(24.51, -3.2, 3.901, 4.1, 25.3, math.nan, 0.55, True, False, True,
                         5.0, 2.75, math.nan, (4.01, 4.02, 4.03, 4.04))  # fmt: skip
    frames = bc.encode_battery(3, r, 7)
    assert [f.arbitration_id for f in frames] == [0x303, 0x363, 0x313, 0x323, 0x333, 0x333]
    got: dict[str, float] = {}
    for f in frames:
        _kind, i, vals = bc.decode(f)
        assert i == 3
        got.update(vals)
    assert got["Voltage"] == pytest.approx(24.51)
    assert got["Current"] == pytest.approx(-3.2)
    assert math.isnan(got["TempMin"]) and math.isnan(got["CycleCount"])
    assert math.isnan(got["GroupV5"])  # beyond the battery's 4 groups
    assert got["GroupV3"] == pytest.approx(4.04)
    assert (got["ChgOn"], got["DsgOn"], got["Present"]) == (1, 0, 1)
    # out of range stays out of range (clamped one count short of "not available")
    hot = bc.encode_battery(0, dataclasses.replace(r, max_cell_v=99.0), 0)
    assert bc.decode(hot[1])[2]["MaxCellV"] == pytest.approx(6.5534)


@pytest.mark.parametrize(
    "msg",
    [
        can.Message(arbitration_id=0x300, is_extended_id=False, data=bytes(7)),  # wrong DLC
        can.Message(arbitration_id=0x300, is_extended_id=True, data=bytes(8)),  # 29-bit
        can.Message(arbitration_id=0x3F0, is_extended_id=False, data=bytes(8)),  # unknown
        can.Message(arbitration_id=0x300, is_extended_id=False, is_remote_frame=True, dlc=8),
        can.Message(arbitration_id=0x300, is_extended_id=False, is_error_frame=True),
    ],
)
def test_battery_codec_is_strict(msg: can.Message) -> None:
    with pytest.raises(FrameError):
        bc.decode(msg)


def test_dronecan_battery_info_round_trip() -> None:
    info = dc.BatteryInfo(battery_id=2, voltage_v=49.8, current_a=-12.5, temp_c=31.0,
                          soc_pct=64, soh_pct=97, remaining_wh=120.0, full_wh=190.0,
                          status_flags=dc.IN_USE | dc.CHARGING,
                          model_name="PackPilot-1")  # fmt: skip
    frames = dc.encode(info, node_id=100, transfer_id=5)
    assert len(frames) > 1 and all(f.is_extended_id for f in frames)
    assert all((f.arbitration_id >> 8) & 0xFFFF == dc.BATTERY_INFO_ID for f in frames)
    back = dc.decode(frames)
    assert back.voltage_v == pytest.approx(49.8125)  # float16 rounding
    assert back.current_a == pytest.approx(-12.5)
    assert back.temp_c == pytest.approx(31.0, abs=0.2)
    assert (back.battery_id, back.soc_pct, back.soh_pct) == (2, 64, 97)
    assert back.status_flags == dc.IN_USE | dc.CHARGING
    assert back.model_name == "PackPilot-1"
    unknown = dc.decode(dc.encode(dc.BatteryInfo(0, 1.0, 0.0, 20.0, 50), 100, 0))
    assert math.isnan(unknown.soh_pct)  # 127 = unknown


def test_dronecan_cells_carry_the_nominal_voltage() -> None:
    """BatteryInfoAux's nominal voltage converts BatteryInfo's Wh to Ah; 0 means "omit the
    conversion" (the DSDL), and so does an unknown Wh."""
    cells = dc.BatteryCells(battery_id=3, cell_v=(3.9, 3.91), cycle_count=7,
                            nominal_voltage_v=22.25)  # fmt: skip
    back = dc.decode_any(dc.encode_cells(cells, node_id=12, transfer_id=1))
    assert isinstance(back, dc.BatteryCells)
    assert (back.battery_id, back.cycle_count, back.nominal_voltage_v) == (3, 7, 22.25)
    assert back.cell_v == pytest.approx((3.9, 3.91), abs=0.002)
    assert dc.ah_from_wh(111.25, 22.25) == 5.0
    assert math.isnan(dc.ah_from_wh(111.25, 0.0))
    assert math.isnan(dc.ah_from_wh(math.nan, 22.25))
    assert math.isnan(dc.ah_from_wh(-1.0, 22.25))
