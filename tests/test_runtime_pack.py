"""The pack as one battery, end to end: what the twin's inverter and aircraft nodes decode from
the BMS's frames (cantools on pylon.dbc, the dronecan package) follows the core."""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.io.can import battery as bc
from packpilot.io.can import dronecan_io as dc
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.hil import Hil, report
from packpilot.runtime.lockstep import Lockstep, lockstep

DT = 0.2


@pytest.fixture(scope="module")
def cfg() -> ScenarioConfig:
    return load_config(scenario_path(Path("uav_mission")))


def run(
    cfg: ScenarioConfig, end_s: float, act: object = None, opts: RuntimeOptions | None = None,
    proxy: object = None,
) -> tuple[Lockstep, list]:
    """Lock-step to ``end_s``; ``act(hil, bus, t)`` after each period's telemetry;
    ``proxy(hil, frames, t)`` rewrites the twin's frames on the wire."""
    ls = lockstep(cfg, opts or RuntimeOptions())
    if proxy is not None:
        ls.hil.proxies.append(proxy)  # type: ignore[arg-type]
    bus = can.Bus(interface="virtual", channel=ls.bms.opts.channel)
    if act is not None:
        ls.hil.hooks.append(lambda h, t: act(h, bus, t))  # type: ignore[operator]
    try:
        for _ in range(round(end_s / DT)):
            ls.step(DT)
    finally:
        ls.close()
        bus.shutdown()
    return ls, ls.hil.inverter.frames


def limits_at(frames: list, t0: float, t1: float) -> list[dict]:
    return [v for t, name, v in frames if name == "Pylon_Limits" and t0 <= t < t1]


def test_limits_follow_the_batteries_connected(cfg: ScenarioConfig) -> None:
    """B's telemetry lost at 100 s: B is isolated and the discharge limit the inverter reads
    drops to A's alone (n_conducting x weakest: 2 x A and B before, 1 x A after)."""

    def silence(h: Hil, bus: can.BusABC, t: float) -> None:
        h.silent = {1} if 100.0 <= t < 120.0 else set()

    _ls, frames = run(cfg, 115.0, silence)
    before = limits_at(frames, 95.0, 100.0)
    during = limits_at(frames, 105.0, 115.0)
    assert before and during
    dcl0 = before[-1]["DischargeCurrentLimit"]
    dcl1 = during[-1]["DischargeCurrentLimit"]
    assert 0 < dcl1 < 0.7 * dcl0
    soc = [v for t, n, v in frames if n == "Pylon_SocSoh"][-1]
    assert 0 < soc["SOC"] <= 100 and 0 < soc["SOH"] <= 100
    alarms = [v for t, n, v in frames if n == "Pylon_Alarms"][-1]
    assert alarms["ModuleCount"] == 2


def test_limits_drop_to_zero_on_a_trip(cfg: ScenarioConfig) -> None:
    """Both batteries report 62 degC from 100 s: the over-temperature discharge trip (60 degC)
    → discharge limit 0 A, the protection bit, discharge enable off at the inverter."""

    def hot(h: Hil, out: list[can.Message], t: float) -> list[can.Message]:
        """The nodes' own state frames (their alive counter intact: an intruder's frame
        with another counter is dropped since #26) rewritten to 62 degC."""
        if t < 100.0:
            return out
        for j, m in enumerate(out):
            if m.arbitration_id in (0x310, 0x311):
                k = m.arbitration_id - 0x310
                r = report(h.m.bat, k)
                r.temp_c = 62.0
                out[j] = bc.encode_battery(k, r, h.counter - 1, t)[2]
        return out

    _ls, frames = run(cfg, 110.0, proxy=hot)
    before = limits_at(frames, 95.0, 100.0)
    assert before[-1]["DischargeCurrentLimit"] > 0
    after = limits_at(frames, 106.0, 110.0)
    assert after and all(v["DischargeCurrentLimit"] == 0 for v in after)
    alarms = [v for t, n, v in frames if n == "Pylon_Alarms" and t >= 106.0]
    assert all(v["ProtOverTemp"] == 1 for v in alarms)
    req = [v for t, n, v in frames if n == "Pylon_Request" and t >= 106.0]
    assert all(v["DischargeEnable"] == 0 for v in req)


def test_dronecan_battery_info_for_pack_and_batteries(cfg: ScenarioConfig) -> None:
    ls, _ = run(cfg, 100.0)
    air = ls.hil.aircraft
    assert air.errors == 0 and set(air.last) == {0, 1, 2}
    m = ls.bms.core.m
    for i in (1, 2):
        info = air.last[i]
        assert info.voltage_v == pytest.approx(float(m.bat.voltage_v[0, i - 1]), abs=0.05)
        assert info.status_flags & dc.IN_USE
    pack = air.last[0]
    assert pack.current_a == pytest.approx(float(m.bat.current_a[0].sum()), abs=0.1)
    assert 0 < pack.soc_pct <= 100
    prot = ls.hil.protection
    assert prot["Mode"] == 2  # discharge
    assert 0 <= prot["AllowanceUsed"] < 1


def test_replay_of_a_recorded_frame_log(cfg: ScenarioConfig, tmp_path: Path) -> None:
    """`run --can-log` writes every frame; `run --replay-log` re-runs the BMS over the frames
    it received and makes the same decisions at the same times."""
    from packpilot.runtime.logreplay import received_frames, replay_log

    log = tmp_path / "run.blf"
    ls, _ = run(cfg, 100.0, opts=RuntimeOptions(log_path=log))
    rx = received_frames(log)
    assert rx and all(m.is_rx for _, m in rx)
    assert {m.arbitration_id for _, m in rx} >= {0x300, 0x301, 0x220, 0x18FF50E5}
    again = replay_log(cfg, log, RuntimeOptions(period_s=DT))
    assert [(round(e.t_s, 6), e.kind, e.battery) for e in again.events] == [
        (round(e.t_s, 6), e.kind, e.battery) for e in ls.bms.events
    ]
    assert again.plant.counters.malformed == 0


def test_replay_can_on_the_command_line(cfg: ScenarioConfig, tmp_path: Path) -> None:
    """`packpilot replay can LOG CONFIG` (and `run --replay-log`, the same code) re-runs the
    BMS over a frame log from the command line: the events of the recorded run, recorded to
    SQLite; a missing, empty or foreign log is one line and exit code 2."""
    import json
    import sqlite3
    import subprocess
    import sys

    log = tmp_path / "run.asc"
    ls, _ = run(cfg, 60.0, opts=RuntimeOptions(log_path=log))
    cli = [sys.executable, "-m", "packpilot.cli"]
    db = tmp_path / "again.sqlite"
    proc = subprocess.run([*cli, "replay", "can", str(log), "uav_mission", "--period", str(DT),
                           "--db", str(db), "--json"],
                          capture_output=True, text=True, timeout=300, check=False)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    m = json.loads(proc.stdout)
    assert m["steps"] == round(60.0 / DT) and m["can_malformed"] == 0
    with sqlite3.connect(db) as c:
        kinds = [r[0] for r in c.execute("select kind from events order by id")]
        status = c.execute("select status from runs").fetchone()[0]
    assert kinds == [e.kind for e in ls.bms.events] and kinds
    assert status == "ok"
    same = subprocess.run([*cli, "run", "uav_mission", "--replay-log", str(log), "--period",
                           str(DT), "--json"],
                          capture_output=True, text=True, timeout=300, check=False)  # fmt: skip
    assert same.returncode == 0, same.stderr
    assert json.loads(same.stdout)["steps"] == m["steps"]

    empty = tmp_path / "empty.asc"
    can.ASCWriter(empty).stop()
    for bad, why in ((tmp_path / "none.blf", "cannot read the frame log"),
                     (empty, "no frame the BMS received"),
                     (tmp_path / "x.csv", "unsupported frame log format")):  # fmt: skip
        argv = [*cli, "replay", "can", str(bad), "uav_mission"]
        bad_proc = subprocess.run(argv, capture_output=True, text=True, timeout=300, check=False)
        assert bad_proc.returncode == 2, (bad, bad_proc.stderr)
        lines = bad_proc.stderr.strip().splitlines()
        assert len(lines) == 1 and why in lines[0], lines


def test_dronecan_batteries_as_inputs(cfg: ScenarioConfig) -> None:
    """Both batteries report by DroneCAN BatteryInfo + BatteryInfoAux (decoded by the dronecan
    package), their switch nodes' SwitchState is the feedback: the flight runs on them (float16
    telemetry: no fault, load supplied, both batteries joined); a silent DroneCAN battery goes
    stale and is isolated like any other."""

    def drive(end_s: float, silent_from: float | None = None) -> Lockstep:
        ls = lockstep(cfg, RuntimeOptions(dronecan_ids=(21, 22)))  # the twin publishes them
        try:
            for _ in range(round(end_s / DT)):
                if silent_from is not None and ls.hil.t_s >= silent_from - 1e-9:
                    ls.hil.silent = {1}
                ls.step(DT)
        finally:
            ls.close()
        return ls

    ls = drive(120.0)
    c = ls.bms.plant.counters
    assert c.malformed == 0 and c.received > 0 and ls.bms.plant.assembler.errors == 0
    assert not [e for e in ls.bms.events if e.kind == "Fault"]
    assert all(ls.supplied)
    assert any(e.kind == "BatteryJoined" for e in ls.bms.events)
    m = ls.bms.core.m
    assert m.bat.n_groups[0].tolist() == [6, 6]  # the cells from BatteryInfoAux
    assert abs(float(m.bat.max_cell_v[0, 0]) - 4.0) < 0.3
    lost = drive(110.0, silent_from=100.0)
    stale = [e for e in lost.bms.events if e.kind == "Fault" and e.data["kind"] == "stale"]
    assert [e.battery for e in stale] == [1]
    assert not lost.chg[-1][1] and not lost.dsg[-1][1]


def half_step(x: np.ndarray) -> np.ndarray:
    """Half a float16 step at ``x``: the most round-to-nearest moves it."""
    return np.spacing(np.abs(x).astype(np.float16)).astype(np.float64) / 2 + 1e-9


def test_dronecan_values_at_the_bms(cfg: ScenarioConfig) -> None:
    """What the BMS reads from DroneCAN batteries is what the twin measured, within the
    wire's resolution, every period: voltage, current, cells within half a float16 step
    (unit, sign and scale right), temperature within half a step of its kelvin, SOC within
    half a percent, the capacities from BatteryInfo's Wh over BatteryInfoAux's nominal
    voltage (they were left unknown: the inverter was told SOC 0 %, SOH 0 %, the aircraft no
    time to empty, for a pack at 86 %)."""
    ls = lockstep(cfg, RuntimeOptions(dronecan_ids=(21, 22)))
    assert ls.hil.dronecan_ids == {0: 21, 1: 22}
    got, truth = ls.bms.core.m.bat, ls.hil.m.bat
    try:
        for _ in range(round(30.0 / DT)):
            ls.step(DT)  # the twin's m: what it published this period; the core's: what it read
            for name in ("voltage_v", "current_a", "min_cell_v", "max_cell_v"):
                want = getattr(truth, name)[0]
                assert np.all(np.abs(getattr(got, name)[0] - want) <= half_step(want)), name
            kelvin = truth.temp_c[0] + 273.15
            assert np.all(np.abs(got.temp_c[0] - truth.temp_c[0]) <= half_step(kelvin))
            assert np.all(np.abs(got.soc[0] - truth.soc[0]) <= 0.005 + 1e-12)
            g = truth.group_v[0, :, :6]
            assert np.all(np.abs(got.group_v[0, :, :6] - g) <= half_step(g))
    finally:
        ls.close()
    for name in ("full_capacity_ah", "remaining_capacity_ah"):
        want = getattr(truth, name)[0]
        # float16 Wh: 2^-4 Wh steps at 64-128 Wh over ~22 V: 1.4 mAh
        assert getattr(got, name)[0] == pytest.approx(want, abs=0.002)
    soc = 100.0 * truth.remaining_capacity_ah[0].sum() / truth.full_capacity_ah[0].sum()
    pylon_soc = ls.hil.inverter.last["Pylon_SocSoh"]
    assert abs(pylon_soc["SOC"] - soc) <= 1.0 and pylon_soc["SOH"] == 100
    assert ls.hil.aircraft.last[0].soc_pct == pytest.approx(soc, abs=1.0)
    assert 0 < ls.hil.protection["TimeToEmpty"] < 65535
