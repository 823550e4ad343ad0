"""Issue #26 §3 figures for what a client can hold (standalone, ~10 s):

* dashboard: 200 connections that send a POST head and trickle the body (the first 63 one by
  one, so they fill every slot of the default cap of 64), then 5 normal ``GET /api/status``
  -- their status and latency; and the reply to an unauthenticated POST head declaring a
  200 MB body;
* CAN hub: a client that sends junk without ever reading (each message answered
  ``< error >``) for up to 2,000 x 10 kB -- the hub's queue for it, the process's peak RSS,
  and whether it was disconnected.

    PYTHONPATH=src python benchmarks/bench_inputs.py
"""

from __future__ import annotations

import logging
import resource
import socket
import threading
import time

SLOW_POST = (
    b"POST /api/speed HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    b"Content-Length: 1000\r\n\r\n{"
)


def _get(port: int) -> str:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
            out = b""
            while chunk := s.recv(65536):
                out += chunk
            return out[9:12].decode()
    except OSError as err:
        return type(err).__name__


def dashboard() -> None:
    from packpilot.web.app import Dashboard

    logging.disable(logging.WARNING)
    dash = Dashboard(host="127.0.0.1", port=0)
    threading.Thread(target=dash.serve, daemon=True).start()
    while dash.server is None or not dash.server.started:
        time.sleep(0.02)
    slow = []
    for k in range(200):
        s = socket.create_connection(("127.0.0.1", dash.port), timeout=5)
        s.sendall(SLOW_POST)
        slow.append(s)
        if k < 63:
            time.sleep(0.01)
    time.sleep(0.2)
    got = []
    for _ in range(5):
        t0 = time.monotonic()
        status = _get(dash.port)
        got.append(f"{status} in {(time.monotonic() - t0) * 1e3:.1f} ms")
    print("dashboard, 200 slow-body connections open, 5 GETs:", ", ".join(got))
    with socket.create_connection(("127.0.0.1", dash.port), timeout=5) as s:
        t0 = time.monotonic()
        s.sendall(
            b"POST /api/speed HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 200000000\r\n\r\n"
        )
        s.settimeout(2.0)
        try:
            reply = s.recv(64)[9:12].decode()
        except TimeoutError:
            reply = "no reply in 2 s (the server waits for the body)"
        print(f"dashboard, unauthenticated 200 MB POST head: {reply} after "
              f"{(time.monotonic() - t0) * 1e3:.1f} ms")  # fmt: skip
    for s in slow:
        s.close()
    dash.stop()


def hub() -> None:
    from packpilot.io.can.hub import CanHub

    logging.disable(logging.ERROR)
    with CanHub("127.0.0.1", 0) as h:
        s = socket.socket()
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        s.connect(("127.0.0.1", h.port))
        s.settimeout(5)
        t0, peak, sent = time.monotonic(), 0, 0
        try:
            for _ in range(2000):
                s.sendall(b"< x >" * 2000)
                sent += 10_000
                peak = max(
                    [peak, *(c.writer.transport.get_write_buffer_size() for c in h._clients)]
                )
        except OSError as err:
            end = f"disconnected by the hub ({type(err).__name__})"
        else:
            end = "still connected"
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        cut = getattr(h.stats, "disconnected", "n/a")
        print(f"can-hub, a client sending junk without reading: {sent / 1e6:.1f} MB sent in "
              f"{time.monotonic() - t0:.1f} s, largest queue for it {peak / 1e6:.2f} MB, "
              f"peak RSS {rss:.0f} MB, {end}; disconnected={cut}")  # fmt: skip
        s.close()


if __name__ == "__main__":
    dashboard()
    hub()
