"""A CAN hub on loopback speaking socketcand's raw mode: one CAN channel shared by processes.

Why: python-can's ``virtual`` interface reaches only within one process, and SocketCAN's
``vcan`` needs a kernel module that many machines and containers lack. socketcand's protocol
is text over TCP and python-can already has its client (the ``socketcand`` interface), so a
process joins the hub with ``--can-interface socketcand --can-arg host=127.0.0.1 --can-arg
port=N`` — and a real ``socketcand`` on a Linux box with a CAN adapter serves the same client
the same way. The protocol, as the client uses it (https://github.com/linux-can/socketcand)::

    hub → client   < hi >                             on connect
    client → hub   < open CHANNEL >          hub → < ok >
    client → hub   < rawmode >               hub → < ok >
    client → hub   < send ID LEN B0 B1 ... >          data bytes in hex, space-separated
    hub → client   < frame ID SEC.USEC HEXDATA >      data as one hex string

ID: 3 hex digits = 11-bit, 8 = 29-bit. A frame one client sends goes to every *other* client in
raw mode on the same channel (SocketCAN without ``recv_own_msgs``), stamped with the hub's wall
clock. python-can reads each handshake reply with one ``recv`` and compares it exactly, so a
reply goes out alone and only after the request it answers, and a client gets frames only once
it has shown it read its last ``< ok >`` (it sent a frame) or :data:`JOIN_DELAY_S` after that
``< ok >`` — a late joiner misses what went before, as a node plugged into a bus does.

Bad input never stops the hub: what does not parse (a message, bytes outside ``< >``) is
counted in :attr:`HubStats.malformed` and skipped; a bad handshake request is answered
``< error ... >`` (python-can fails its open with that text). A client that cannot keep up
loses frames (``dropped``), as a node with a full receive queue does, and a client that does
not read the hub's replies to its own requests (``< ok >``, ``< error >``; one that sent junk
without reading got 190 MB queued in 13 s) is disconnected (``disconnected``): every byte the
hub queues for a client goes through one send queue capped at ``max_pending_bytes``, so memory
stays bounded whatever a client does.

Security: the protocol has no authentication and whoever connects can put frames on the bus —
on a real pack, switch commands. So the hub listens on 127.0.0.1 and refuses any other address
unless ``allow_remote`` (``can-hub --allow-remote``) asks for it explicitly. IPv4 only: the
client is.
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import socket
import threading
import time
from dataclasses import asdict, dataclass, field

from packpilot.errors import ConfigError
from packpilot.io.net import resolves_to_loopback

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 29536
"""socketcand's port."""
JOIN_DELAY_S = 0.2
MAX_MESSAGE_CHARS = 256
"""A valid message is under 50 characters; a longer unfinished one is dropped as junk."""
DEFAULT_BITRATE = 500_000
"""bit/s a client's frames may take (``packpilot.dbc``'s bus): what one node can put on a
real bus at all."""
BURST_S = 0.1
"""Bus time a client may send in one burst beyond its rate (a period's telemetry at once)."""
MAX_PENDING_BYTES = 1 << 20
"""Output queued for one client beyond which frames to it are dropped (~25,000 frames)."""
READ_CHUNK = 1 << 16
_HEX = re.compile(r"[0-9A-Fa-f]+")
_CHANNEL = re.compile(r"[A-Za-z0-9_.-]{1,64}")


@dataclass(frozen=True, slots=True)
class Frame:
    can_id: int
    extended: bool
    data: bytes


@dataclass
class HubStats:
    """What went through the hub (read from any thread: plain counters)."""

    connections: int = 0
    frames_in: int = 0
    """Frames clients sent."""
    frames_out: int = 0
    """Frame deliveries (one frame to two other clients counts two)."""
    malformed: int = 0
    dropped: int = 0
    """Deliveries skipped because the receiving client was too far behind."""
    disconnected: int = 0
    """Clients closed because they did not read the replies to their own requests."""
    throttled: int = 0
    """Frames refused because their client sent more than the bus's bitrate carries."""

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def check_bind(host: str, allow_remote: bool) -> None:
    """Refuse a non-loopback address unless explicitly allowed (the protocol has no auth)."""
    if not allow_remote and not resolves_to_loopback(host):
        raise ConfigError(
            f"--host {host}: not a loopback address; the hub has no authentication and anyone"
            " who reaches it can send CAN frames (switch commands), so serving other machines"
            " needs --allow-remote"
        )


def parse_send(words: list[str]) -> Frame | None:
    """``send ID LEN B0 B1 ...`` (split into words) as a frame; None if it is not one."""
    if len(words) < 3 or words[0] != "send" or not all(_HEX.fullmatch(w) for w in words[1:]):
        return None
    ident, length, data = words[1], words[2], words[3:]
    can_id = int(ident, 16)
    extended = len(ident) == 8
    if not (can_id <= 0x1FFFFFFF if extended else len(ident) <= 3 and can_id <= 0x7FF):
        return None
    n = int(length, 16)
    if len(length) != 1 or n > 8 or len(data) != n or any(len(b) > 2 for b in data):
        return None
    return Frame(can_id, extended, bytes(int(b, 16) for b in data))


def format_frame(frame: Frame, t: float) -> str:
    """``frame`` as the hub sends it, stamped ``t`` (seconds since the epoch)."""
    ident = f"{frame.can_id:08X}" if frame.extended else f"{frame.can_id:03X}"
    sec, usec = divmod(round(t * 1e6), 1_000_000)
    return f"< frame {ident} {sec}.{usec:06d} {frame.data.hex().upper()} >"


def frame_bits(frame: Frame) -> int:
    """Bits ``frame`` occupies on a CAN bus: SOF, identifier, control, data, CRC, ACK, EOF and
    the interframe space (47 + 8 per byte standard, 67 + 8 per byte extended; bit stuffing,
    which depends on the content, left out: the rate is the bus's best case)."""
    return (67 if frame.extended else 47) + 8 * len(frame.data)


def split_messages(text: str) -> tuple[list[str], str, int]:
    """The insides of the complete ``< ... >`` messages of ``text``, the unfinished rest, and
    how many stretches of junk were skipped (text outside ``< >``, a message cut short by the
    next ``<``, an unfinished one longer than any message)."""
    bodies: list[str] = []
    junk = pos = 0
    while True:
        start = text.find("<", pos)
        if start < 0:
            return bodies, "", junk + bool(text[pos:].strip())
        junk += bool(text[pos:start].strip())
        end = text.find(">", start)
        if end < 0:
            rest = text[start:]
            if len(rest) > MAX_MESSAGE_CHARS:
                return bodies, "", junk + 1
            return bodies, rest, junk
        inner = text.rfind("<", start, end)
        junk += inner != start
        bodies.append(text[inner + 1 : end])
        pos = end + 1


def _ack_now(sock: socket.socket | None) -> None:
    """Acknowledge the client's data at once. python-can's client leaves Nagle on (unless
    ``tcp_tune``), so its second frame of a period waits for the first one's ACK, which a
    delayed ACK holds for ~40 ms; Linux's quick-ACK mode has to be re-armed after each read."""
    quickack = getattr(socket, "TCP_QUICKACK", None)
    if sock is not None and quickack is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, quickack, 1)


@dataclass(eq=False)
class _Client:
    writer: asyncio.StreamWriter
    channel: str | None = None
    raw: bool = False
    pending: str = field(default="", repr=False)
    bits: float = 0.0
    """Bus time the client may still use now (bits; a token bucket refilled at the bitrate)."""
    refilled: float = 0.0


class CanHub:
    """The hub, served by an asyncio loop in a thread of its own (:meth:`start`)."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        *,
        allow_remote: bool = False,
        join_delay_s: float = JOIN_DELAY_S,
        max_pending_bytes: int = MAX_PENDING_BYTES,
        bitrate: float = DEFAULT_BITRATE,
    ) -> None:
        """``bitrate``: bit/s one client may send (0: unlimited)."""
        check_bind(host, allow_remote)
        if not 0 <= port <= 65535:
            raise ConfigError(f"--port {port}: must be 0..65535 (0: any free port)")
        self.host, self.port, self.join_delay_s = host, port, join_delay_s
        self.max_pending_bytes = max_pending_bytes
        if not (bitrate == 0 or 1e3 <= bitrate <= 1e7):
            raise ConfigError(f"--bitrate {bitrate:g}: must be 0 (unlimited) or 1e3..1e7 bit/s")
        self.bitrate = float(bitrate)
        self.stats = HubStats()
        self._clients: set[_Client] = set()
        self._channels: dict[str, set[_Client]] = {}
        self._tasks: set[asyncio.Task[None]] = set()
        self._thread: threading.Thread | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._ready = threading.Event()

    # ------------------------------------------------------------------ lifetime
    def start(self) -> tuple[str, int]:
        """Listen (port 0: a free one) and serve in a thread; returns (host, port)."""
        try:
            sock = socket.create_server((self.host, self.port), family=socket.AF_INET)
        except OSError as err:
            raise ConfigError(
                f"can-hub: cannot listen on {self.host}:{self.port}: {err.strerror or err}"
            ) from None
        self.port = int(sock.getsockname()[1])
        self._thread = threading.Thread(target=asyncio.run, args=(self._serve(sock),),
                                        name="can-hub", daemon=True)  # fmt: skip
        self._thread.start()
        self._ready.wait()
        return self.host, self.port

    def wait(self) -> None:
        """Until the hub stops (Ctrl-C interrupts it in the main thread)."""
        while self._thread is not None and self._thread.is_alive():
            self._thread.join(0.5)

    def close(self) -> None:
        """Stop serving and disconnect every client."""
        if self._loop is not None and self._stop is not None:
            with contextlib.suppress(RuntimeError):  # the loop already ended
                self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(5.0)

    def __enter__(self) -> CanHub:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    async def _serve(self, sock: socket.socket) -> None:
        self._loop, self._stop = asyncio.get_running_loop(), asyncio.Event()
        try:
            server = await asyncio.start_server(self._serve_client, sock=sock)
        finally:
            self._ready.set()
        async with server:
            await self._stop.wait()
            for client in list(self._clients):
                client.writer.close()
            if self._tasks:  # each ends at its EOF: none is cancelled mid-read
                await asyncio.wait(self._tasks, timeout=2.0)

    # ------------------------------------------------------------------ one client
    async def _serve_client(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        client = _Client(writer)
        self._clients.add(client)
        task = asyncio.current_task()
        if task is not None:
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        self.stats.connections += 1
        self._reply(client, b"< hi >")
        sock = writer.get_extra_info("socket")
        try:
            while data := await reader.read(READ_CHUNK):
                _ack_now(sock)
                self._take(client, data.decode("latin-1"))
        except OSError:
            pass  # a reset connection is a client leaving
        finally:
            self._leave(client)
            writer.close()

    def _take(self, client: _Client, text: str) -> None:
        """What a client sent: requests answered, frames passed on, junk counted."""
        bodies, client.pending, junk = split_messages(client.pending + text)
        self.stats.malformed += junk
        frames = [f for body in bodies if (f := self._message(client, body.split())) is not None]
        if frames and self.bitrate > 0:
            frames = self._within_bitrate(client, frames)
        if frames:
            self._deliver(client, frames)

    def _within_bitrate(self, client: _Client, frames: list[Frame]) -> list[Frame]:
        """The frames of ``client`` a real bus at :attr:`bitrate` could have carried; the rest
        are refused and counted (``throttled``).

        A CAN node cannot put more on the bus than its bitrate, and on a saturated bus
        arbitration gives every slot to the highest-priority frame waiting, so a babbling
        low-priority node delays the others by one frame at most. The hub forwards in arrival
        order (no arbitration), so without this a client writing 15,000 frames/s over TCP
        buried the telemetry behind seconds of its frames in every other client's queue
        (issue #26, real-time flood: telemetry 10-20 s old at the BMS). Per client, not per
        channel: the well-behaved nodes' frames are never refused for another's flood."""
        now = time.monotonic()
        cap = self.bitrate * BURST_S
        if client.refilled == 0.0:
            client.bits = cap
        else:
            client.bits = min(cap, client.bits + (now - client.refilled) * self.bitrate)
        client.refilled = now
        keep = 0
        for f in frames:
            b = frame_bits(f)
            if b > client.bits:
                break
            client.bits -= b
            keep += 1
        self.stats.throttled += len(frames) - keep
        return frames[:keep] if keep < len(frames) else frames

    def _message(self, client: _Client, words: list[str]) -> Frame | None:
        if client.channel is None:
            self._open(client, words)
            return None
        if words == ["rawmode"] and not client.raw:
            client.raw = True
            self._reply(client, b"< ok >")
            if self._loop is not None:
                self._loop.call_later(self.join_delay_s, self._join, client)
            return None
        frame = parse_send(words)
        if frame is None:
            self.stats.malformed += 1
        return frame

    def _open(self, client: _Client, words: list[str]) -> None:
        if len(words) == 2 and words[0] == "open" and _CHANNEL.fullmatch(words[1]):
            client.channel = words[1]
            self._reply(client, b"< ok >")
            return
        self.stats.malformed += 1
        self._reply(client, b"< error expected: open CHANNEL (letters, digits, _ . -) >")

    def _join(self, client: _Client) -> None:
        """From now on ``client`` receives its channel's frames."""
        if client.raw and client.channel is not None and client in self._clients:
            self._channels.setdefault(client.channel, set()).add(client)

    def _deliver(self, sender: _Client, frames: list[Frame]) -> None:
        """``frames`` to every other client of the sender's channel, stamped now."""
        self._join(sender)  # it sent: it has read its last reply
        self.stats.frames_in += len(frames)
        assert sender.channel is not None
        peers = [c for c in self._channels.get(sender.channel, ()) if c is not sender]
        if not peers:
            return
        now = time.time()
        payload = "".join(format_frame(f, now) for f in frames).encode("ascii")
        for peer in peers:
            if peer.writer.transport.is_closing():
                continue
            if self._queued(peer) > self.max_pending_bytes:  # beyond by one payload at most
                self.stats.dropped += len(frames)
                continue
            self.stats.frames_out += len(frames)  # counted before it can arrive
            peer.writer.write(payload)

    def _queued(self, client: _Client) -> int:
        """Bytes waiting in ``client``'s send queue (the transport's buffer)."""
        return client.writer.transport.get_write_buffer_size()

    def _reply(self, client: _Client, data: bytes) -> None:
        """A reply to the client's own request; a client so far behind that it would not fit
        is not reading what it asks for: it is disconnected (frames to it are only dropped)."""
        tr = client.writer.transport
        if tr.is_closing():
            return
        if self._queued(client) > self.max_pending_bytes:
            self.stats.disconnected += 1
            tr.abort()
            return
        client.writer.write(data)

    def _leave(self, client: _Client) -> None:
        self._clients.discard(client)
        members = self._channels.get(client.channel or "")
        if members is not None:
            members.discard(client)
            if not members:
                del self._channels[client.channel or ""]


__all__ = [
    "DEFAULT_HOST", "DEFAULT_PORT", "CanHub", "Frame", "HubStats", "check_bind", "format_frame",
    "parse_send", "split_messages",
]  # fmt: skip
