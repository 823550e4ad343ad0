"""Headless Chromium driven over the DevTools protocol, with no network: a helper for tests.

The browser gets no network at all: a proxy that does not exist, a host resolver that resolves
nothing (loopback excepted, for the DevTools socket) and QUIC off. ``Network.enable`` records
every request the page makes, so a test can assert a page needed none but its own file.
"""

from __future__ import annotations

import json
import subprocess
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from websockets.sync.client import ClientConnection, connect

CHROMIUM = Path("/usr/bin/chromium")


class Cdp:
    """The few DevTools-protocol calls the tests need, over one page's WebSocket."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.n = 0
        self.requests: list[str] = []
        """URLs of every request the page started (``Network.requestWillBeSent``)."""

    def _note(self, msg: dict[str, Any]) -> None:
        if msg.get("method") == "Network.requestWillBeSent":
            self.requests.append(msg["params"]["request"]["url"])

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self.n += 1
        self.ws.send(json.dumps({"id": self.n, "method": method, "params": params}))
        for _ in range(100_000):  # note protocol events until our answer
            msg = json.loads(self.ws.recv(timeout=60))
            if msg.get("id") == self.n:
                assert "error" not in msg, msg["error"]
                result: dict[str, Any] = msg["result"]
                return result
            self._note(msg)
        raise AssertionError(f"no answer to {method}")

    def eval(self, expr: str) -> Any:
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise AssertionError(r["exceptionDetails"])
        return r["result"].get("value")

    def wait(self, expr: str, timeout_s: float = 20.0) -> Any:
        """Poll ``expr`` until it is truthy; its value."""
        deadline = time.monotonic() + timeout_s
        value: Any = None
        while True:
            try:  # during navigation the expression may not evaluate yet
                value = self.eval(expr)
            except AssertionError:
                value = None
            if value or time.monotonic() >= deadline:
                break
            time.sleep(0.05)
        assert value, f"never true: {expr}"
        return value

    def mouse(self, kind: str, x: float, y: float, **kw: Any) -> None:
        """A real input event (``mouseMoved``, ``mousePressed``, ``mouseReleased``,
        ``mouseWheel``) at page coordinates."""
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, **kw)

    def screenshot(self, path: Path, *, full_page: bool = False) -> None:
        import base64

        params: dict[str, Any] = {"format": "png"}
        if full_page:
            params["captureBeyondViewport"] = True
            w = self.eval("document.documentElement.scrollWidth")
            h = self.eval("document.documentElement.scrollHeight")
            params["clip"] = {"x": 0, "y": 0, "width": w, "height": h, "scale": 1}
        data = self.call("Page.captureScreenshot", **params)["data"]
        path.write_bytes(base64.b64decode(data))


def _get_json(url: str) -> Any:
    with urllib.request.urlopen(url, timeout=5) as resp:
        return json.loads(resp.read())


@contextmanager
def chromium(profile: Path, width: int = 1280, height: int = 900) -> Iterator[Cdp]:
    """A headless Chromium without network, its first page driven over the protocol."""
    proc = subprocess.Popen(
        [
            str(CHROMIUM),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--proxy-server=http://127.0.0.1:9",  # nothing listens there
            "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
            "--remote-debugging-address=127.0.0.1",
            "--remote-debugging-port=0",
            f"--window-size={width},{height}",
            "--hide-scrollbars",
            f"--user-data-dir={profile}",
            "about:blank",
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + 20.0
        while not port_file.exists() and time.monotonic() < deadline:
            assert proc.poll() is None, "chromium exited at start"
            time.sleep(0.05)
        port = int(port_file.read_text().split()[0])
        pages = [t for t in _get_json(f"http://127.0.0.1:{port}/json/list") if t["type"] == "page"]
        with connect(pages[0]["webSocketDebuggerUrl"], max_size=None, open_timeout=10) as ws:
            cdp = Cdp(ws)
            cdp.call(
                "Emulation.setDeviceMetricsOverride",
                width=width,
                height=height,
                deviceScaleFactor=1,
                mobile=False,
            )
            cdp.call("Network.enable")
            cdp.call("Page.enable")
            yield cdp
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


def open_page(cdp: Cdp, url: str, ready: str = "document.readyState === 'complete'") -> None:
    """Navigate and wait until ``ready`` holds."""
    cdp.requests.clear()
    cdp.call("Page.navigate", url=url)
    cdp.wait(ready, 30.0)
