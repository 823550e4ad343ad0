"""The live dashboard: a FastAPI app over a :class:`Session`, and the server around it.

Routes: ``/`` (the page, package data, no external URL), ``/static/*``, ``GET /api/status``,
``GET /api/events``, ``GET /api/samples``, ``GET /api/catalog``, ``GET /api/at`` (a recording's
sample at a time), ``GET /report``, the WebSocket ``/ws``, and the state-changing ``POST
/api/pause``, ``/api/resume``, ``/api/speed``, ``/api/start``, ``/api/open`` (token always).
Each WebSocket client gets its own pull loop: every ``push_interval_s`` it sends what changed
since its cursor (a few updates per second however fast the simulation runs), so clients never
slow the run down and a closed browser only ends its own loop. Access rules: :mod:`.guard`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import signal
import socket
import threading
from pathlib import Path
from typing import Any

from fastapi import Body, FastAPI, Query, Request, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.errors import InputError, PackPilotError
from packpilot.web.guard import (
    BODY_TIMEOUT_S,
    HEADER_TIMEOUT_S,
    MAX_CONNECTIONS,
    MAX_WEBSOCKETS,
    TOKEN_COOKIE,
    TOKEN_QUERY,
    Guard,
    guarded_h11,
    query,
)
from packpilot.web.guard import BodyLimitMiddleware as _BodyLimitMiddleware
from packpilot.web.guard import GuardMiddleware as _GuardMiddleware
from packpilot.web.live import CHART_CHANNELS, MAX_SPEED, LiveRun, SimThread, jsonable
from packpilot.web.session import Library, NotAllowed, ReportWriter, RunnerFactory, Session

STATIC = Path(__file__).resolve().parent / "static"
MAX_EVENTS_PER_MESSAGE = 500
TOKEN_SLOT = "__PACKPILOT_TOKEN__"
PAGE_HEADERS = {
    "Cache-Control": "no-store",
    # Only this server's own script, style and WebSocket; not framed (clickjacking the
    # controls); the token in a URL never leaves in a Referer.
    "Content-Security-Policy": (
        "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; "
        "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"
    ),
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
}


def dumps(obj: Any) -> str:
    """Strict JSON (``allow_nan=False``): a NaN that slipped past ``jsonable`` is a bug."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


def _json(obj: Any, status: int = 200) -> Response:
    return Response(dumps(obj), status_code=status, media_type="application/json")


def _error(status: int, why: str) -> Response:
    return _json({"error": why}, status)


def create_app(
    target: LiveRun | Session, push_interval_s: float = 0.2, guard: Guard | None = None,
    fleet: Path | None = None,
) -> FastAPI:  # fmt: skip
    """The dashboard app for a session (or one run, already running in a ``SimThread`` or
    about to). ``guard``: the access rules; default loopback with a fresh token."""
    if not push_interval_s > 0:
        raise ValueError(f"push_interval_s must be > 0, got {push_interval_s}")
    session = target if isinstance(target, Session) else Session(target)
    rules = guard if guard is not None else Guard()
    app = FastAPI(title="PackPilot dashboard", docs_url=None, redoc_url=None, openapi_url=None)
    app.state.session = session
    app.state.guard = rules
    app.state.websockets = 0
    app.add_middleware(_GuardMiddleware, guard=rules)
    app.add_middleware(_BodyLimitMiddleware)  # outermost: sizes before authentication
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
    page = (STATIC / "index.html").read_text(encoding="utf-8")
    _read_routes(app, session, rules, page, fleet is not None)
    _control_routes(app, session, rules)
    _fleet_routes(app, fleet)

    @app.websocket("/ws")
    async def ws(sock: WebSocket) -> None:
        if not rules.origin_ok(sock.scope):
            await sock.close(code=1008, reason="cross-origin WebSocket refused")
            return
        if app.state.websockets >= rules.max_websockets:
            await sock.close(code=1013, reason="too many dashboard connections")
            return
        app.state.websockets += 1
        try:
            await sock.accept()
            await _stream(sock, session, push_interval_s)
        finally:
            app.state.websockets -= 1

    return app


def _read_routes(app: FastAPI, session: Session, rules: Guard, page: str, fleet: bool) -> None:
    """What any allowed client may read (in remote mode the middleware demands the token).
    The catalog says where the fleet view is (``--fleet``; null without one), so the page
    links it."""

    @app.get("/", include_in_schema=False)
    async def index(request: Request) -> Response:
        html = page.replace(TOKEN_SLOT, rules.token)
        resp = Response(html, media_type="text/html", headers=PAGE_HEADERS)
        if rules.remote and query(request.scope, TOKEN_QUERY) is not None:
            # the browser keeps the token for the page's files, API reads and WebSocket
            resp.set_cookie(TOKEN_COOKIE, rules.token, httponly=True, samesite="strict")
        return resp

    @app.get("/api/status")
    async def status() -> Response:
        return _json(session.live.status())

    @app.get("/api/events")
    async def events(
        since: int = Query(0, ge=0, description="index of the first event to return"),
        limit: int = Query(1000, ge=1, le=100_000),
    ) -> Response:
        live = session.live
        evs = live.events(since, limit)
        return _json({"events": evs, "next": since + len(evs), "state": live.state})

    @app.get("/api/samples")
    async def samples(
        after_step: int = Query(-1, ge=-1, description="only points after this step"),
    ) -> Response:
        live = session.live
        pts = live.points(after_step)
        return _json({"channels": list(CHART_CHANNELS), "points": pts, "state": live.state})

    @app.get("/api/catalog")
    async def catalog() -> Response:
        cat = await asyncio.to_thread(session.catalog)
        return _json({**cat, "fleet": "/fleet" if fleet else None})

    @app.get("/api/at")
    async def at(t_s: float = Query(..., description="simulated time to show")) -> Response:
        rec = session.recording
        if rec is None:
            return _error(409, "not a recording: only a recorded run can be scrubbed")
        if not math.isfinite(t_s):
            return _error(422, "t_s must be finite")
        return _json(await asyncio.to_thread(rec.at, t_s))

    @app.get("/report", include_in_schema=False)
    async def report() -> Response:
        path = session.report_path
        if path is None or not path.is_file():
            return _error(404, "no report for this run")
        return FileResponse(path, media_type="text/html", headers={"Cache-Control": "no-store"})


def _fleet_routes(app: FastAPI, fleet: Path | None) -> None:
    """The fleet view (``--fleet``): battery health across flights, read-only."""

    @app.get("/fleet", include_in_schema=False)
    async def fleet_page() -> Response:
        if fleet is None:
            return _error(404, "no fleet: start the dashboard with --fleet fleet.sqlite")
        from packpilot.web.fleet import FLEET_HEADERS
        from packpilot.web.fleet import fleet_page as page

        try:
            text = await asyncio.to_thread(page, fleet)
        except PackPilotError as err:
            return _error(400, str(err))
        return Response(text, media_type="text/html", headers=FLEET_HEADERS)

    @app.get("/api/fleet")
    async def fleet_json() -> Response:
        if fleet is None:
            return _error(404, "no fleet: start the dashboard with --fleet fleet.sqlite")
        from packpilot.web.fleet import fleet_data

        try:
            return _json(jsonable(await asyncio.to_thread(fleet_data, fleet)))
        except PackPilotError as err:
            return _error(400, str(err))


class _Gate:
    """The checks of every state-changing endpoint: the token in the ``X-PackPilot-Token``
    header (which a cross-site page cannot set) and a same-origin ``Origin``, on loopback
    too."""

    def __init__(self, session: Session, rules: Guard) -> None:
        self.session = session
        self.rules = rules

    def refused(self, request: Request) -> Response | None:
        if not self.rules.token_ok(request.scope, header_only=True):
            return _error(403, "the X-PackPilot-Token header is missing or wrong")
        if not self.rules.origin_ok(request.scope):
            return _error(403, "cross-origin request refused")
        return None

    def pace(self, request: Request, do: Any) -> Response:
        """Apply ``do(live)`` to the live run on show (a recording has no pace)."""
        refused = self.refused(request)
        if refused is not None:
            return refused
        live = self.session.live
        if live.kind != "live" or self.session.sim is None:
            return _error(409, "no live run: a recording has no pace")
        do(live)
        return _json({"paused": live.paused, "speed": live.speed})

    async def switch(self, request: Request, do: Any) -> Response:
        """Switch the session to another run (built off the event loop)."""
        refused = self.refused(request)
        if refused is not None:
            return refused
        try:
            live = await asyncio.to_thread(do)
        except NotAllowed as err:
            return _error(403, str(err))
        except PackPilotError as err:
            return _error(400, str(err))
        return _json({"scenario": live.scenario, "kind": live.kind, "source": live.source})


def _bad_speed(speed: float) -> Response | None:
    if math.isfinite(speed) and 0 <= speed <= MAX_SPEED:
        return None
    return _error(422, f"speed must be 0..{MAX_SPEED:g} (0: as fast as possible)")


def _control_routes(app: FastAPI, session: Session, rules: Guard) -> None:
    """Pause, resume, speed, start an example, open a recording: all behind :class:`_Gate`."""
    gate = _Gate(session, rules)

    @app.post("/api/pause")
    async def pause(request: Request) -> Response:
        return gate.pace(request, lambda live: live.set_paused(True))

    @app.post("/api/resume")
    async def resume(request: Request) -> Response:
        return gate.pace(request, lambda live: live.set_paused(False))

    @app.post("/api/speed")
    async def speed(request: Request, speed: float = Body(..., embed=True)) -> Response:
        return _bad_speed(speed) or gate.pace(request, lambda live: live.set_speed(speed))

    @app.post("/api/start")
    async def start(
        request: Request,
        example: str = Body(..., embed=True, max_length=200),
        speed: float = Body(10.0, embed=True),
    ) -> Response:
        bad = gate.refused(request) or _bad_speed(speed)
        return bad or await gate.switch(request, lambda: session.start_example(example, speed))

    @app.post("/api/open")
    async def open_recording(
        request: Request,
        recording: str = Body(..., embed=True, max_length=1000),
        run_id: int | None = Body(None, embed=True, ge=1, le=2**63 - 1),
    ) -> Response:
        return await gate.switch(request, lambda: session.open_recording(recording, run_id))


async def _stream(sock: WebSocket, session: Session, push_interval_s: float) -> None:
    """One client's pull loop; a switch to another run greets the client again."""
    gone = asyncio.create_task(_until_disconnect(sock))
    try:
        generation = -1
        live = session.live
        cursor = (-1, 0)
        seen_version = -1
        backlog = False
        while not gone.done():
            if session.generation != generation:
                generation, live = session.generation, session.live
                cursor, seen_version, backlog = (-1, 0), -1, False
                await sock.send_text(dumps(_hello(live)))
            version = live.version
            if version != seen_version or backlog:
                seen_version = version
                # The state first, the points after: a run that reads "finished" here has
                # recorded its last sample, so this message carries it. (Read the other way
                # round, a loaded machine sent "finished" with the last 13 of 600 samples
                # still to come, and the page showed a finished run missing its end.)
                st = live.status()
                up = live.update_since(cursor, max_events=MAX_EVENTS_PER_MESSAGE)
                cursor = up.cursor
                await sock.send_text(dumps(_update(st, up.points, up.events, live.finished)))
                # More events queued than one message carries: send on without a pause.
                backlog = len(up.events) >= MAX_EVENTS_PER_MESSAGE and bool(
                    live.events(cursor[1], 1)
                )
                if backlog:
                    continue
            await asyncio.wait({gone}, timeout=push_interval_s)
    except (WebSocketDisconnect, ConnectionError, RuntimeError):
        pass  # the browser went away: only this loop ends, the run goes on
    finally:
        gone.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await gone


def _update(
    st: dict[str, Any], points: list[dict[str, Any]], events: list[dict[str, Any]], done: bool
) -> dict[str, Any]:
    keys = ("state", "t_s", "progress", "verdict", "latest", "error", "run_id", "speed",
            "paused", "headline", "report", "notice", "power", "power_note")  # fmt: skip
    msg = {"type": "update", **{k: st[k] for k in keys}}
    msg.update(points=points, events=events, metrics=st["metrics"] if done else None)
    return msg


async def _until_disconnect(sock: WebSocket) -> None:
    """Return when the client disconnects; what it sends is ignored."""
    while True:
        msg = await sock.receive()
        if msg["type"] == "websocket.disconnect":
            return


def _hello(live: LiveRun) -> dict[str, Any]:
    return {
        "type": "hello",
        "kind": live.kind,
        "source": live.source,
        "layout": live.layout,
        "scenario": live.scenario,
        "battery_names": list(live.battery_names),
        "duration_s": live.duration_s,
        "dt_s": live.dt_s,
        "speed": live.speed,
        "channels": list(BATTERY_CHANNELS),
        "chart_channels": list(CHART_CHANNELS),
        "max_points": live.max_points,
    }


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def check_db(db: Path) -> None:
    """Open the telemetry file once up front: a bad path is a one-line error, not a dead run.

    The simulation thread opens it again (SQLite connections belong to their thread).
    """
    import sqlite3

    from packpilot.io.telemetry import SQLiteRecorder

    try:
        SQLiteRecorder(db).close()
    except sqlite3.Error as err:
        raise InputError(f"--db {db}: cannot open ({err})") from None


def bind(host: str, port: int) -> socket.socket:
    """Listen before anything else starts, so a busy port is a one-line error (port 0: any)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as err:
        raise InputError(f"--host {host}: cannot resolve ({err.strerror})") from None
    family, _, _, _, addr = infos[0]
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(addr)
        sock.listen(128)
    except OSError as err:
        sock.close()
        raise InputError(f"--host {host} --port {port}: cannot listen ({err.strerror})") from None
    sock.set_inheritable(True)
    return sock


class Dashboard:
    """A session plus its server: ``start()`` the simulation, ``serve()`` until Ctrl-C or
    ``stop``.

    Shows a live run (``runner``), a recording (``recording``: a telemetry file the user
    named) or, with neither, nothing until the page starts an example or opens a recording.
    ``serve`` blocks in the calling thread (uvicorn handles SIGINT/SIGTERM and shuts down
    gracefully, closing WebSockets); the simulation is then asked to stop and joined, so the
    SQLite run, if any, is finished as ``stopped`` rather than left ``running``.
    """

    def __init__(
        self,
        runner: Any = None,
        *,
        scenario: str = "",
        source: str | None = None,
        speed: float = 10.0,
        db: Path | None = None,
        host: str = "127.0.0.1",
        port: int = 8765,
        push_interval_s: float = 0.2,
        max_points: int = 2000,
        recording: Path | None = None,
        run_id: int | None = None,
        library: Library | None = None,
        make_runner: RunnerFactory | None = None,
        write_report: ReportWriter | None = None,
        fleet: Path | None = None,
        allow_remote: bool = False,
        token: str | None = None,
        allowed_hosts: tuple[str, ...] = (),
        max_websockets: int = MAX_WEBSOCKETS,
        max_connections: int = MAX_CONNECTIONS,
        header_timeout_s: float = HEADER_TIMEOUT_S,
        body_timeout_s: float = BODY_TIMEOUT_S,
    ) -> None:
        try:
            self._setup_limits(max_websockets, max_connections, header_timeout_s)
            if not (math.isfinite(body_timeout_s) and body_timeout_s > 0):
                raise InputError(f"body timeout must be > 0 s, got {body_timeout_s}")
            self.body_timeout_s = body_timeout_s
            self.guard = Guard.for_bind(
                host,
                allow_remote=allow_remote,
                token=token,
                extra_hosts=allowed_hosts,
                max_websockets=max_websockets,
            )
            sim = None
            if runner is not None:
                live = self._live_run(runner, scenario, speed, db, max_points)
                live.source = source
                sim = SimThread(runner, live, db)
            else:
                live = LiveRun(scenario="no run yet", state="idle", max_points=max_points)
            self.session = Session(
                live, sim, library=library, make_runner=make_runner, db=db,
                write_report=write_report, max_points=max_points,
            )  # fmt: skip
            if recording is not None:
                self.session.open_path(recording, run_id)
            if db is not None:
                check_db(db)
            self.sock = bind(host, port)
        except BaseException:
            close = getattr(getattr(runner, "charger_link", None), "close", None)
            if callable(close):  # e.g. a CAN bus already open
                close()
            raise
        self.app = create_app(self.session, push_interval_s, self.guard, fleet)
        self.host = host
        self.port = int(self.sock.getsockname()[1])
        self.server: Any = None

    def _setup_limits(self, max_websockets: int, max_connections: int, timeout_s: float) -> None:
        if not 1 <= max_websockets < max_connections:
            raise InputError(
                f"--max-websockets {max_websockets}: must be 1..{max_connections - 1} "
                f"(below --max-connections {max_connections}, so the page itself still loads)"
            )
        if not (math.isfinite(timeout_s) and timeout_s > 0):
            raise InputError(f"header timeout must be > 0 s, got {timeout_s}")
        self.max_connections = max_connections
        self.header_timeout_s = timeout_s

    @staticmethod
    def _live_run(runner: Any, scenario: str, speed: float, db: Path | None, n: int) -> LiveRun:
        cfg = runner.cfg
        return LiveRun(
            scenario=scenario,
            duration_s=float(cfg.sim.duration_s),
            dt_s=float(cfg.sim.dt_s),
            speed=float(speed),
            max_points=n,
            battery_names=list(runner.pack.names),
            db=str(db) if db is not None else None,
        )

    @property
    def live(self) -> LiveRun:
        """The run on show now."""
        return self.session.live

    @property
    def sim(self) -> SimThread | None:
        return self.session.sim

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def open_url(self) -> str:
        """The URL to open in a browser: with the token when every request needs it."""
        return self.url + (f"?{TOKEN_QUERY}={self.guard.token}" if self.guard.remote else "")

    def start(self) -> None:
        self.session.start()

    def serve(self) -> None:
        """Serve until shutdown. In the main thread uvicorn turns Ctrl-C into a graceful exit
        and re-raises it afterwards as KeyboardInterrupt; elsewhere use :meth:`stop`."""
        import uvicorn

        config = uvicorn.Config(
            self.app,
            log_level="warning",
            http=guarded_h11(self.max_connections, self.header_timeout_s, self.body_timeout_s),
            ws="websockets-sansio",
            ws_max_size=64 * 1024,  # the page sends nothing; a client's frames are ignored
            limit_concurrency=self.max_connections,
            timeout_keep_alive=5,
            timeout_graceful_shutdown=3,
        )
        self.server = uvicorn.Server(config)
        main = threading.current_thread() is threading.main_thread()
        # uvicorn re-raises a captured SIGTERM after its graceful shutdown; with the default
        # handler that would kill the process before the run below is stopped and recorded.
        previous = signal.signal(signal.SIGTERM, _interrupt) if main else None
        try:
            self.server.run(sockets=[self.sock])
        finally:
            if main:
                signal.signal(signal.SIGTERM, previous)
            self.session.stop()
            self.sock.close()

    def stop(self) -> None:
        """Ask a serving server to exit (from another thread)."""
        if self.server is not None:
            self.server.should_exit = True
        sim = self.session.sim
        if sim is not None:
            sim.live.request_stop()
