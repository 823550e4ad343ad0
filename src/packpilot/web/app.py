"""The live dashboard: a FastAPI app over a :class:`LiveRun`, and the server around it.

Routes: ``/`` (the page, package data, no external URL), ``/static/*``, ``GET /api/status``,
``GET /api/events``, ``GET /api/samples`` and the WebSocket ``/ws``. Each WebSocket client gets
its own pull loop: every ``push_interval_s`` it sends what changed since its cursor (a few
updates per second however fast the simulation runs), so clients never slow the run down and a
closed browser only ends its own loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import socket
import threading
from pathlib import Path
from typing import Any

from fastapi import FastAPI, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.errors import InputError
from packpilot.web.live import CHART_CHANNELS, LiveRun, SimThread

STATIC = Path(__file__).resolve().parent / "static"
MAX_EVENTS_PER_MESSAGE = 500


def dumps(obj: Any) -> str:
    """Strict JSON (``allow_nan=False``): a NaN that slipped past ``jsonable`` is a bug."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


def _json(obj: Any) -> Response:
    return Response(dumps(obj), media_type="application/json")


def create_app(live: LiveRun, push_interval_s: float = 0.2) -> FastAPI:
    """The dashboard app for one run (already running in a ``SimThread``, or about to)."""
    if not push_interval_s > 0:
        raise ValueError(f"push_interval_s must be > 0, got {push_interval_s}")
    app = FastAPI(title="PackPilot dashboard", docs_url=None, redoc_url=None, openapi_url=None)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/", include_in_schema=False)
    async def index() -> FileResponse:
        return FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-store"})

    @app.get("/api/status")
    async def status() -> Response:
        return _json(live.status())

    @app.get("/api/events")
    async def events(
        since: int = Query(0, ge=0, description="index of the first event to return"),
        limit: int = Query(1000, ge=1, le=100_000),
    ) -> Response:
        evs = live.events(since, limit)
        return _json({"events": evs, "next": since + len(evs), "state": live.state})

    @app.get("/api/samples")
    async def samples(
        after_step: int = Query(-1, ge=-1, description="only points after this step"),
    ) -> Response:
        pts = live.points(after_step)
        return _json({"channels": list(CHART_CHANNELS), "points": pts, "state": live.state})

    @app.websocket("/ws")
    async def ws(sock: WebSocket) -> None:
        await sock.accept()
        gone = asyncio.create_task(_until_disconnect(sock))
        try:
            await sock.send_text(dumps(_hello(live)))
            cursor = (-1, 0)
            seen_version = -1
            backlog = False
            while not gone.done():
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
                    msg = {
                        "type": "update",
                        "state": st["state"],
                        "t_s": st["t_s"],
                        "progress": st["progress"],
                        "verdict": st["verdict"],
                        "latest": st["latest"],
                        "points": up.points,
                        "events": up.events,
                        "metrics": st["metrics"] if live.finished else None,
                        "error": st["error"],
                        "run_id": st["run_id"],
                    }
                    await sock.send_text(dumps(msg))
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

    return app


async def _until_disconnect(sock: WebSocket) -> None:
    """Return when the client disconnects; what it sends is ignored."""
    while True:
        msg = await sock.receive()
        if msg["type"] == "websocket.disconnect":
            return


def _hello(live: LiveRun) -> dict[str, Any]:
    return {
        "type": "hello",
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
    """A run plus its server: ``start()`` the simulation, ``serve()`` until Ctrl-C or ``stop``.

    ``serve`` blocks in the calling thread (uvicorn handles SIGINT/SIGTERM and shuts down
    gracefully, closing WebSockets); the simulation is then asked to stop and joined, so the
    SQLite run, if any, is finished as ``stopped`` rather than left ``running``.
    """

    def __init__(
        self,
        runner: Any,
        *,
        scenario: str,
        speed: float,
        db: Path | None = None,
        host: str = "127.0.0.1",
        port: int = 8765,
        push_interval_s: float = 0.2,
        max_points: int = 2000,
    ) -> None:
        cfg = runner.cfg
        self.live = LiveRun(
            scenario=scenario,
            duration_s=float(cfg.sim.duration_s),
            dt_s=float(cfg.sim.dt_s),
            speed=float(speed),
            max_points=max_points,
            battery_names=list(runner.pack.names),
            db=str(db) if db is not None else None,
        )
        try:
            if db is not None:
                check_db(db)
            self.sock = bind(host, port)
        except BaseException:
            close = getattr(runner.charger_link, "close", None)  # e.g. a CAN bus already open
            if callable(close):
                close()
            raise
        self.sim = SimThread(runner, self.live, db)
        self.app = create_app(self.live, push_interval_s)
        self.host = host
        self.port = int(self.sock.getsockname()[1])
        self.server: Any = None

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def start(self) -> None:
        self.sim.start()

    def serve(self) -> None:
        """Serve until shutdown. In the main thread uvicorn turns Ctrl-C into a graceful exit
        and re-raises it afterwards as KeyboardInterrupt; elsewhere use :meth:`stop`."""
        import uvicorn

        config = uvicorn.Config(
            self.app, log_level="warning", ws="websockets-sansio", timeout_graceful_shutdown=3
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
            self.sim.stop()
            self.sock.close()

    def stop(self) -> None:
        """Ask a serving server to exit (from another thread)."""
        if self.server is not None:
            self.server.should_exit = True
        self.sim.stop(timeout_s=0)
