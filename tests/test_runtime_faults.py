"""Bus faults against the runtime (lock-step `run` against `hil`, real virtual buses): each is
detected, leads to the safe state documented in docs/runtime.md, the run goes on logging and
nothing crashes.

uav_mission in flight (both batteries joined from t = 85 s); faults from t = 100 s.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
import pytest

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.bms import Event
from packpilot.io.can import battery as bc
from packpilot.io.telemetry import SQLiteRecorder
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.hil import PLATFORM, Hil, SwitchNode, report
from packpilot.runtime.lockstep import Lockstep, lockstep

DT = 0.2
FAULT_S = (100.0, 110.0)
END_S = 130.0


@pytest.fixture(scope="module")
def cfg() -> ScenarioConfig:
    return load_config(scenario_path(Path("uav_mission")))


def during(t: float) -> bool:
    return FAULT_S[0] - 1e-9 <= t < FAULT_S[1] - 1e-9


def drive(
    cfg: ScenarioConfig,
    hook: Callable[[Lockstep, float], bool] | None = None,
    intrude: Callable[[Hil, can.BusABC, float], None] | None = None,
    recorder: SQLiteRecorder | None = None,
) -> Lockstep:
    """Lock-step to END_S; ``hook`` may step the period itself (returns True); ``intrude``
    sends from a third node after the twin's telemetry went out."""
    ls = lockstep(cfg, RuntimeOptions(), recorder)
    bus = can.Bus(interface="virtual", channel=ls.bms.opts.channel)
    if intrude is not None:
        ls.hil.hooks.append(lambda h, t: intrude(h, bus, t))
    try:
        for _ in range(round(END_S / DT)):
            if hook is None or not hook(ls, ls.hil.t_s):
                ls.step(DT)
    finally:
        ls.close()
        bus.shutdown()
    return ls


def faults(ls: Lockstep, kind: str) -> list[Event]:
    return [e for e in ls.bms.events if e.kind == "Fault" and e.data.get("kind") == kind]


def at(ls: Lockstep, t: float) -> int:
    return round(t / DT)


def no_switch_faults(ls: Lockstep) -> bool:
    return not [e for e in ls.bms.events if e.kind == "Fault" and "fet" in str(e.data["kind"])]


def test_telemetry_loss_of_one_battery(cfg: ScenarioConfig, tmp_path: Path) -> None:
    """Battery B falls silent: stale after max_sample_age_s (2 s), isolated (A supplies)."""

    def hook(ls: Lockstep, t: float) -> bool:
        ls.hil.silent = {1} if during(t) else set()
        return False

    rec = SQLiteRecorder(tmp_path / "run.sqlite", flush_every=50)
    ls = drive(cfg, hook, recorder=rec)
    rec.close()
    (stale,) = faults(ls, "stale")
    assert stale.battery == 1
    fts = 2.0 + 2 * DT  # max_sample_age_s, then one period to see it and one to act
    assert FAULT_S[0] < stale.t_s <= FAULT_S[0] + fts
    k = at(ls, stale.t_s) + 1
    assert not ls.chg[k][1] and not ls.dsg[k][1]  # isolated
    assert ls.dsg[k][0]  # the healthy battery keeps supplying
    assert all(ls.supplied)
    assert no_switch_faults(ls)
    assert any(e.kind == "FaultCleared" and e.battery == 1 for e in ls.bms.events)
    assert ls.chg[-1][1] and ls.dsg[-1][1]  # rejoined after 5 s of fresh data
    with sqlite3.connect(tmp_path / "run.sqlite") as db:
        (rows,) = db.execute("select count(*) from pack_samples").fetchone()
    assert rows == round(END_S / DT)  # logging went on through the fault


def test_telemetry_loss_of_all_batteries(cfg: ScenarioConfig) -> None:
    """Every battery silent in flight: the last-source rule (MOSFET pairs): charge paths open,
    discharge left alone — the load stays supplied (and the supervisor goes to fault)."""

    def hook(ls: Lockstep, t: float) -> bool:
        ls.hil.silent = {0, 1} if during(t) else set()
        return False

    ls = drive(cfg, hook)
    assert {e.battery for e in faults(ls, "stale")} == {0, 1}
    k = at(ls, max(e.t_s for e in faults(ls, "stale"))) + 1
    assert not ls.chg[k].any()
    assert ls.dsg[k].all()
    assert all(ls.supplied)
    assert any(e.kind == "ModeChanged" and e.data["to"] == "fault" for e in ls.bms.events)
    assert no_switch_faults(ls)


@pytest.mark.parametrize("keep_dsg", [False, True])
def test_switch_node_timeout(cfg: ScenarioConfig, keep_dsg: bool) -> None:
    """The BMS stops sending (a hung task) for 3 s: the switch nodes open after 5 periods —
    both paths by default (the load drops: why an aircraft should use the keep-discharge
    variant), only the charge path with ``timeout_keeps_discharge``; commands resume, the
    nodes obey again."""
    hang = (100.0, 103.0)

    def hook(ls: Lockstep, t: float) -> bool:
        ls.hil.keep_dsg = keep_dsg
        if hang[0] - 1e-9 <= t < hang[1] - 1e-9:
            ls.hil.publish()
            iv = ls.hil.advance(DT)
            c, d = ls.hil.gates()
            ls.chg.append(c)
            ls.dsg.append(d)
            ls.supplied.append(bool(iv.supplied[0]))
            return True
        return False

    ls = drive(cfg, hook)
    assert [n.timeouts for n in ls.hil.switch] == [1, 1]
    timeout_s = 5 * DT
    before = at(ls, hang[0] + timeout_s) - 1
    after = at(ls, hang[0] + timeout_s) + 1
    assert ls.dsg[before].all()
    assert not ls.chg[after].any()
    assert ls.dsg[after].all() == keep_dsg
    assert all(ls.supplied) == keep_dsg
    assert ls.chg[-1].all() and ls.dsg[-1].all()  # obeying again


def test_babbling_node(cfg: ScenarioConfig) -> None:
    """Battery A's node sends its measurement frame 10x per period: detected, its sample is
    not trusted (stale), it is isolated while B supplies; it rejoins once it is quiet."""

    def babble(h: Hil, bus: can.BusABC, t: float) -> None:
        if during(t):
            for _ in range(10):
                bus.send(bc.encode_battery(0, _report(h, 0), 0, t)[0])

    ls = drive(cfg, intrude=babble)
    assert ls.bms.plant.babbled == round((FAULT_S[1] - FAULT_S[0]) / DT)
    (stale,) = faults(ls, "stale")
    assert stale.battery == 0 and stale.t_s == pytest.approx(FAULT_S[0])
    k = at(ls, stale.t_s) + 1
    assert not ls.chg[k][0] and not ls.dsg[k][0]
    assert all(ls.supplied)
    assert any(e.kind == "FaultCleared" and e.battery == 0 for e in ls.bms.events)
    assert ls.dsg[-1][0]  # back on the bus


def test_malformed_frames_and_wrong_dlc(cfg: ScenarioConfig) -> None:
    """Frames on PackPilot identifiers that do not decode (wrong DLC, an undefined multiplexer
    block) are counted and dropped; remote, 29-bit and unknown frames are counted as
    unexpected; the telemetry around them still gets through: no fault, same switching."""
    clean = drive(cfg)
    bad = [
        can.Message(arbitration_id=0x300, is_extended_id=False, data=bytes(5)),  # DLC 5
        can.Message(arbitration_id=0x331, is_extended_id=False, data=bytes([200]) + bytes(7)),
        can.Message(arbitration_id=0x310, is_extended_id=False, is_remote_frame=True, dlc=8),
        can.Message(arbitration_id=0x310, is_extended_id=True, data=bytes(8)),
        can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)),
    ]

    def inject(h: Hil, bus: can.BusABC, t: float) -> None:
        if during(t):
            for m in bad:
                bus.send(m)

    ls = drive(cfg, intrude=inject)
    n = round((FAULT_S[1] - FAULT_S[0]) / DT)
    assert ls.bms.plant.counters.malformed == 2 * n
    assert ls.bms.plant.counters.unexpected == 3 * n
    assert [e.kind for e in ls.bms.events] == [e.kind for e in clean.bms.events]
    assert np.array_equal(np.array(ls.chg), np.array(clean.chg))


def test_out_of_range_values(cfg: ScenarioConfig) -> None:
    """Battery A reports a 6.0 V cell: out_of_range after range_delay_s, isolated; clears."""

    def inject(h: Hil, bus: can.BusABC, t: float) -> None:
        if during(t):
            r = _report(h, 0)
            r.max_cell_v = 6.0
            frames = bc.encode_battery(0, r, 0, t)
            bus.send(frames[1])  # the cells frame, after the node's own: the latest wins

    ls = drive(cfg, intrude=inject)
    (f,) = faults(ls, "out_of_range")
    assert f.battery == 0 and f.data["value"] == pytest.approx(6.0)
    assert FAULT_S[0] < f.t_s <= FAULT_S[0] + 0.5 + 2 * DT
    k = at(ls, f.t_s) + 1
    assert not ls.chg[k][0] and not ls.dsg[k][0]
    assert all(ls.supplied)
    assert any(e.kind == "FaultCleared" and e.battery == 0 for e in ls.bms.events)


# ----------------------------------------------------------------------------- helpers
def _report(h: Hil, k: int) -> bc.BatteryReport:
    """What battery ``k`` of the twin reports now."""
    return report(h.m.bat, k)


def test_platform_silent_is_a_pack_fault(cfg: ScenarioConfig) -> None:
    """No bus-voltage frame for longer than platform_timeout_s (1 s): the bus voltage reads
    NaN, the plausibility layer's pack nonfinite fault follows (0.5 s), and clears."""

    def hook(ls: Lockstep, t: float) -> bool:
        ls.hil.silent = {PLATFORM} if during(t) else set()
        return False

    ls = drive(cfg, hook)
    (f,) = [e for e in faults(ls, "nonfinite") if e.battery is None]
    assert FAULT_S[0] + 1.0 < f.t_s <= FAULT_S[0] + 1.0 + 0.5 + 2 * DT
    assert any(e.kind == "FaultCleared" and e.battery is None for e in ls.bms.events)


def test_switch_node_ignores_a_repeated_sequence_number() -> None:
    """A BMS stuck repeating its last frame is as silent as one sending nothing."""
    node = SwitchNode(chg=True, dsg=True)
    assert node.command(True, True, 7, t=0.0)
    for k in range(1, 8):
        assert not node.command(True, True, 7, t=0.1 * k)  # the same frame again
        node.check(0.1 * k, timeout_s=0.5, started_s=0.0)
    assert node.timed_out and (node.chg, node.dsg) == (False, False)
    assert node.command(True, True, 8, t=0.8)  # a new command: obeyed again
    assert (node.chg, node.dsg) == (True, True) and not node.timed_out
