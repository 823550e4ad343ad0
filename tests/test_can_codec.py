"""TC/Elcon frames: golden vectors, DBC layout, every status flag, strict decoding."""

from __future__ import annotations

import math

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.charger import ChargerCommand
from packpilot.io.can import (
    FLAG_NAMES,
    REQUEST_ID,
    STATUS_ID,
    ChargerFlags,
    FrameError,
    database,
    decode_request,
    decode_status,
    encode_request,
    encode_status,
)
from tests.budget import budget


def test_golden_request_vectors() -> None:
    on = encode_request(ChargerCommand(98.0, 16.0, enable=True))
    assert bytes(on.data) == bytes.fromhex("03 D4 00 A0 00 00 00 00")
    off = encode_request(ChargerCommand(320.1, 58.2, enable=False))
    assert bytes(off.data) == bytes.fromhex("0C 81 02 46 01 00 00 00")
    for msg in (on, off):
        assert msg.arbitration_id == 0x1806E5F4 and msg.is_extended_id and msg.dlc == 8
    req = decode_request(off)
    assert (req.voltage_v, req.current_a, req.enable, req.mode) == (320.1, 58.2, False, 0)
    assert decode_request(on).voltage_v == 98.0


def test_dbc_layout_is_big_endian_29_bit() -> None:
    db = database()
    req = db.get_message_by_frame_id(REQUEST_ID)
    sta = db.get_message_by_frame_id(STATUS_ID)
    assert req.is_extended_frame and sta.is_extended_frame
    for msg in (req, sta):
        for sig in msg.signals:
            if sig.length == 16:
                assert sig.byte_order == "big_endian" and sig.scale == 0.1, sig.name
    # byte 4 bits 0..4 in the documented order
    bits = [
        sta.get_signal_by_name(n).start
        for n in (
            "HardwareFailure",
            "OverTemperature",
            "InputVoltageFault",
            "BatteryNotDetected",
            "CommunicationTimeout",
        )
    ]
    assert bits == [32, 33, 34, 35, 36]


def test_status_decode_values_and_no_flags() -> None:
    msg = can.Message(
        arbitration_id=STATUS_ID, is_extended_id=True, data=bytes.fromhex("0C81024600000000")
    )
    s = decode_status(msg)
    assert (s.output_v, s.output_a, s.online, s.faulted, s.communication_timeout) == (
        320.1,
        58.2,
        True,
        False,
        False,
    )


@pytest.mark.parametrize("bit", range(5))
def test_each_status_flag_decodes(bit: int) -> None:
    data = bytes([0x03, 0xD4, 0x00, 0xA0, 1 << bit, 0, 0, 0])
    s = decode_status(can.Message(arbitration_id=STATUS_ID, is_extended_id=True, data=data))
    got = {name: getattr(s, name) for name in FLAG_NAMES}
    assert got == {name: k == bit for k, name in enumerate(FLAG_NAMES)}
    # and the encoder puts it back in the same bit
    enc = encode_status(98.0, 16.0, {FLAG_NAMES[bit]: True})
    assert bytes(enc.data) == data


def test_flags_from_attributes_and_unknown_keys() -> None:
    flags = ChargerFlags(over_temperature=True)
    assert bytes(encode_status(0.0, 0.0, flags).data)[4] == 0b10
    with pytest.raises(ValueError, match="unknown charger flag"):
        ChargerFlags.of({"on_fire": True})


def test_non_finite_or_out_of_range_requests_fail_safe() -> None:
    assert bytes(encode_request(ChargerCommand(math.nan, 10.0)).data) == bytes.fromhex(
        "0000000001000000"
    )
    clamp = decode_request(encode_request(ChargerCommand(1e6, -5.0)))
    assert (clamp.voltage_v, clamp.current_a) == (6553.5, 0.0)


@pytest.mark.parametrize(
    ("msg", "fragment"),
    [
        (can.Message(arbitration_id=STATUS_ID, is_extended_id=True, data=b"\x01\x02\x03"), "DLC"),
        (can.Message(arbitration_id=STATUS_ID, is_extended_id=False, data=bytes(8)), "standard"),
        (can.Message(arbitration_id=0x123, is_extended_id=True, data=bytes(8)), "0x123"),
        (
            can.Message(arbitration_id=STATUS_ID, is_extended_id=True, is_remote_frame=True, dlc=8),
            "remote",
        ),
        (can.Message(is_error_frame=True), "error"),
    ],
)
def test_bad_status_frames_raise_frame_error(msg: can.Message, fragment: str) -> None:
    with pytest.raises(FrameError, match=fragment):
        decode_status(msg)


@pytest.mark.parametrize(("byte", "value", "fragment"), [(4, 7, "control"), (5, 1, "mode")])
def test_bad_request_enumerations(byte: int, value: int, fragment: str) -> None:
    data = bytearray(encode_request(ChargerCommand(98.0, 16.0)).data)
    data[byte] = value
    msg = can.Message(arbitration_id=REQUEST_ID, is_extended_id=True, data=bytes(data))
    with pytest.raises(FrameError, match=fragment):
        decode_request(msg)


@budget(200)
@given(
    v=st.integers(min_value=0, max_value=0xFFFF),
    i=st.integers(min_value=0, max_value=0xFFFF),
    enable=st.booleans(),
)
def test_request_roundtrip_exact(v: int, i: int, enable: bool) -> None:
    cmd = ChargerCommand(v / 10, i / 10, enable)
    msg = encode_request(cmd)
    assert bytes(msg.data[:4]) == v.to_bytes(2, "big") + i.to_bytes(2, "big")
    req = decode_request(msg)
    assert (req.voltage_v, req.current_a, req.enable) == (v / 10, i / 10, enable)
