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
import time
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
BODY_TIMEOUT_S = 10.0
"""A request whose body has not fully arrived this long after its head is closed (63
connections trickling a POST body held every slot for >= 34 s)."""
MAX_BODY_BYTES = 64 * 1024
"""Largest request body accepted (the API's bodies are a few hundred bytes of JSON); refused
by its Content-Length before authentication, before a byte of it is read (an unauthenticated
200 MB body was read in full before its 403)."""
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})


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


class BodyLimitMiddleware:
    """ASGI middleware, outermost (before the Host and token checks): a request body is
    refused by its declared size before anything reads it -- 413 above ``max_bytes``, 411
    for a POST without a Content-Length (a chunked body of unknown size) -- so no client,
    authenticated or not, makes the server read more than ``max_bytes``. h11 reads no more
    than the Content-Length a request declares."""

    def __init__(self, app: ASGIApp, max_bytes: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get("type") == "http":
            length = header(scope, "content-length")
            if length is None and scope.get("method") in _BODY_METHODS:
                if header(scope, "transfer-encoding") is not None:
                    await refuse(scope, receive, send, 411, "a Content-Length is required")
                    return
            elif length is not None and not _size_ok(length, self.max_bytes):
                why = f"request body larger than {self.max_bytes} bytes"
                await refuse(scope, receive, send, 413, why)
                return
        await self.app(scope, receive, send)


def _size_ok(length: str, most: int) -> bool:
    text = length.strip()
    return text.isdigit() and len(text) <= 12 and int(text) <= most


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


def _serving(p: Any) -> bool:
    """``p`` still owns an open transport (not closed, not upgraded to a WebSocket)."""
    tr = getattr(p, "transport", None)
    return tr is not None and not tr.is_closing() and tr.get_protocol() is p


def is_pending(p: Any) -> bool:
    """A guarded HTTP connection not being served: no request in flight, or a request whose
    body is still coming and whose response is not being sent (none yet, or already
    complete: an early 403 leaves the client trickling the rest of its body)."""
    import h11

    if not hasattr(p, "opened_at") or not _serving(p):
        return False
    state = p.conn.their_state
    if state is h11.IDLE:
        return True
    cycle = getattr(p, "cycle", None)
    sending = cycle is not None and cycle.response_started and not cycle.response_complete
    return state is h11.SEND_BODY and not sending


def evict_oldest_pending(connections: set[Any]) -> None:
    """Close the oldest pending connection (:func:`is_pending`), if any, and drop it from
    ``connections`` now (its ``connection_lost`` runs a loop tick later)."""
    waiting = [p for p in connections if is_pending(p)]
    if waiting:
        oldest = min(waiting, key=lambda p: p.opened_at)
        oldest.transport.abort()
        connections.discard(oldest)


_ProtocolBase: Any = object
"""The mixin's static base: uvicorn's H11Protocol comes in at class creation, so it is
imported only when a server starts."""


class _GuardedMixin(_ProtocolBase):  # type: ignore[misc]
    """The limits of :func:`guarded_h11`, over uvicorn's ``H11Protocol`` (next in the MRO)."""

    max_connections: int = MAX_CONNECTIONS
    header_timeout_s: float = HEADER_TIMEOUT_S
    body_timeout_s: float = BODY_TIMEOUT_S
    head_timer: asyncio.TimerHandle | None = None
    body_timer: asyncio.TimerHandle | None = None
    opened_at: float = 0.0

    def connection_made(self, transport: asyncio.Transport) -> None:
        self.opened_at = time.monotonic()
        if len(self.connections) >= self.max_connections - 1:
            evict_oldest_pending(self.connections)
        if len(self.connections) >= self.max_connections:
            self.transport = transport
            transport.abort()  # refused: closed before a byte is read
            return
        super().connection_made(transport)
        self._arm_head_timer()

    def handle_events(self) -> None:
        super().handle_events()
        self._watch_body()

    def _watch_body(self) -> None:
        """A body timer runs while the peer is sending a request body."""
        import h11

        sending = self.conn.their_state is h11.SEND_BODY
        if sending and self.body_timer is None:
            self.body_timer = self.loop.call_later(self.body_timeout_s, self._body_timeout)
        elif not sending and self.body_timer is not None:
            self.body_timer.cancel()
            self.body_timer = None

    def _body_timeout(self) -> None:
        import h11

        self.body_timer = None
        if _serving(self) and self.conn.their_state is h11.SEND_BODY:
            self.transport.abort()

    def _arm_head_timer(self) -> None:
        if self.head_timer is not None:
            self.head_timer.cancel()
        self.head_timer = self.loop.call_later(self.header_timeout_s, self._head_timeout)

    def _head_timeout(self) -> None:
        """No complete request head since the connection opened or the last response
        (h11 leaves IDLE only on a complete head): close it."""
        import h11

        if _serving(self) and self.conn.their_state is h11.IDLE:
            self.transport.abort()  # (not closed already, nor upgraded to a WebSocket)

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_head_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        for timer in (self.head_timer, self.body_timer):
            if timer is not None:
                timer.cancel()
        super().connection_lost(exc)


def guarded_h11(
    max_connections: int, header_timeout_s: float, body_timeout_s: float = BODY_TIMEOUT_S
) -> type[asyncio.Protocol]:
    """uvicorn's HTTP/1.1 protocol with the limits it lacks:

    * at most ``max_connections`` open connections. When a new one would reach the cap (where
      uvicorn answers 503), the oldest connection that is not being served -- idle, still
      sending its head, or still sending its body, no response started -- is closed to make
      room; only when every connection is being served is the new one closed at once. So
      clients that open connections and trickle (slowloris) cannot lock a normal request
      out: they evict each other, not a request that arrives whole;
    * a connection that has not sent a complete request head within ``header_timeout_s``
      is closed (half-open and trickling clients; uvicorn only times out idle keep-alive
      connections);
    * a request whose body is not complete ``body_timeout_s`` after its head is closed."""
    from uvicorn.protocols.http.h11_impl import H11Protocol

    limits = {
        "max_connections": max_connections,
        "header_timeout_s": header_timeout_s,
        "body_timeout_s": body_timeout_s,
    }
    return type("GuardedH11", (_GuardedMixin, H11Protocol), limits)
