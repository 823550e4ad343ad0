"""The dashboard's access rules (#18 §5), each checked so that dropping the rule fails a test:
Host check (DNS rebinding), WebSocket Origin check, the token on state-changing endpoints (and
on every request in remote mode), the WebSocket and connection caps, the half-open timeout,
the non-loopback bind opt-in, and recordings only from the directory the user named.

FastAPI's TestClient drives the app without sockets; the caps and timeouts that live in the
server are checked against a real uvicorn on 127.0.0.1 (never another address: the remote
mode's rules are checked through the app, and the opt-in by the refusal to bind).
"""

from __future__ import annotations

import socket
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

with warnings.catch_warnings():
    warnings.filterwarnings("ignore", message="Using `httpx` with")
    from fastapi.testclient import TestClient

from starlette.websockets import WebSocketDisconnect

from packpilot.errors import InputError
from packpilot.web.app import Dashboard, create_app
from packpilot.web.guard import TOKEN_COOKIE, Guard, split_host
from packpilot.web.live import LiveRun
from packpilot.web.session import Library, NotAllowed, Session
from tests.test_web_app import WS_URL, local, scenario, start, strict_loads

TOKEN = "t0k3n-for-the-tests-0123456789"


def finished_run() -> LiveRun:
    live = LiveRun(scenario="x", battery_names=["A"], duration_s=1.0)
    live.on_start(["A"])
    live.on_finish({"steps": 0}, "finished")
    return live


def client(guard: Guard | None = None, peer: str = "127.0.0.1", **kw: Any) -> TestClient:
    app = create_app(finished_run(), push_interval_s=0.05, guard=guard or Guard(token=TOKEN))
    return TestClient(app, base_url="http://127.0.0.1", client=(peer, 50000), **kw)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A real telemetry file: the two-battery web test scenario, 30 s, recorded to SQLite."""
    from packpilot.config import parse_config
    from packpilot.io.telemetry import SQLiteRecorder
    from packpilot.sim.runner import Runner

    path = tmp_path_factory.mktemp("rec") / "run.sqlite"
    with SQLiteRecorder(path) as rec:
        Runner(parse_config(scenario()), recorder=rec, progress=False).run()
    return path


# ---------------------------------------------------------------- Host (DNS rebinding)
@pytest.mark.parametrize("path", ["/", "/api/status", "/api/events", "/static/dashboard.js"])
def test_a_foreign_host_header_is_refused(path: str) -> None:
    c = client()
    for host in ("evil.example.com", "evil.example.com:8765", "127.0.0.1.evil.example", ""):
        r = c.get(path, headers={"Host": host})
        assert r.status_code == 421, (host, r.status_code)
        assert "rebinding" in r.text
    for host in ("127.0.0.1", "127.0.0.1:8765", "localhost:8765", "LOCALHOST", "[::1]:8765"):
        assert c.get(path, headers={"Host": host}).status_code == 200, host


def test_a_foreign_host_websocket_is_refused() -> None:
    c = client()
    with pytest.raises(WebSocketDisconnect), c.websocket_connect("ws://evil.example.com/ws") as ws:
        ws.receive_text()
    with c.websocket_connect(WS_URL) as ws:
        assert strict_loads(ws.receive_text())["type"] == "hello"


def test_split_host() -> None:
    assert split_host("[::1]:8765") == "::1"
    assert split_host("LocalHost:1") == "localhost"
    assert split_host("127.0.0.1") == "127.0.0.1"


# ---------------------------------------------------------------- WebSocket Origin
def ws_accepted(c: TestClient, headers: dict[str, str], url: str = WS_URL) -> bool:
    try:
        with c.websocket_connect(url, headers=headers) as ws:
            return bool(strict_loads(ws.receive_text())["type"] == "hello")
    except WebSocketDisconnect:
        return False


def test_websocket_origin_must_be_the_page_itself() -> None:
    c = client()
    assert ws_accepted(c, {"Origin": "http://127.0.0.1"})
    assert not ws_accepted(c, {"Origin": "http://evil.example.com"})
    assert not ws_accepted(c, {"Origin": "null"})  # a sandboxed frame or a file:// page
    # another local server (another port) is another origin
    url = "ws://127.0.0.1:8765/ws"
    assert ws_accepted(c, {"Origin": "http://127.0.0.1:8765"}, url)
    assert not ws_accepted(c, {"Origin": "http://127.0.0.1:9999"}, url)
    assert not ws_accepted(c, {"Origin": "http://localhost:8765"}, url)


def test_websocket_without_origin_only_from_loopback() -> None:
    """Browsers always send Origin with a WebSocket: none means a script, accepted when it
    runs on this machine."""
    assert ws_accepted(client(peer="127.0.0.1"), {})
    assert ws_accepted(client(peer="::1"), {})
    assert not ws_accepted(client(peer="192.0.2.7"), {})
    assert ws_accepted(client(peer="192.0.2.7"), {"Origin": "http://127.0.0.1"})


# ---------------------------------------------------------------- WebSocket cap
def test_websockets_beyond_the_cap_are_refused_and_a_freed_slot_is_reused() -> None:
    c = client(Guard(token=TOKEN, max_websockets=2))
    with c.websocket_connect(WS_URL) as one, c.websocket_connect(WS_URL) as two:
        one.receive_text()
        two.receive_text()
        with pytest.raises(WebSocketDisconnect) as refused, c.websocket_connect(WS_URL) as three:
            three.receive_text()
        assert refused.value.code == 1013  # "try again later"
    with c.websocket_connect(WS_URL) as again:  # both closed: slots free again
        assert strict_loads(again.receive_text())["type"] == "hello"


# ---------------------------------------------------------------- token
def test_state_changing_endpoints_need_the_token_on_loopback_too() -> None:
    live, sim = start(speed=1.0, duration_s=600.0)  # a real paced run
    try:
        app = create_app(Session(live, sim), guard=Guard(token=TOKEN))
        c = TestClient(app, base_url="http://127.0.0.1", client=("127.0.0.1", 1))
        same = {"Origin": "http://127.0.0.1"}
        for path, body in (
            ("/api/pause", {}),
            ("/api/resume", {}),
            ("/api/speed", {"speed": 5}),
            ("/api/start", {"example": "uav_mission"}),
            ("/api/open", {"recording": "x.sqlite"}),
        ):
            assert c.post(path, json=body, headers=same).status_code == 403, path
            bad = {**same, "X-PackPilot-Token": TOKEN[:-1] + "x"}
            assert c.post(path, json=body, headers=bad).status_code == 403, path
            # the token in a cookie or the query string is not enough: a cross-site form
            # carries cookies, it cannot set a header
            c.cookies.set(TOKEN_COOKIE, TOKEN)
            assert c.post(path + f"?token={TOKEN}", json=body, headers=same).status_code == 403
            c.cookies.clear()
            evil = {"Origin": "http://evil.example.com", "X-PackPilot-Token": TOKEN}
            assert c.post(path, json=body, headers=evil).status_code == 403, path
        assert not live.paused and live.speed == 1.0 and live.scenario == "web_test"
        ok = {**same, "X-PackPilot-Token": TOKEN}
        r = c.post("/api/pause", json={}, headers=ok)
        assert r.status_code == 200 and live.paused
        assert c.post("/api/speed", json={"speed": 7.5}, headers=ok).json()["speed"] == 7.5
        assert c.post("/api/speed", json={"speed": -1}, headers=ok).status_code == 422
        assert c.post("/api/resume", json={}, headers=ok).status_code == 200 and not live.paused
        assert c.get("/api/pause").status_code == 405  # no state change by GET
        # the page the server hands out carries the token for its own requests
        assert f'content="{TOKEN}"' in c.get("/").text
    finally:
        sim.stop()


def test_remote_mode_needs_the_token_on_every_request() -> None:
    c = client(Guard(token=TOKEN, remote=True), peer="192.0.2.7")
    for path in ("/", "/api/status", "/static/dashboard.js", "/api/catalog"):
        assert c.get(path).status_code == 401, path
        wrong = {"X-PackPilot-Token": "wrong-token-0123456789"}
        assert c.get(path, headers=wrong).status_code == 401
        assert c.get(path, headers={"X-PackPilot-Token": TOKEN}).status_code == 200, path
    page = c.get(f"/?token={TOKEN}")  # the URL the CLI prints
    assert page.status_code == 200
    cookie = page.headers["set-cookie"]
    assert TOKEN in cookie and "httponly" in cookie.lower() and "samesite=strict" in cookie.lower()
    assert c.get("/api/status").status_code == 200  # the browser's cookie from now on
    origin = {"Origin": "http://127.0.0.1"}
    assert ws_accepted(c, origin)
    c.cookies.clear()
    assert not ws_accepted(c, origin)


def test_pages_cannot_be_framed_and_load_nothing_foreign() -> None:
    r = client().get("/")
    assert r.headers["x-frame-options"] == "DENY"
    csp = r.headers["content-security-policy"]
    assert "frame-ancestors 'none'" in csp and "default-src 'self'" in csp
    assert r.headers["referrer-policy"] == "no-referrer"


# ---------------------------------------------------------------- bind opt-in
def test_a_non_loopback_host_needs_allow_remote() -> None:
    with pytest.raises(InputError, match="--allow-remote"):
        Guard.for_bind("0.0.0.0", allow_remote=False)
    with pytest.raises(InputError, match="--allow-remote"):
        Dashboard(host="0.0.0.0", port=0)  # refused before anything listens
    with pytest.raises(InputError, match="--token"):
        Guard.for_bind("0.0.0.0", allow_remote=True, token="short")
    g = Guard.for_bind("0.0.0.0", allow_remote=True, extra_hosts=["pack.lan:8765"])
    assert g.remote and "pack.lan" in g.allowed_hosts and len(g.token) >= 16
    local_guard = Guard.for_bind("127.0.0.1", allow_remote=False)
    assert not local_guard.remote and "evil.example.com" not in local_guard.allowed_hosts
    assert not Guard.for_bind("localhost", allow_remote=True).remote  # loopback stays local
    with pytest.raises(InputError, match="--allowed-host"):
        Guard.for_bind("127.0.0.1", allow_remote=False, extra_hosts=["evil.example.com"])


# ---------------------------------------------------------------- real server limits
@pytest.fixture
def server() -> Iterator[Dashboard]:
    dash = Dashboard(
        host="127.0.0.1", port=0, max_connections=8, max_websockets=2, header_timeout_s=1.5
    )
    thread = threading.Thread(target=dash.serve, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while dash.server is None or not dash.server.started:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    yield dash
    dash.stop()
    thread.join(10)


def closed_by_server(s: socket.socket, within_s: float) -> bool:
    """The server closed (or reset) ``s`` within ``within_s`` without a response."""
    s.settimeout(within_s)
    try:
        return s.recv(1024) == b""
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def get(port: int, host: str = "127.0.0.1") -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(f"GET /api/status HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode())
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out


def test_real_server_refuses_a_rebinding_host(server: Dashboard) -> None:
    assert get(server.port, "evil.example.com").startswith(b"HTTP/1.1 421")
    assert get(server.port).startswith(b"HTTP/1.1 200")


def test_half_open_connections_are_capped_and_timed_out(server: Dashboard) -> None:
    t0 = time.monotonic()
    idle = [socket.create_connection(("127.0.0.1", server.port), timeout=5) for _ in range(4)]
    trickle = [socket.create_connection(("127.0.0.1", server.port), timeout=5) for _ in range(4)]
    for s in trickle:  # a request head that never ends
        s.sendall(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: ")
    time.sleep(0.3)
    try:
        # at the cap, a new request evicts the oldest connection not being served (issue #26:
        # it used to be refused, so trickling clients locked every normal request out)
        assert get(server.port).startswith(b"HTTP/1.1 200")
        assert closed_by_server(idle[0], 0.5), "the oldest idle connection was kept"
        assert time.monotonic() - t0 < 1.4  # all of that before the header timeout
        for s in idle[1:] + trickle:  # the header timeout (1.5 s) frees every slot
            assert closed_by_server(s, 5.0), "a half-open connection was never closed"
        assert time.monotonic() - t0 >= 1.4
    finally:
        for s in idle + trickle:
            s.close()
    assert get(server.port).startswith(b"HTTP/1.1 200")  # served again


def test_connections_beyond_the_cap_are_refused_when_all_are_being_served(
    server: Dashboard,
) -> None:
    """Eviction takes only connections not being served: WebSockets (served) hold their
    slots, and a new connection beyond the cap is closed at once."""
    import websockets.sync.client as wsc

    url = f"ws://127.0.0.1:{server.port}/ws"
    socks = [wsc.connect(url, open_timeout=5) for _ in range(2)]  # max_websockets = 2
    try:
        held = [socket.create_connection(("127.0.0.1", server.port), timeout=5) for _ in range(5)]
        time.sleep(0.2)
        assert get(server.port).startswith(b"HTTP/1.1 200")  # evicts an idle one
        assert sum(closed_by_server(s, 0.3) for s in held) >= 1
        for s in held:
            s.close()
    finally:
        for w in socks:
            w.close()


@pytest.fixture
def busy_server() -> Iterator[Dashboard]:
    """The default connection cap (64), a 1 s body timeout."""
    yield from _serving(Dashboard(host="127.0.0.1", port=0, body_timeout_s=1.0))


@pytest.fixture
def default_server() -> Iterator[Dashboard]:
    """Every limit at its default (a 10 s body timeout: not what frees the slots below)."""
    yield from _serving(Dashboard(host="127.0.0.1", port=0))


def _serving(dash: Dashboard) -> Iterator[Dashboard]:
    thread = threading.Thread(target=dash.serve, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while dash.server is None or not dash.server.started:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    yield dash
    dash.stop()
    thread.join(10)


SLOW_POST = (
    b"POST /api/speed HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    b"Content-Length: 1000\r\n\r\n{"
)


def test_a_normal_request_is_served_within_1s_while_200_slow_bodies_are_open(
    default_server: Dashboard,
) -> None:
    """Issue #26: 63 connections sending a POST head and trickling the body held every slot
    (>= 34 s) while everything else got 503."""
    slow: list[socket.socket] = []
    try:
        for k in range(200):
            s = socket.create_connection(("127.0.0.1", default_server.port), timeout=5)
            s.sendall(SLOW_POST)
            slow.append(s)
            if k < 63:
                time.sleep(0.01)  # the first 63 settle one by one: every slot of the cap of 64
        time.sleep(0.2)
        for _ in range(3):
            t0 = time.monotonic()
            reply = get(default_server.port)
            assert reply.startswith(b"HTTP/1.1 200"), reply[:80]
            assert time.monotonic() - t0 < 1.0
    finally:
        for s in slow:
            s.close()


def test_a_trickled_body_is_cut_after_the_body_timeout(busy_server: Dashboard) -> None:
    """An authenticated request whose handler waits for its body: the body timer (1 s here)
    closes it, however the bytes trickle."""
    s = socket.create_connection(("127.0.0.1", busy_server.port), timeout=5)
    try:
        t0 = time.monotonic()
        s.sendall(
            b"POST /api/speed HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100\r\n"
            + f"X-PackPilot-Token: {busy_server.guard.token}\r\n\r\n".encode()
            + b'{"speed": '
        )
        for _ in range(3):  # a byte every 0.2 s: the head timer no longer runs, the body's does
            time.sleep(0.2)
            s.sendall(b" ")
        assert closed_by_server(s, 3.0), "a trickled body was never cut"
        assert 0.9 <= time.monotonic() - t0 < 3.0
    finally:
        s.close()


@pytest.mark.parametrize(
    ("head", "status"),
    [
        (b"Content-Length: 200000000\r\n", b"413"),  # 200 MB, unauthenticated
        (b"Content-Length: 99999999999999999999999\r\n", b"400"),  # h11's own refusal
        (b"Transfer-Encoding: chunked\r\n", b"411"),
    ],
)
def test_an_oversized_body_is_refused_by_its_size_before_authentication(
    busy_server: Dashboard, head: bytes, status: bytes
) -> None:
    """An unauthenticated 200 MB body was read in full before its 403: now the declared
    size is refused at once, with no token and before a byte of the body is sent."""
    with socket.create_connection(("127.0.0.1", busy_server.port), timeout=5) as s:
        t0 = time.monotonic()
        s.sendall(b"POST /api/speed HTTP/1.1\r\nHost: 127.0.0.1\r\n" + head + b"\r\n")
        reply = s.recv(4096)
        assert reply.startswith(b"HTTP/1.1 " + status), reply[:80]
        assert time.monotonic() - t0 < 1.0


def test_a_keep_alive_client_is_not_cut_off(server: Dashboard) -> None:
    """The header timeout counts from the last response: a client that keeps asking is
    served on one connection past the timeout."""
    import http.client

    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=5)
    try:
        for _ in range(4):
            conn.request("GET", "/api/status")
            assert conn.getresponse().read() and True
            time.sleep(0.6)  # 2.4 s in all, longer than the 1.5 s header timeout
    finally:
        conn.close()


# ---------------------------------------------------------------- recordings directory
def test_recordings_only_from_the_named_directory(tmp_path: Path, recording: Path) -> None:
    runs = tmp_path / "runs"
    (runs / "sub").mkdir(parents=True)
    outside = tmp_path / "outside"
    outside.mkdir()
    data = recording.read_bytes()
    (runs / "a.sqlite").write_bytes(data)
    (runs / "sub" / "b.sqlite").write_bytes(data)
    (outside / "secret.sqlite").write_bytes(data)
    (runs / "fake.sqlite").write_text("not a database", encoding="utf-8")
    (runs / "link.sqlite").symlink_to(outside / "secret.sqlite")
    (runs / "dirlink").symlink_to(outside, target_is_directory=True)
    (runs / "inside_link.sqlite").symlink_to(runs / "a.sqlite")
    lib = Library.of_dirs([], runs)
    listed = lib.recordings()
    assert listed == ["a.sqlite", "inside_link.sqlite", "sub/b.sqlite"], listed
    assert lib.resolve("sub/b.sqlite") == (runs / "sub" / "b.sqlite").resolve()
    for name in (
        "../outside/secret.sqlite",
        str(outside / "secret.sqlite"),
        "link.sqlite",
        "dirlink/secret.sqlite",
        "sub/../../outside/secret.sqlite",
        "fake.sqlite",
        "missing.sqlite",
        "a.sqlite\x00",
        "",
        ".",
        "sub",
    ):
        with pytest.raises(NotAllowed):
            lib.resolve(name)
    with pytest.raises(NotAllowed, match="--runs-dir"):
        Library().resolve("a.sqlite")
    # through the API, with the token
    session = Session(finished_run(), library=lib)
    c = TestClient(
        create_app(session, guard=Guard(token=TOKEN)),
        base_url="http://127.0.0.1",
        client=("127.0.0.1", 1),
    )
    ok = {"Origin": "http://127.0.0.1", "X-PackPilot-Token": TOKEN}
    assert c.get("/api/catalog").json()["recordings"] == listed
    r = c.post("/api/open", json={"recording": "../outside/secret.sqlite"}, headers=ok)
    assert r.status_code == 403 and session.recording is None
    assert c.post("/api/open", json={"recording": "link.sqlite"}, headers=ok).status_code == 403
    r = c.post("/api/open", json={"recording": "sub/b.sqlite"}, headers=ok)
    assert r.status_code == 200, r.text
    st = c.get("/api/status").json()
    assert st["kind"] == "recorded" and st["state"] == "finished"


def test_bad_limits_are_one_line_errors() -> None:
    with pytest.raises(InputError, match="--max-websockets"):
        Dashboard(port=0, max_websockets=64, max_connections=64)
    with pytest.raises(InputError, match="--max-websockets"):
        Dashboard(port=0, max_websockets=0)


def test_local_client_helper_is_loopback() -> None:
    """The helper the other web tests use passes the Host and Origin rules as a script on
    this machine would; a client named otherwise would not."""
    c = local(create_app(finished_run()))
    assert c.get("/api/status").status_code == 200
