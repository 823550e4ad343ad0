"""Closed loop over CAN on the eVTOL charging bus: the charging controller's setpoints travel
ChargerClient → python-can virtual bus → ChargerEmulator → plant charger, and the status comes
back the same way. The scenario is examples/evtol_charging.toml with 2 Ah cells and a 10 A
charger (same C-rates and voltages, 50x shorter) so a full charge takes seconds of wall time."""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.record import Result
from packpilot.io.can import (
    REQUEST_ID,
    SIM_EPOCH_S,
    STATUS_ID,
    CanChargerLink,
)
from packpilot.sim.runner import Runner

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "evtol_charging.toml"
V_SAT = 117.0


def small_evtol(duration_s: float, **charging: Any) -> dict[str, Any]:
    data = tomllib.loads(EXAMPLE.read_text())
    for b in data["pack"]["batteries"]:
        if b.get("role", "traction") == "traction":
            b["capacity_ah"] = 2.0
    data["charger"]["current_a"] = 10.0
    data["charging"].update({"charger_current_limit_a": 10.0, "termination_current_a": 0.2})
    data["charging"].update(charging)
    data["sim"].update({"dt_s": 1.0, "duration_s": duration_s, "progress": False})
    return data


def run_can(
    data: dict[str, Any],
    hooks: list[Callable[[Runner, float], None]] | None = None,
    setup: Callable[[CanChargerLink], None] | None = None,
    log_path: Path | None = None,
) -> tuple[Result, Runner, CanChargerLink]:
    runner = Runner(parse_config(data), progress=False, hooks=hooks or [])
    link = CanChargerLink(runner.pack.charger.view(0), log_path=log_path)
    runner.charger_link = link
    if setup is not None:
        setup(link)
    try:
        res = runner.run()
    finally:
        link.close()
    return res, runner, link


def traction(res: Result) -> list[int]:
    return [i for i, n in enumerate(res.battery_names) if n != "AUX"]


def events(res: Result, kind: str) -> list[Any]:
    return [e for e in res.events if e.kind == kind]


def test_pack_charges_to_full_over_can(tmp_path: Path) -> None:
    res, _runner, link = run_can(small_evtol(4000.0), log_path=tmp_path / "charge.blf")
    tr = traction(res)
    done = events(res, "ChargeComplete")
    assert len(done) == 1
    soc = res.trace.channel("soc")[-1, tr]
    assert soc.min() > 0.97, soc
    # every relay open once complete; the dock only feeds the aux DC/DC (5 A at ~14 V)
    k = int(done[0].t_s)
    assert not res.trace.channel("chg_on")[k + 2 :, tr].any()
    assert res.trace.charger_a[k + 3 :].max() < 1.0
    # setpoints never above V_sat and the stage sequence of the spec
    cmd = np.array(res.trace.status["chg_cmd_v"], dtype=float)[:, tr[0]]
    assert np.nanmax(cmd) <= V_SAT
    stages = [e.data["stage"] for e in events(res, "StageChanged")]
    # (issue #24 item 3: at this dock the second batteries would discharge into the first at
    # the S30 join, so each join waits until the first are charged up to their level: the
    # levels merge, S20 goes on with four first batteries, then S40 with all six)
    assert stages[:3] == ["rest", "S20", "S20"]
    assert "S40" in stages and stages[-2:] == ["top_off", "complete"]
    tr_cur = res.trace.channel("current_a")[:, tr]
    assert np.where(res.trace.charger_a[:, None] > 0.01, tr_cur, 0.0).max() < 0.2
    # the traffic really went over the bus, cleanly
    c = link.client.counters
    assert c.sent >= 3000 and c.received >= 3000 and c.malformed == c.unexpected == 0
    assert link.emulator is not None and link.emulator.counters.received == c.sent
    assert not events(res, "Fault")
    # the aux battery was charged off the bus (starts below its 30 % floor)
    aux = res.trace.channel("soc")[:, res.battery_names.index("AUX")]
    assert aux[-1] > aux[0]
    frames = list(can.LogReader(tmp_path / "charge.blf"))
    assert {m.arbitration_id for m in frames} == {REQUEST_ID, STATUS_ID}
    assert frames[-1].timestamp - SIM_EPOCH_S == pytest.approx(3999.0, abs=1.0)


def test_stopped_heartbeat_drops_output_and_raises_event() -> None:
    hang_from, hang_until = 300.0, 330.0
    res, _, _link = run_can(small_evtol(420.0), setup=lambda lk: lk.hang(hang_from, hang_until))
    t = res.trace.t_s
    out_a = res.trace.charger_a
    assert out_a[(t > 250) & (t < hang_from)].min() > 1.0  # charging before the hang
    off = t[(t >= hang_from) & (out_a < 1e-9)]
    assert off.size and off[0] - hang_from <= 5.0 + 1.0  # plant timeout 5 s (+ one period)
    assert (out_a[(t >= off[0]) & (t < hang_until)] < 1e-9).all()
    # the BMS notices: the runner marks a silent link offline after its timeout, and the first
    # status read after the hang carries the charger's communication-timeout bit
    faults = [e for e in events(res, "Fault") if e.t_s >= hang_from]
    assert faults and faults[0].t_s <= hang_until + 2.0
    assert any(
        e.data.get("communication_timeout") and hang_until <= e.t_s <= hang_until + 2.0
        for e in faults
    )
    # relays open from the first fault until the charger is healthy again, then charging resumes
    tr = traction(res)
    k = int(faults[0].t_s)
    assert not res.trace.channel("chg_on")[k + 1 : int(hang_until), tr].any()
    assert out_a[t > hang_until + 20.0].max() > 1.0


def test_charger_fault_flag_stops_charging_and_opens_relays() -> None:
    def hook(runner: Runner, t_s: float) -> None:
        if t_s == 200.0:
            runner.pack.charger.view(0).set_fault("over_temperature")
        if t_s == 260.0:
            runner.pack.charger.view(0).set_fault("over_temperature", False)

    res, _, _ = run_can(small_evtol(320.0), hooks=[hook])
    faults = [e for e in events(res, "Fault") if e.data.get("over_temperature")]
    assert len(faults) == 1 and 200.0 < faults[0].t_s <= 203.0
    k = int(faults[0].t_s)
    tr = traction(res)
    chg_on = res.trace.channel("chg_on")[:, tr]
    assert not chg_on[k + 1 : 260].any()
    cmd = np.array(res.trace.status["chg_cmd_v"], dtype=float)[:, tr[0]]
    assert (cmd[k:260] == 0.0).all()  # charger commanded off
    assert chg_on[300:].any() and res.trace.charger_a[300:].max() > 1.0  # resumed


def test_malformed_frames_are_counted_and_ignored() -> None:
    garbage = [
        can.Message(arbitration_id=STATUS_ID, is_extended_id=True, data=b"\x00\x01"),
        can.Message(arbitration_id=REQUEST_ID, is_extended_id=True, data=b"\x00"),
        can.Message(arbitration_id=0x123, is_extended_id=False, data=bytes(8)),
        can.Message(arbitration_id=STATUS_ID, is_extended_id=False, data=bytes(8)),
        can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, data=b"\xff" * 8),
        can.Message(arbitration_id=STATUS_ID, is_extended_id=True, is_remote_frame=True, dlc=8),
    ]
    holder: dict[str, CanChargerLink] = {}

    def inject(runner: Runner, t_s: float) -> None:
        if 50.0 <= t_s < 150.0:
            for msg in garbage:
                holder["link"].inject(msg)

    clean, _, _ = run_can(small_evtol(200.0))
    res, _, link = run_can(
        small_evtol(200.0), hooks=[inject], setup=lambda lk: holder.update(link=lk)
    )
    c = link.client.counters
    assert c.malformed == 100 and c.unexpected == 500
    assert link.emulator is not None
    e = link.emulator.counters
    assert e.malformed == 100 and e.unexpected == 500
    assert not events(res, "Fault")
    # the charge itself is untouched by the noise
    np.testing.assert_allclose(
        res.trace.channel("current_a"), clean.trace.channel("current_a"), atol=1e-9
    )


def test_can_loop_matches_direct_loop() -> None:
    data = small_evtol(600.0)
    direct = Runner(parse_config(data), progress=False).run()
    over_can, _, _ = run_can(data)
    assert [e.data["stage"] for e in events(direct, "StageChanged")] == [
        e.data["stage"] for e in events(over_can, "StageChanged")
    ]
    cur_d = direct.trace.channel("current_a")[:, traction(direct)]
    cur_c = over_can.trace.channel("current_a")[:, traction(over_can)]
    assert abs(cur_d.sum() - cur_c.sum()) / abs(cur_d.sum()) < 0.01
    assert math.isclose(direct.trace.charger_a.sum(), over_can.trace.charger_a.sum(), rel_tol=0.01)
