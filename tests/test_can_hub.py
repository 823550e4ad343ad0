"""The loopback CAN hub (``io/can/hub.py``) with python-can's own ``socketcand`` client and raw
sockets, all on 127.0.0.1: framing both ways, no echo, channels, bad input, the join rule that
keeps python-can's handshake readable, a stalled client, the loopback-only bind; and
``--can-arg``."""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import can
import pytest

from packpilot.errors import ConfigError
from packpilot.io.can.bus import open_bus, parse_bus_args
from packpilot.io.can.client import FrameCounters, received
from packpilot.io.can.hub import (
    CanHub,
    Frame,
    check_bind,
    format_frame,
    parse_send,
    split_messages,
)
from packpilot.runtime.bms import filters
from packpilot.runtime.lockstep import REQUEST_ONLY
from tests.conftest import EXAMPLES

CLI = [sys.executable, "-m", "packpilot.cli"]


@pytest.fixture
def hub() -> Iterator[CanHub]:
    with CanHub("127.0.0.1", 0) as h:
        yield h


def client(hub: CanHub, channel: str = "pack") -> can.BusABC:
    return open_bus("socketcand", channel, host=hub.host, port=hub.port)


def joined(hub: CanHub) -> None:
    """Wait until the clients that have not sent yet have joined (the hub's join delay after
    their handshake)."""
    time.sleep(hub.join_delay_s + 0.1)


def raw(hub: CanHub, channel: str = "pack", *, rcvbuf: int | None = None) -> socket.socket:
    """A hand-driven client through the handshake, each reply read alone."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    if rcvbuf is not None:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    s.settimeout(5.0)
    s.connect((hub.host, hub.port))
    assert s.recv(256) == b"< hi >"
    s.sendall(f"< open {channel} >".encode())
    assert s.recv(256) == b"< ok >"
    s.sendall(b"< rawmode >")
    assert s.recv(256) == b"< ok >"
    return s


FRAMES = [
    can.Message(arbitration_id=0x123, data=b"\x01\x02\xab", is_extended_id=False),
    can.Message(arbitration_id=0x7FF, data=bytes(range(8)), is_extended_id=False),
    can.Message(arbitration_id=0x000, data=b"", is_extended_id=False),
    can.Message(arbitration_id=0x1806E5F4, data=b"\xff" * 8, is_extended_id=True),
    can.Message(arbitration_id=0x00000005, data=b"", is_extended_id=True),
]


def same(a: can.Message, b: can.Message) -> bool:
    return (a.arbitration_id, a.is_extended_id, bytes(a.data)) == (
        b.arbitration_id, b.is_extended_id, bytes(b.data))  # fmt: skip


def test_frames_pass_both_ways_with_python_can(hub: CanHub) -> None:
    """Standard and extended ids, 0 to 8 bytes, A → B and B → A, stamped with wall time."""
    a, b = client(hub), client(hub)
    try:
        joined(hub)
        for sender, receiver in ((a, b), (b, a)):
            before = time.time()
            for msg in FRAMES:
                sender.send(msg)
            got = [receiver.recv(2.0) for _ in FRAMES]
            assert all(m is not None for m in got)
            assert all(same(m, f) for m, f in zip(got, FRAMES, strict=True))
            assert all(before - 0.01 <= m.timestamp <= time.time() for m in got)
    finally:
        a.shutdown()
        b.shutdown()
    assert hub.stats.frames_in == hub.stats.frames_out == 2 * len(FRAMES)
    assert hub.stats.malformed == 0


def test_a_frame_is_not_echoed_and_stays_on_its_channel(hub: CanHub) -> None:
    a, b, other = client(hub), client(hub), client(hub, "other")
    try:
        joined(hub)
        a.send(FRAMES[0])
        assert same(b.recv(2.0), FRAMES[0])
        assert a.recv(0.3) is None  # not back to its sender
        assert other.recv(0.1) is None  # not to another channel
    finally:
        for bus in (a, b, other):
            bus.shutdown()
    assert hub.stats.frames_out == 1


def test_the_wire_format_is_socketcand_raw_mode(hub: CanHub) -> None:
    """What the hub sends, byte for byte: 3 / 8 hex digit ids, data as one hex string (two
    spaces before ``>`` when empty), seconds.microseconds."""
    rx = raw(hub)
    tx = raw(hub)
    joined(hub)
    tx.sendall(b"< send 123 3 1 a2 ff >< send 1806E5F4 0  >")
    data = b""
    while data.count(b">") < 2:
        data += rx.recv(4096)
    first, second = data.decode().split(">")[:2]
    assert first.startswith("< frame 123 ") and first.endswith(" 01A2FF ")
    assert second.startswith("< frame 1806E5F4 ") and second.endswith("  ")
    stamp = float(first.split()[3])
    assert abs(stamp - time.time()) < 5.0 and len(first.split()[3].split(".")[1]) == 6
    assert parse_send(["send", "5", "0"]) == Frame(5, False, b"")
    assert format_frame(Frame(5, False, b""), 12.5) == "< frame 005 12.500000  >"
    assert format_frame(Frame(5, True, b"\x07"), 0.0) == "< frame 00000005 0.000000 07 >"
    rx.close()
    tx.close()


BAD = [
    b"hello",  # text outside < >
    b"< send 123 2 01 >",  # fewer bytes than LEN
    b"< send 123 1 01 02 >",  # more
    b"< send XYZ 1 00 >",  # not hex
    b"< send 1234 0 >",  # neither 3 nor 8 digits
    b"< send 800 0 >",  # beyond 11 bits
    b"< send 20000000 0 >",  # beyond 29 bits
    b"< send 123 9 0 0 0 0 0 0 0 0 0 >",  # more than 8 bytes
    b"< send 123 1 100 >",  # a byte of 3 digits
    b"< send 123 1 \xff >",  # not ASCII
    b"< bogus >",
    b"< send 123 1 <",  # cut short by the next message
]


def test_malformed_input_is_counted_and_skipped(hub: CanHub) -> None:
    rx = client(hub)
    tx = raw(hub)
    try:
        joined(hub)
        for line in BAD:
            tx.sendall(line)
        tx.sendall(b"< send 321 1 42 >")
        got = rx.recv(2.0)
        assert got is not None and got.arbitration_id == 0x321 and bytes(got.data) == b"\x42"
        assert rx.recv(0.3) is None  # nothing else came through
        assert hub.stats.malformed == len(BAD)
        assert hub.stats.frames_in == 1
        late = client(hub)  # the hub still serves
        late.shutdown()
    finally:
        rx.shutdown()
        tx.close()


def test_an_unfinished_message_longer_than_any_is_dropped() -> None:
    bodies, rest, junk = split_messages("< send 1 0 >< send " + "0 " * 200)
    assert bodies == [" send 1 0 "] and rest == "" and junk == 1
    bodies, rest, junk = split_messages("< send 1 0 >< send 2")
    assert bodies == [" send 1 0 "] and rest == "< send 2" and junk == 0


def test_a_bad_channel_name_fails_the_open_with_the_hubs_reason(hub: CanHub) -> None:
    with pytest.raises(ConfigError, match="expected: open CHANNEL"):
        client(hub, "bad/name")
    assert hub.stats.malformed == 1


def test_handshake_replies_arrive_alone_while_the_channel_is_busy() -> None:
    """python-can reads each reply with one recv() and compares it exactly: a frame must not
    come glued to the last ``< ok >``. A new client gets frames only after the join delay (or
    once it sent one), so a client slow to read its ``< ok >`` still reads it alone."""
    with CanHub("127.0.0.1", 0, join_delay_s=1.0) as hub:
        talker = raw(hub)
        talker.sendall(b"< send 100 0  >")  # the talker joined: it sent
        s = socket.create_connection((hub.host, hub.port), timeout=5.0)
        assert s.recv(256) == b"< hi >"
        s.sendall(b"< open pack >")
        assert s.recv(256) == b"< ok >"
        s.sendall(b"< rawmode >")
        for _ in range(20):  # traffic while the client dawdles
            talker.sendall(b"< send 101 1 1 >")
            time.sleep(0.01)
        assert s.recv(256) == b"< ok >"
        s.sendall(b"< send 102 0  >")  # it sent: it reads frames from now on
        time.sleep(0.1)
        talker.sendall(b"< send 103 0  >")
        assert s.recv(256).startswith(b"< frame 103 ")
        assert talker.recv(256).startswith(b"< frame 102 ")
        s.close()
        talker.close()


def test_a_listener_joins_after_the_delay() -> None:
    with CanHub("127.0.0.1", 0, join_delay_s=0.3) as hub:
        talker, listener = raw(hub), raw(hub)
        talker.sendall(b"< send 111 0  >")  # before the listener's delay: not for it
        time.sleep(0.5)
        talker.sendall(b"< send 222 0  >")
        assert listener.recv(256).startswith(b"< frame 222 ")
        talker.close()
        listener.close()


def test_a_stalled_client_loses_frames_the_others_do_not() -> None:
    """Memory stays bounded: beyond its queue a client that does not read is skipped."""
    with CanHub("127.0.0.1", 0, max_pending_bytes=4096, bitrate=0) as hub:  # no rate cap
        stalled = raw(hub, rcvbuf=4096)
        reader = client(hub)
        tx = raw(hub)
        joined(hub)
        sent = got = 0
        try:
            while hub.stats.dropped == 0 and sent < 200_000:
                tx.sendall(b"< send 123 8 1 2 3 4 5 6 7 8 >" * 100)
                sent += 100
                while reader.recv(0.0) is not None:
                    got += 1
            while reader.recv(0.5) is not None:
                got += 1
            assert hub.stats.dropped > 0
            assert got == sent == hub.stats.frames_in  # the reader lost nothing
        finally:
            stalled.close()
            reader.shutdown()
            tx.close()


def test_a_client_cannot_send_more_than_the_bus_carries() -> None:
    """Issue #26, real time: a babbling client wrote 15,000 frames/s over TCP and, the hub
    forwarding in arrival order, the telemetry waited behind seconds of its frames in every
    other client's queue. A node on a real 500 kbit/s bus cannot send more than its bitrate
    (and arbitration favours the telemetry): beyond 500 kbit/s (plus a 0.1 s burst) a
    client's frames are refused and counted, another client's frames all pass."""
    with CanHub("127.0.0.1", 0) as hub:
        reader = client(hub)
        flood, node = raw(hub), raw(hub)
        joined(hub)
        try:
            t0 = time.monotonic()
            for _ in range(20):
                flood.sendall(b"< send 7F0 8 0 0 0 0 0 0 0 0 >" * 1000)  # 20,000 frames
                node.sendall(b"< send 300 8 1 2 3 4 5 6 7 8 >")
            elapsed = time.monotonic() - t0
            got: dict[int, int] = {}
            while (m := reader.recv(0.5)) is not None:
                got[m.arbitration_id] = got.get(m.arbitration_id, 0) + 1
            allowed = 500_000 * (0.1 + elapsed + 0.5) / 111  # burst + what the time allowed
            assert got[0x300] == 20  # the well-behaved node lost nothing
            assert got[0x7F0] <= allowed and got[0x7F0] + hub.stats.throttled == 20_000
            assert hub.stats.throttled > 10_000
        finally:
            reader.shutdown()
            flood.close()
            node.close()


def test_a_client_that_never_reads_its_replies_is_disconnected_and_memory_stays_bounded() -> None:
    """Issue #26: a client that sends without ever reading grew the hub without bound (its
    ``< error >`` replies were queued unconditionally: 190 MB in 13 s). Every byte for a client
    now goes through one send queue capped at ``max_pending_bytes``; replies it does not read
    disconnect it, while a well-behaved client on the same hub is served throughout."""
    with CanHub("127.0.0.1", 0, max_pending_bytes=4096) as hub:
        reader = client(hub)
        tx = raw(hub)
        joined(hub)
        junk = socket.socket()
        junk.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        junk.connect(("127.0.0.1", hub.port))
        junk.settimeout(5)
        peak = 0
        try:
            with pytest.raises(OSError):  # reset by the hub
                for _ in range(2000):
                    junk.sendall(b"< x >" * 2000)  # each one answered '< error ... >'
                    queued = [c.writer.transport.get_write_buffer_size() for c in hub._clients]
                    peak = max(peak, *queued)
            assert hub.stats.disconnected == 1
            assert peak <= 4096 + 256
            tx.sendall(b"< send 123 1 AA >")
            got = reader.recv(2.0)
            assert got is not None and got.arbitration_id == 0x123  # the others still served
        finally:
            junk.close()
            reader.shutdown()
            tx.close()


def test_receivers_on_socketcand_get_every_pending_frame_in_one_drain(hub: CanHub) -> None:
    """python-can filters ``socketcand`` in software and its ``recv(timeout=0)`` gives up at
    the first frame a filter drops, so the runtime passes no filter there (as on
    ``virtual``): one drain reads every pending frame and the receiver classifies them."""
    rx = open_bus("socketcand", "pack", host=hub.host, port=hub.port,
                  **filters("socketcand", REQUEST_ONLY))  # fmt: skip
    tx = raw(hub)
    try:
        joined(hub)
        tx.sendall(b"< send 123 0  >" * 5 + b"< send 1806E5F4 8 0 0 0 0 0 0 0 0 >")
        time.sleep(0.3)
        got = list(received(rx, FrameCounters(), None, 0.0))
        assert [m.arbitration_id for m in got] == [0x123] * 5 + [0x1806E5F4]
    finally:
        rx.shutdown()
        tx.close()


def test_a_non_loopback_bind_is_refused_unless_allowed() -> None:
    """No socket is opened for a refused address (192.0.2.1 is TEST-NET-1)."""
    for host in ("192.0.2.1", "0.0.0.0", "example.invalid"):
        with pytest.raises(ConfigError, match="--allow-remote"):
            CanHub(host, 0)
    for host in ("127.0.0.1", "localhost", "127.0.0.2"):
        check_bind(host, allow_remote=False)
    check_bind("0.0.0.0", allow_remote=True)  # explicit: allowed (not bound here)


def test_a_busy_port_is_one_line(hub: CanHub) -> None:
    with pytest.raises(ConfigError, match=f"cannot listen on 127.0.0.1:{hub.port}"):
        CanHub("127.0.0.1", hub.port).start()


# ---------------------------------------------------------------------- the command line
def test_can_hub_command_serves_and_stops_on_sigterm() -> None:
    proc = subprocess.Popen([*CLI, "can-hub", "--port", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        assert line.startswith("can-hub on 127.0.0.1:"), line
        port = int(line.split()[2].rsplit(":", 1)[1])
        a = open_bus("socketcand", "x", host="127.0.0.1", port=port)
        b = open_bus("socketcand", "x", host="127.0.0.1", port=port)
        time.sleep(0.3)
        a.send(FRAMES[3])
        assert same(b.recv(2.0), FRAMES[3])
        a.shutdown()
        b.shutdown()
        proc.send_signal(signal.SIGTERM)
        _out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    assert "connections 2, frames_in 1, frames_out 1, malformed 0, dropped 0" in err


def test_can_hub_command_refuses_a_remote_host() -> None:
    proc = subprocess.run([*CLI, "can-hub", "--host", "192.0.2.1", "--port", "0"],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1
    assert "--allow-remote" in proc.stderr


def test_can_args_are_typed() -> None:
    got = parse_bus_args(["host=127.0.0.1", "port=29536", "tcp_tune=true", "bitrate=5e5",
                          "mask=0x7FF", "name=can0", "fd=False", "empty="])  # fmt: skip
    assert got == {"host": "127.0.0.1", "port": 29536, "tcp_tune": True, "bitrate": 500000.0,
                   "mask": 0x7FF, "name": "can0", "fd": False, "empty": ""}  # fmt: skip
    assert type(got["port"]) is int and type(got["bitrate"]) is float


@pytest.mark.parametrize(
    ("item", "why"),
    [("bitrate", "expected KEY=VALUE"), ("=5", "expected KEY=VALUE"),
     ("1a=2", "expected KEY=VALUE"), ("channel=x", "not an interface option"),
     ("can_filters=x", "not an interface option")],
)  # fmt: skip
def test_bad_can_args_are_refused(item: str, why: str) -> None:
    with pytest.raises(ConfigError, match=why):
        parse_bus_args([item])
    with pytest.raises(ConfigError, match="given twice"):
        parse_bus_args(["port=1", "port=2"])


@pytest.mark.parametrize("command", ["run", "hil"])
def test_a_malformed_can_arg_is_one_line(command: str) -> None:
    proc = subprocess.run([*CLI, command, str(EXAMPLES / "uav_mission.toml"), "--can-interface",
                           "virtual", "--can-arg", "bitrate", "--duration", "0.1"],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: --can-arg 'bitrate': expected KEY=VALUE, e.g. bitrate=500000"
    ]


def test_a_missing_interface_option_is_one_line() -> None:
    with pytest.raises(ConfigError, match=r"host.*--can-arg KEY=VALUE"):
        open_bus("socketcand", "pack")


def test_can_args_reach_the_bus(hub: CanHub) -> None:
    """``run --can-arg`` options open the bus: a run of 0.3 s against the hub (no pack there:
    it fails safe) connected, on the batteries' and the charger's channels."""
    proc = subprocess.run([*CLI, "run", str(EXAMPLES / "uav_mission.toml"), "--can-interface",
                           "socketcand", "--can-channel", "pack", "--charger-channel", "chg",
                           "--can-arg", "host=127.0.0.1", "--can-arg", f"port={hub.port}",
                           "--duration", "0.3", "--json"],
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["can_sent"] > 0
    assert hub.stats.connections == 2
    assert hub.stats.frames_in > 0 and hub.stats.malformed == 0
