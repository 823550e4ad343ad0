"""The frame faults of issue #26 in real time through the CAN hub.

The lock-step suite (:mod:`tests.fault_suite`) waits for every backlog, so a flood there only
shows that nothing breaks. Here the same pair runs on the wall clock as separate processes,
as on a pack: ``packpilot can-hub`` (the bus), ``packpilot run`` (the BMS, recording to
SQLite), the twin (``hil``'s :class:`~packpilot.runtime.hil.Hil` in a thread of this process, so
every period's supply and battery currents can be read from its plant, with the switch nodes
keeping the discharge path on their timeout as the lock-step suite's do), an **intruder**
process that puts the fault's frames on the bus through the hub (a third node: the same frames
as the lock-step suite's ``load_10x`` / ``flood`` hooks), and a **probe** process that measures
the hub's latency (a frame sent, the same frame received by a second client) throughout.

Measured per fault: the longest time the load was without supply, the largest charge current
into a battery against its limit, when the BMS detected the fault (and the documented bound),
whether every BMS period was recorded, the BMS's step time and the age of the telemetry it
read, the hub's latency, and the peak memory (VmHWM) of the hub and of ``run``.

``python -m tests.fault_realtime`` (part of ``make faults``, ~2.5 min: real time) prints the
table; exit 1 on an acceptance miss. Not in ``make test``: each fault needs its own minute.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.io.can.bus import open_bus
from packpilot.io.telemetry import load_run
from packpilot.runtime.bms import filters
from packpilot.runtime.hil import Hil, run_realtime
from packpilot.runtime.lockstep import REQUEST_ONLY
from tests import fault_suite as fs

ROOT = Path(__file__).resolve().parents[1]
DT = fs.DT
CLI = [sys.executable, "-m", "packpilot.cli"]
PROBE_ID = 0x7E1
"""The probe's identifier (nobody's: the BMS counts it ``unexpected``, the twin ignores it)."""


@dataclass
class RtFault:
    name: str
    at_s: float
    """Twin time (s) the intruder starts."""
    until_s: float
    end_s: float
    fps: float
    """Frames per second the intruder sends (0: as fast as it can)."""
    ids: tuple[int, ...]
    detect: tuple[str, ...] = ()
    bound_s: float = math.inf
    """Detection bound from ``at_s`` (inf: nothing is documented to be detected)."""


def faults() -> list[RtFault]:
    """The lock-step suite's two frame faults, on the wall clock. Both batteries are joined
    from 85.2 s in uav_mission; the faults start at 20 s (A alone supplies, B stands by) so
    that one run takes a minute, not two."""
    return [
        RtFault("30 s of 10x frame load", 20.0, 50.0, 60.0, fps=15 * 9 / DT,
                ids=tuple(0x30A + k for k in range(5))),
        RtFault("35 s frame flood (a babbling node, 3000 frames per 0.2 s)", 20.0, 55.0, 65.0,
                fps=3000 / DT, ids=(0x7F0,)),
        RtFault("35 s frame flood, as fast as the node's socket takes them", 20.0, 55.0, 65.0,
                fps=0.0, ids=(0x7F0,)),
    ]


@dataclass
class RtOutcome:
    fault: RtFault
    unsupplied_s: float
    max_charge_a: float
    limit_a: float
    detected_s: float
    events: list[tuple[float, str]]
    recorded: int
    bms: dict[str, Any]
    hub: dict[str, Any]
    probe: dict[str, Any]
    intruder: dict[str, Any]
    hub_peak_mb: float
    run_peak_mb: float
    twin_periods: int
    switch_timeouts: int
    max_charge_at_s: float = math.nan
    before_bms_a: float = 0.0
    """Largest charge current into a battery before the BMS's first period (not judged)."""
    bms_start_s: float = math.nan

    def row(self) -> str:
        f = self.fault
        det = "—" if math.isinf(self.detected_s) else f"{self.detected_s:.1f} s"
        bound = "nothing to detect" if math.isinf(f.bound_s) else f"≤ {f.bound_s:.1f} s"
        b, p = self.bms, self.probe
        sent = self.intruder.get("sent", 0)
        return (
            f"| {f.name} | {sent:,} frames ({sent / max(f.until_s - f.at_s, 1e-9):,.0f}/s) | "
            f"{det} ({bound}) | {self.unsupplied_s:.1f} s | "
            f"{self.max_charge_a:.2f} A / {self.limit_a:.1f} A | "
            f"{self.recorded} / {b.get('steps', 0)} | "
            f"{b.get('step_p50_ms', math.nan):.2f} / {b.get('step_p99_ms', math.nan):.1f} / "
            f"{b.get('step_max_ms', math.nan):.0f} ms | "
            f"{b.get('can_frame_age_p50_ms', math.nan):.1f} / "
            f"{b.get('can_frame_age_p99_ms', math.nan):.1f} / "
            f"{b.get('can_frame_age_max_ms', math.nan):.0f} ms | "
            f"{p.get('p50_ms', math.nan):.2f} / {p.get('p99_ms', math.nan):.1f} / "
            f"{p.get('max_ms', math.nan):.0f} ms | "
            f"{self.hub_peak_mb:.0f} / {self.run_peak_mb:.0f} MB |"
        )


HEADER = (
    "| fault (uav_mission, real time, 0.2 s periods, through the hub) | intruder sent | "
    "detected after (documented) | longest unsupplied | max charge current / limit | "
    "periods recorded / run | BMS step p50 / p99 / max | telemetry age at the BMS p50 / p99 "
    "/ max | hub latency p50 / p99 / max | peak RSS hub / run |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


# ----------------------------------------------------------------------------- processes
def _hello(sock: socket.socket, channel: str, raw: bool) -> None:
    """socketcand's handshake (``< hi >``, open, optionally rawmode), as python-can does it."""
    def expect(what: bytes) -> None:
        got = b""
        while not got.endswith(b">"):
            chunk = sock.recv(64)
            if not chunk:
                raise ConnectionError("hub closed the connection")
            got += chunk
        if got.strip() != what:
            raise ConnectionError(f"hub said {got!r}, expected {what!r}")

    expect(b"< hi >")
    sock.sendall(f"< open {channel} >".encode())
    expect(b"< ok >")
    if raw:
        sock.sendall(b"< rawmode >")
        expect(b"< ok >")


def intrude(port: int, fps: float, seconds: float, ids: list[int]) -> dict[str, Any]:
    """A third node: ``fps`` frames per second (0: as fast as the socket takes them) of 8 zero
    bytes on ``ids`` in turn for ``seconds``, sent in 10 ms bursts. It opens the channel but
    never asks for raw mode, so the hub sends it nothing (a node that only talks)."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    _hello(sock, "pack", raw=False)
    frames = [f"< send {i:03X} 8 0 0 0 0 0 0 0 0 >".encode() for i in ids]
    sent = 0
    t0 = time.monotonic()
    tick = 0.01
    while (now := time.monotonic()) - t0 < seconds:
        due = len(frames) * 200 if fps <= 0 else round((now - t0 + tick) * fps) - sent
        if due > 0:
            burst = b"".join(frames[(sent + k) % len(frames)] for k in range(due))
            sock.sendall(burst)
            sent += due
        if fps > 0:
            time.sleep(max(0.0, t0 + (sent / fps) - tick - time.monotonic()) or tick / 2)
    sock.close()
    return {"sent": sent, "seconds": time.monotonic() - t0}


def probe(port: int, seconds: float, hz: float = 20.0) -> dict[str, Any]:
    """The hub's latency: a frame sent every 1/``hz`` s by one client, received by another
    (raw mode, reading everything the channel carries, flood included) — the wall time
    between the two."""
    tx = socket.create_connection(("127.0.0.1", port))
    tx.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    _hello(tx, "pack", raw=False)
    rx = socket.create_connection(("127.0.0.1", port))
    _hello(rx, "pack", raw=True)
    rx.sendall(b"< send 7E2 0 >")  # it read its ok: the hub joins it at once
    sent: dict[int, float] = {}
    lat: list[float] = []
    stop = threading.Event()
    marker = f"< frame {PROBE_ID:03X} ".encode()

    def read() -> None:
        buf = b""
        rx.settimeout(0.5)
        while not stop.is_set():
            try:
                chunk = rx.recv(1 << 20)
            except TimeoutError:
                continue
            if not chunk:
                return
            now = time.monotonic()
            buf = buf[-64:] + chunk
            pos = 0
            while (i := buf.find(marker, pos)) >= 0:
                end = buf.find(b">", i)
                if end < 0:
                    break
                data = buf[i:end].split()[-1]
                seq = int(data, 16)
                if seq in sent:
                    lat.append(now - sent.pop(seq))
                pos = end
            buf = buf[pos:]

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < seconds:
        k += 1
        sent[k] = time.monotonic()
        tx.sendall(f"< send {PROBE_ID:03X} 4 {' '.join(f'{b:X}' for b in k.to_bytes(4, 'big'))} >"
                   .encode())  # fmt: skip
        time.sleep(1.0 / hz)
    time.sleep(1.0)
    stop.set()
    reader.join(2.0)
    tx.close()
    rx.close()
    ms = np.array(lat) * 1e3
    if not ms.size:
        return {"sent": k, "received": 0}
    return {"sent": k, "received": int(ms.size), "p50_ms": float(np.percentile(ms, 50)),
            "p99_ms": float(np.percentile(ms, 99)), "max_ms": float(ms.max())}  # fmt: skip


def peak_mb(pid: int) -> float:
    """VmHWM (peak resident set) of a live process, in MB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return math.nan


def _child(args: list[str], out: Path) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT),
                                                        os.environ.get("PYTHONPATH", "")])}
    return subprocess.Popen(args, stdout=out.open("w"), stderr=subprocess.STDOUT, text=True,
                            env=env, cwd=ROOT)  # fmt: skip


def _stop(p: subprocess.Popen[str] | None) -> None:
    if p is not None and p.poll() is None:
        p.terminate()
        try:
            p.wait(10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _json_tail(path: Path) -> dict[str, Any]:
    """The last JSON object a child printed (its summary)."""
    text = path.read_text()
    start = text.rfind("\n{")
    start = 0 if start < 0 and text.startswith("{") else start
    try:
        out: dict[str, Any] = json.loads(text[start:])
        return out
    except (ValueError, IndexError):
        return {}


# ----------------------------------------------------------------------------- one fault
def measure(f: RtFault, tmp: Path, bitrate: float | None = None) -> RtOutcome:
    """Run ``f`` in real time through a hub of its own; everything stopped before returning."""
    cfg = fs.config()
    hub_out, run_out = tmp / "hub.out", tmp / "run.out"
    rate = [] if bitrate is None else ["--bitrate", str(bitrate)]
    hub = _child([*CLI, "can-hub", "--port", "0", *rate], hub_out)
    run = intruder = prober = None
    twin_bus = charger_bus = None
    stop = threading.Event()
    twin_thread = None
    try:
        port = _port(hub, hub_out)
        kw = {"host": "127.0.0.1", "port": port}
        twin_bus = open_bus("socketcand", "pack", **kw)
        charger_bus = open_bus("socketcand", "charger", **filters("socketcand", REQUEST_ONLY),
                               **kw)  # fmt: skip
        twin = Hil(cfg, twin_bus, charger_bus=charger_bus, bms_period_s=DT,
                   timeout_keeps_discharge=True)  # fmt: skip
        log: list[tuple[float, bool, np.ndarray]] = []
        # after each period's telemetry: the plant as it is now (currents of the interval
        # just stepped, whether the load was supplied over it)
        twin.hooks.append(lambda h, t: log.append((
            t, h.last_iv is None or bool(h.last_iv.supplied[0]), h.m.bat.current_a[0].copy())))
        twin_thread = threading.Thread(target=run_realtime, args=(twin, DT, f.end_s, 1.0, stop),
                                       daemon=True)  # fmt: skip
        twin_thread.start()
        db = tmp / "run.sqlite"
        bus = ["--can-interface", "socketcand", "--can-channel", "pack", "--charger-channel",
               "charger", "--can-arg", "host=127.0.0.1", "--can-arg", f"port={port}"]  # fmt: skip
        run = _child([*CLI, "run", "uav_mission", *bus, "--period", str(DT), "--db", str(db),
                      "--json"], run_out)  # fmt: skip
        prober = _child([sys.executable, "-m", "tests.fault_realtime", "probe", "--port",
                         str(port), "--seconds", str(f.end_s - 3.0)],
                        tmp / "probe.out")  # fmt: skip
        bms_start = math.nan
        while twin.t_s < f.at_s - 1e-9:
            _alive(run, run_out)
            if math.isnan(bms_start) and "packpilot run:" in run_out.read_text():
                bms_start = twin.t_s  # its first period follows within a period or two
            time.sleep(0.02)
        intruder = _child([sys.executable, "-m", "tests.fault_realtime", "intrude", "--port",
                           str(port), "--fps", str(f.fps), "--seconds", str(f.until_s - f.at_s),
                           "--ids", *[str(i) for i in f.ids]], tmp / "intruder.out")  # fmt: skip
        twin_thread.join(f.end_s + 60.0)
        run_peak = peak_mb(run.pid)
        hub_peak = peak_mb(hub.pid)
        _stop(run)
        for p in (intruder, prober):
            if p is not None:
                p.wait(30)
        _stop(hub)
    finally:
        stop.set()
        if twin_thread is not None:
            twin_thread.join(5.0)
        for p in (run, intruder, prober, hub):
            _stop(p)
        for b in (twin_bus, charger_bus):
            if b is not None:
                b.shutdown()
    return _outcome(f, twin, log, db, run_out, tmp, hub_out, hub_peak, run_peak, bms_start)


def _hub_stats(out: Path) -> dict[str, Any]:
    """The counters ``can-hub`` prints when it stops (``can-hub: connections 5, ...``)."""
    for line in out.read_text().splitlines():
        if line.startswith("can-hub: "):
            return {k: int(v) for k, v in (w.rsplit(" ", 1) for w in line[9:].split(", "))}
    return {}


def _port(hub: subprocess.Popen[str], out: Path) -> int:
    deadline = time.monotonic() + 60.0
    while time.monotonic() < deadline:
        text = out.read_text() if out.exists() else ""
        if "can-hub on" in text:
            return int(text.split("can-hub on ", 1)[1].split()[0].rsplit(":", 1)[1])
        if hub.poll() is not None:
            raise RuntimeError(f"can-hub exited: {text}")
        time.sleep(0.05)
    raise RuntimeError("can-hub did not start")


def _alive(p: subprocess.Popen[str], out: Path) -> None:
    if p.poll() is not None:
        raise RuntimeError(f"run exited early ({p.returncode}): {out.read_text()[-2000:]}")


def _outcome(f: RtFault, twin: Hil, log: list[tuple[float, bool, np.ndarray]], db: Path,
             run_out: Path, tmp: Path, hub_out: Path, hub_peak: float,
             run_peak: float, offset: float) -> RtOutcome:  # fmt: skip
    stored = load_run(db)
    bms = _json_tail(run_out)
    # the BMS's clock starts with run: its events go on the twin's time axis by the twin's
    # time when run said it starts (its banner; the first period follows at once, the twin's
    # telemetry being already on the bus): good to a period or two
    events = [(e.t_s, fs.event_key(e)) for e in stored.events]
    # judged from the BMS's first period on: before it, the twin's switches are as configured
    # (and after its nodes' 1 s timeout, charge paths open) with no BMS on the bus
    mine = [x for x in log if x[0] >= offset + 2 * DT]
    longest = run = 0
    for _, ok, _cur in mine:
        run = 0 if ok else run + 1
        longest = max(longest, run)
    cur = np.array([c for _, _, c in mine])
    into = np.maximum(-cur, 0.0) if cur.size else np.zeros((1, 1))
    before = np.array([c for t, _, c in log if t < offset + 2 * DT])
    cap = float(min(twin.plant.infos[0].capacity_ah))
    det = [t + offset - f.at_s for t, k in events if k in f.detect and t + offset >= f.at_s]
    return RtOutcome(
        fault=f, unsupplied_s=longest * DT,
        max_charge_a=float(into.max()),
        max_charge_at_s=float(mine[int(np.argmax(into.max(axis=1)))][0]) if mine else math.nan,
        before_bms_a=float(np.max(np.maximum(-before, 0.0))) if before.size else 0.0,
        bms_start_s=offset,
        limit_a=fs.CHARGE_LIMIT_C * cap, detected_s=min(det, default=math.inf),
        events=[(round(t + offset, 1), k) for t, k in events],
        recorded=int(stored.metrics["steps"]),
        bms=bms, hub=_hub_stats(hub_out), probe=_json_tail(tmp / "probe.out"),
        intruder=_json_tail(tmp / "intruder.out"), hub_peak_mb=hub_peak, run_peak_mb=run_peak,
        twin_periods=len(log), switch_timeouts=sum(n.timeouts for n in twin.switch),
    )  # fmt: skip


# ----------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd")
    a_int = sub.add_parser("intrude")
    a_int.add_argument("--port", type=int, required=True)
    a_int.add_argument("--fps", type=float, required=True)
    a_int.add_argument("--seconds", type=float, required=True)
    a_int.add_argument("--ids", type=int, nargs="+", required=True)
    a_pr = sub.add_parser("probe")
    a_pr.add_argument("--port", type=int, required=True)
    a_pr.add_argument("--seconds", type=float, required=True)
    ap.add_argument("--only", nargs="*", help="faults whose name contains one of these")
    ap.add_argument("--hub-bitrate", type=float, default=None,
                    help="can-hub --bitrate (default: the hub's, 500 kbit/s; 0: no cap, as "
                    "before issue #26's fix)")  # fmt: skip
    a = ap.parse_args(argv)
    if a.cmd == "intrude":
        print(json.dumps(intrude(a.port, a.fps, a.seconds, a.ids)))
        return 0
    if a.cmd == "probe":
        print(json.dumps(probe(a.port, a.seconds)))
        return 0
    print(HEADER)
    bad = []
    for f in faults():
        if a.only and not any(n in f.name for n in a.only):
            continue
        with tempfile.TemporaryDirectory() as tmp:
            o = measure(f, Path(tmp), a.hub_bitrate)
        print(o.row(), flush=True)
        print(f"  events: {[e for e in o.events if not e[1].startswith('Balancing')]}",
              file=sys.stderr)  # fmt: skip
        print(f"  bms: {o.bms}\n  hub: {o.hub}\n  probe: {o.probe}\n  intruder: {o.intruder}"
              f"\n  twin periods {o.twin_periods}, switch timeouts {o.switch_timeouts}, "
              f"BMS from twin t {o.bms_start_s:.1f} s, max charge at {o.max_charge_at_s:.1f} s, "
              f"{o.before_bms_a:.2f} A before the BMS",
              file=sys.stderr)  # fmt: skip
        if o.unsupplied_s > DT + 1e-9:
            bad.append(f"{f.name}: unsupplied {o.unsupplied_s:.1f} s")
        if o.max_charge_a > o.limit_a:
            bad.append(f"{f.name}: {o.max_charge_a:.2f} A into a battery")
        if o.detected_s > f.bound_s + 1e-6:
            bad.append(f"{f.name}: detected after {o.detected_s:.1f} s")
        if o.recorded != o.bms.get("steps"):
            bad.append(f"{f.name}: {o.recorded} periods recorded of {o.bms.get('steps')}")
    for line in bad:
        print(f"faults: acceptance not met: {line}", file=sys.stderr)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
