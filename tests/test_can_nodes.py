"""Charger client and emulator talking over a real python-can virtual bus, in simulated time."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import pytest

from packpilot.contract.charger import ChargerCommand, ChargerStatus
from packpilot.errors import ConfigError
from packpilot.io.can import (
    REQUEST_ID,
    SIM_EPOCH_S,
    STATUS_ID,
    ChargerClient,
    ChargerEmulator,
    ChargerFlags,
    FrameLog,
    encode_request,
    encode_status,
    open_bus,
)

_channels = itertools.count()


@dataclass
class FakeCharger:
    """Minimal ChargerPlant: CC/CV into a fixed 90 V battery, 5 s heartbeat timeout."""

    heartbeat_timeout_s: float = 5.0
    flags: dict[str, bool] = field(default_factory=dict)
    requests: list[tuple[float, float, float, bool]] = field(default_factory=list)
    now: float = 0.0

    def request(self, voltage_v: float, current_a: float, enable: bool, t_s: float) -> None:
        self.requests.append((t_s, voltage_v, current_a, enable))

    def live(self) -> bool:
        if not self.requests:
            return False
        t, _, _, enable = self.requests[-1]
        return enable and self.now - t <= self.heartbeat_timeout_s and not any(self.flags.values())

    def output(self) -> tuple[float, float]:
        if not self.live():
            return 0.0, 0.0
        _, v, i, _ = self.requests[-1]
        return v, min(i, max(0.0, (v - 90.0) / 0.1))

    @property
    def fault_flags(self) -> dict[str, bool]:
        return dict(self.flags)


@pytest.fixture
def buses() -> Iterator[tuple[can.BusABC, can.BusABC, can.BusABC]]:
    """BMS bus, charger bus and a third 'intruder' node on one fresh virtual channel."""
    channel = f"test-can-{next(_channels)}"
    nodes = [open_bus("virtual", channel) for _ in range(3)]
    yield nodes[0], nodes[1], nodes[2]
    for b in nodes:
        b.shutdown()


def run(
    client: ChargerClient | None,
    emu: ChargerEmulator,
    fake: FakeCharger,
    t0: float,
    t1: float,
    dt: float = 0.1,
) -> list[tuple[float, ChargerStatus | None]]:
    """Step both nodes from t0 to t1 (client skipped when None = a hung BMS loop)."""
    seen = []
    for k in range(round((t1 - t0) / dt)):
        t = round(t0 + k * dt, 9)
        fake.now = t
        status = client.poll(t) if client is not None else None
        emu.poll(t)
        seen.append((t, status))
    return seen


def test_exchange_in_simulated_time(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, _ = buses
    fake = FakeCharger()
    client = ChargerClient(bms)
    emu = ChargerEmulator(chg, fake)
    client.set_request(ChargerCommand(98.0, 16.0, enable=True))
    seen = run(client, emu, fake, 0.0, 10.0)
    # one request per simulated second (0, 1, ..., 9), forwarded with the decoded values
    assert [round(r[0], 6) for r in fake.requests] == [float(k) for k in range(10)]
    assert all(r[1:] == (98.0, 16.0, True) for r in fake.requests)
    assert client.counters.sent == 10 and emu.counters.received == 10
    assert emu.counters.sent == 10 and client.counters.received == 10
    last = seen[-1][1]
    assert last is not None and last.online and (last.output_v, last.output_a) == (98.0, 16.0)
    assert client.counters.malformed == client.counters.unexpected == 0


def test_status_none_then_offline(buses: tuple[can.BusABC, ...]) -> None:
    bms, _, _ = buses
    client = ChargerClient(bms, status_timeout_s=3.0)
    assert client.poll(0.0) is None
    assert client.poll(3.0) is None
    off = client.poll(3.5)
    assert off is not None and not off.online and math.isnan(off.output_v)


def test_stopped_heartbeat_drops_output_and_reports_timeout(
    buses: tuple[can.BusABC, ...],
) -> None:
    bms, chg, _ = buses
    fake = FakeCharger()
    client = ChargerClient(bms, status_timeout_s=5.0)
    emu = ChargerEmulator(chg, fake)
    client.set_request(ChargerCommand(98.0, 16.0, enable=True))
    run(client, emu, fake, 0.0, 10.0)
    last_request = fake.requests[-1][0]
    # the BMS loop hangs: nobody polls the client, the charger node keeps running
    run(None, emu, fake, 10.0, 20.0)
    assert fake.requests[-1][0] == last_request  # no request reached the plant
    assert fake.output() == (0.0, 0.0)  # plant's own timeout switched the output off
    assert emu.heartbeat_lost(20.0)
    # the loop resumes: first it reads the statuses queued meanwhile, incl. the timeout bit
    status = client.poll(20.0)
    assert status is not None and status.communication_timeout and status.output_a == 0.0
    seen = run(client, emu, fake, 20.0, 23.0)
    final = seen[-1][1]
    assert final is not None and not final.communication_timeout and final.output_a == 16.0


def test_charger_silence_marks_offline(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, _ = buses
    fake = FakeCharger()
    client = ChargerClient(bms, status_timeout_s=2.0)
    emu = ChargerEmulator(chg, fake)
    run(client, emu, fake, 0.0, 5.0)
    statuses = [client.poll(5.0 + 0.5 * k) for k in range(8)]  # charger node stopped
    assert statuses[0] is not None and statuses[0].online
    assert statuses[-1] is not None and not statuses[-1].online


def test_fault_flag_travels(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, _ = buses
    fake = FakeCharger(flags={"over_temperature": True})
    client = ChargerClient(bms)
    emu = ChargerEmulator(chg, fake)
    client.set_request(ChargerCommand(98.0, 16.0))
    seen = run(client, emu, fake, 0.0, 2.0)
    st = seen[-1][1]
    assert st is not None and st.over_temperature and st.faulted and st.output_a == 0.0


def test_malformed_frames_counted_and_ignored(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, intruder = buses
    fake = FakeCharger()
    client = ChargerClient(bms)
    emu = ChargerEmulator(chg, fake)
    client.set_request(ChargerCommand(98.0, 16.0))
    run(client, emu, fake, 0.0, 1.0)
    good_status = encode_status(50.0, 1.0, {})
    good_request = encode_request(ChargerCommand(10.0, 1.0))
    bad = [
        can.Message(arbitration_id=STATUS_ID, is_extended_id=True, data=b"\x01\x02"),  # DLC
        can.Message(arbitration_id=REQUEST_ID, is_extended_id=True, data=b"\x01"),  # DLC
        can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)),  # garbage ID
        can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True, data=bytes(8)),  # unknown
        can.Message(arbitration_id=STATUS_ID, is_extended_id=False, data=good_status.data),
        can.Message(arbitration_id=REQUEST_ID, is_extended_id=False, data=good_request.data),
        can.Message(arbitration_id=STATUS_ID, is_extended_id=True, is_remote_frame=True, dlc=8),
        can.Message(
            arbitration_id=REQUEST_ID,
            is_extended_id=True,
            data=bytes.fromhex("03D400A007000000"),  # control byte 7
        ),
    ]
    for msg in bad:
        intruder.send(msg)
    n_req = len(fake.requests)
    seen = run(client, emu, fake, 1.0, 3.0)
    # client: short status = malformed; 0x7FF, unknown ext, std-status, std-request, remote,
    # and the intruder's two request-ID frames (short, bad control) are not for it
    assert client.counters.malformed == 1
    assert client.counters.unexpected == 7
    # emulator: short request and control-7 request malformed; 0x7FF, unknown, std-status,
    # std-request, remote and the short status are unexpected
    assert emu.counters.malformed == 2
    assert emu.counters.unexpected == 6
    # nothing bogus was forwarded, the real traffic carried on
    assert all(r[1:] == (98.0, 16.0, True) for r in fake.requests[n_req:])
    assert len(fake.requests) == n_req + 2
    final = seen[-1][1]
    assert final is not None and final.online and final.output_v == 98.0


def test_plant_flags_as_attributes_or_unreadable(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, _ = buses

    class AttrCharger(FakeCharger):
        @property
        def fault_flags(self) -> ChargerFlags:  # type: ignore[override]
            return ChargerFlags(input_voltage_fault=True)

    class BadCharger(FakeCharger):
        @property
        def fault_flags(self) -> dict[str, bool]:
            return {"mystery": True}

    for plant, flag in ((AttrCharger(), "input_voltage_fault"), (BadCharger(), "hardware_failure")):
        client = ChargerClient(bms)
        emu = ChargerEmulator(chg, plant)
        seen = run(client, emu, plant, 0.0, 1.0)
        st = seen[-1][1]
        assert st is not None and getattr(st, flag)
        for b in (bms, chg):
            while b.recv(timeout=0.0) is not None:
                pass


@pytest.mark.parametrize("suffix", [".blf", ".asc"])
def test_frame_log_readable_with_sim_timestamps(
    buses: tuple[can.BusABC, ...], tmp_path: Path, suffix: str
) -> None:
    bms, chg, _ = buses
    fake = FakeCharger()
    path = tmp_path / f"frames{suffix}"
    with FrameLog(path) as log:
        client = ChargerClient(bms, log=log)
        emu = ChargerEmulator(chg, fake)
        client.set_request(ChargerCommand(98.0, 16.0))
        run(client, emu, fake, 100.0, 103.0)
    generic = list(can.LogReader(path))  # readable by python-can's generic reader
    assert len(generic) == 6
    frames = list(can.ASCReader(path, relative_timestamp=False)) if suffix == ".asc" else generic
    tx = [(m.timestamp - SIM_EPOCH_S, m.arbitration_id) for m in frames if not m.is_rx]
    rx = [(m.timestamp - SIM_EPOCH_S, m.arbitration_id) for m in frames if m.is_rx]
    assert [i for _, i in tx] == [REQUEST_ID] * 3
    assert [t for t, _ in tx] == pytest.approx([100.0, 101.0, 102.0], abs=1e-6)
    assert [i for _, i in rx] == [STATUS_ID] * 3
    assert all(100.0 - 1e-6 <= t < 103.0 for t, _ in rx)
    assert bytes(frames[0].data) == bytes.fromhex("03D400A000000000")
    assert frames[0].is_extended_id


def test_frame_log_rejects_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"use \.blf or \.asc"):
        FrameLog(tmp_path / "frames.txt")


def test_open_bus_errors_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="--can-interface nosuchbus"):
        open_bus("nosuchbus", "x")


def test_virtual_bus_does_not_echo_own_frames(buses: tuple[can.BusABC, ...]) -> None:
    bms, chg, _ = buses
    bms.send(encode_request(ChargerCommand(1.0, 1.0)))
    assert bms.recv(timeout=0.0) is None
    assert chg.recv(timeout=0.0) is not None
