"""`run` against `hil` in real time: two threads on one python-can ``virtual`` channel, each
on its own monotonic clock; and the two-process form over SocketCAN ``vcan`` where the kernel
has it."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.runtime.bms import BmsRuntime
from packpilot.runtime.hil import Hil
from packpilot.runtime.realtime import run_against_twin


def uav(dt_s: float) -> ScenarioConfig:
    cfg = load_config(scenario_path(Path("uav_mission")))
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"dt_s": dt_s})})


def realtime(period_s: float, seconds: float, channel: str) -> tuple[BmsRuntime, Hil, dict]:
    """The twin and the BMS each stepping every ``period_s``, for ``seconds`` of wall time."""
    return run_against_twin(uav(period_s), period_s, seconds, channel)


def test_realtime_100ms() -> None:
    bms, hil, m = realtime(0.1, 4.0, "rt-100")
    assert m["periods"] == m["steps"] >= 37
    assert m["step_p50_ms"] < 10.0  # the BMS step well inside the period
    assert m["overruns"] <= 3  # a 2-core machine shared with other test workers may stall
    assert m["can_malformed"] == m["can_unexpected"] == 0
    assert sum(n.timeouts for n in hil.switch) == 0  # no switch node ever timed out
    assert not [e for e in bms.events if e.kind == "Fault"]  # telemetry always fresh
    assert hil.commands >= 0.9 * m["can_sent"]
    assert hil.inverter.last["Pylon_Limits"]["DischargeCurrentLimit"] > 0


def test_realtime_10ms() -> None:
    _bms, hil, m = realtime(0.01, 3.0, "rt-10")
    assert m["steps"] >= 250
    assert m["step_p50_ms"] < 10.0
    assert sum(n.timeouts for n in hil.switch) == 0 or m["overruns"] > 0
    assert m["can_malformed"] == 0


def has_vcan() -> str | None:
    """None if a vcan interface can be used here, else why not."""
    if not sys.platform.startswith("linux") or shutil.which("ip") is None:
        return "SocketCAN needs Linux and iproute2"
    out = subprocess.run(["ip", "-details", "link", "show", "type", "vcan"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    if out.returncode != 0 or "vcan" not in out.stdout:
        return ("no vcan interface: this kernel has no vcan module ('ip link add dev vcan0 "
                "type vcan' -> 'Unknown device type'); run and hil then share one process")
    return None


@pytest.mark.skipif(has_vcan() is not None, reason=str(has_vcan()))
def test_two_processes_over_vcan(tmp_path: Path) -> None:  # pragma: no cover - needs vcan
    """`packpilot hil` and `packpilot run` as two processes on vcan0."""
    py = [sys.executable, "-m", "packpilot.cli"]
    twin = subprocess.Popen([*py, "hil", "uav_mission", "--can-interface", "socketcan",
                             "--can-channel", "vcan0", "--duration", "8"])  # fmt: skip
    run = subprocess.run([*py, "run", "uav_mission", "--can-interface", "socketcan",
                          "--can-channel", "vcan0", "--duration", "5", "--json"],
                         capture_output=True, text=True, check=False)  # fmt: skip
    twin.wait(timeout=60)
    assert run.returncode == 0, run.stderr
    assert '"can_received"' in run.stdout
