"""The dashboard's access rules: Host and Origin checks, the token, connection caps.

The threat model (docs/dashboard.md, "Security"): the server listens on loopback by default,
where the danger is a *web page* in the user's browser, not another machine. A page from
elsewhere can make the browser talk to 127.0.0.1 in two ways: DNS rebinding (its own name
re-resolved to 127.0.0.1, so requests carry ``Host: evil.example``) and cross-site requests
(a WebSocket or a form post carrying ``Origin: http://evil.example``). The Host check stops the
first, the Origin check and the token (a custom header a cross-site request cannot set) the
second. Bound to another address (``--allow-remote``), every request needs the token.
"""

from __future__ import annotations

import asyncio
import hmac
import secrets
import socket
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from dataclasses import dataclass, field
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qs

from packpilot.errors import InputError
from packpilot.io.net import is_loopback, resolves_to_loopback

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

TOKEN_HEADER = "x-packpilot-token"
TOKEN_COOKIE = "packpilot_token"
TOKEN_QUERY = "token"
MIN_TOKEN_CHARS = 16
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
MAX_WEBSOCKETS = 32
MAX_CONNECTIONS = 64
HEADER_TIMEOUT_S = 10.0
"""A connection that has not sent a complete request head within this time is closed: a
half-open or trickling client holds a socket for at most this long."""


def new_token() -> str:
    return secrets.token_urlsafe(24)


def check_token(token: str) -> str:
    """A given token must be long enough not to be guessed; one line otherwise."""
    if len(token) < MIN_TOKEN_CHARS or not token.isprintable() or " " in token:
        raise InputError(
            f"--token: must be at least {MIN_TOKEN_CHARS} printable characters without spaces"
        )
    return token


def split_host(value: str) -> str:
    """The name part of a ``Host`` header (``[::1]:8765`` → ``::1``), lowercased."""
    v = value.strip().lower()
    if v.startswith("["):
        end = v.find("]")
        return v[1:end] if end > 0 else v
    if v.count(":") == 1:
        return v.split(":", 1)[0]
    return v


@dataclass(frozen=True)
class Guard:
    """What a request must satisfy. ``remote``: the server listens beyond loopback, so every
    request needs the token; otherwise only state-changing ones do."""

    token: str = field(default_factory=new_token)
    allowed_hosts: frozenset[str] = LOOPBACK_NAMES
    remote: bool = False
    max_websockets: int = MAX_WEBSOCKETS

    def __post_init__(self) -> None:
        if self.max_websockets < 1:
            raise ValueError(f"max_websockets must be >= 1, got {self.max_websockets}")

    @classmethod
    def for_bind(
        cls,
        host: str,
        *,
        allow_remote: bool,
        token: str | None = None,
        extra_hosts: Iterable[str] = (),
        max_websockets: int = MAX_WEBSOCKETS,
    ) -> Guard:
        """The rules for a server on ``host``; a non-loopback host needs ``allow_remote``."""
        tok = check_token(token) if token is not None else new_token()
        extra = {split_host(h) for h in extra_hosts if h.strip()}
        if resolves_to_loopback(host):
            if extra:
                raise InputError("--allowed-host: only with a non-loopback --host")
            local = LOOPBACK_NAMES | {host.lower().strip("[]")}
            return cls(tok, frozenset(local), False, max_websockets)
        if not allow_remote:
            raise InputError(
                f"--host {host}: not a loopback address; serving other machines needs "
                "--allow-remote (every request then needs the token)"
            )
        names = set(LOOPBACK_NAMES) | extra
        if host not in ("0.0.0.0", "::", ""):
            names.add(host.lower().strip("[]"))
        else:  # a wildcard bind: the machine's own names, plus what the user lists
            names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
        return cls(tok, frozenset(names), True, max_websockets)

    # ---------------------------------------------------------------- checks
    def host_ok(self, scope: Scope) -> bool:
        host = header(scope, "host")
        return host is not None and split_host(host) in self.allowed_hosts

    def token_ok(self, scope: Scope, *, header_only: bool = False) -> bool:
        """The token from the header, or (for what a browser loads by itself: the page, its
        files, the WebSocket) the cookie or ``?token=``. Constant-time comparison."""
        given = [header(scope, TOKEN_HEADER)]
        if not header_only:
            given += [cookie(scope, TOKEN_COOKIE), query(scope, TOKEN_QUERY)]
        want = self.token.encode()
        return any(g is not None and hmac.compare_digest(g.encode(), want) for g in given)

    def origin_ok(self, scope: Scope) -> bool:
        """Same origin as the (already checked) Host. No Origin at all means no browser sent
        it (browsers always send one with a WebSocket or a POST): accepted from a loopback
        peer only."""
        origin = header(scope, "origin")
        if origin is None:
            client = scope.get("client")
            return client is not None and is_loopback(str(client[0]))
        host = header(scope, "host") or ""
        return origin.strip().lower() in {f"http://{host.lower()}", f"https://{host.lower()}"}


def header(scope: Scope, name: str) -> str | None:
    key = name.encode("latin-1")
    for k, v in scope.get("headers", ()):
        if k.lower() == key:
            return bytes(v).decode("latin-1")
    return None


def cookie(scope: Scope, name: str) -> str | None:
    raw = header(scope, "cookie")
    if raw is None:
        return None
    jar: SimpleCookie = SimpleCookie()
    try:
        jar.load(raw)
    except Exception:  # a malformed cookie header is no token
        return None
    morsel = jar.get(name)
    return morsel.value if morsel is not None else None


def query(scope: Scope, name: str) -> str | None:
    qs = parse_qs(bytes(scope.get("query_string", b"")).decode("latin-1"))
    vals = qs.get(name)
    return vals[0] if vals else None


class GuardMiddleware:
    """ASGI middleware: Host check on every request and WebSocket (421 / refused handshake),
    the token on every request in remote mode (401)."""

    def __init__(self, app: ASGIApp, guard: Guard) -> None:
        self.app = app
        self.guard = guard

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope.get("type")
        if kind not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        if not self.guard.host_ok(scope):
            await refuse(scope, receive, send, 421, "Host not allowed (DNS rebinding defence)")
            return
        if self.guard.remote and not self.guard.token_ok(scope):
            await refuse(scope, receive, send, 401, "token required")
            return
        await self.app(scope, receive, send)


async def refuse(scope: Scope, receive: Receive, send: Send, status: int, why: str) -> None:
    """An HTTP error, or for a WebSocket a refused handshake (the client sees HTTP 403)."""
    if scope["type"] == "websocket":
        await receive()  # websocket.connect
        await send({"type": "websocket.close", "code": 1008, "reason": why})
        return
    body = f'{{"error": "{why}"}}'.encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


def guarded_h11(max_connections: int, header_timeout_s: float) -> type[asyncio.Protocol]:
    """uvicorn's HTTP/1.1 protocol with two limits it lacks: at most ``max_connections``
    open connections (beyond, a new one is closed at once), and a connection that has not
    sent a complete request head within ``header_timeout_s`` is closed (half-open and
    trickling clients; uvicorn only times out idle keep-alive connections)."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class GuardedH11(H11Protocol):
        head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            if len(self.connections) >= max_connections:
                self.transport = transport
                transport.abort()  # refused: closed before a byte is read
                return
            super().connection_made(transport)
            self._arm_head_timer()

        def _arm_head_timer(self) -> None:
            if self.head_timer is not None:
                self.head_timer.cancel()
            self.head_timer = self.loop.call_later(header_timeout_s, self._head_timeout)

        def _head_timeout(self) -> None:
            """No complete request head since the connection opened or the last response
            (h11 leaves IDLE only on a complete head): close it."""
            tr = self.transport
            if tr.is_closing() or tr.get_protocol() is not self:
                return  # closed already, or upgraded to a WebSocket
            if self.conn.their_state is h11.IDLE:
                tr.abort()

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._arm_head_timer()

        def connection_lost(self, exc: Exception | None) -> None:
            if self.head_timer is not None:
                self.head_timer.cancel()
            super().connection_lost(exc)

    return GuardedH11
