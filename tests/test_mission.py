"""The full mission of examples/uav_mission.toml: fly, land, dock, charge over CAN, balance."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from packpilot.config import load_config
from packpilot.io.can.link import CanChargerLink
from packpilot.sim.elcon import ElconLinks
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES


def test_mission_flies_charges_over_can_and_balances() -> None:
    cfg = load_config(EXAMPLES / "uav_mission.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"dt_s": 0.5, "progress": False})}
    )
    runner = Runner(cfg)
    # no frame log: the TC/Elcon link runs as its compiled model (bit-identical to the
    # python-can path, tests/test_elcon_model.py) ...
    assert runner.charger_link is None
    res = runner.run()
    assert isinstance(runner.loop.links, ElconLinks)
    m = res.metrics
    ev = m["events"]
    # Flight: sequencing joins B, no battery is ever charged by the other, load always supplied.
    assert ev.get("BatteryJoined", 0) >= 1
    assert m["peak_cross_current_a"] <= 1.0
    assert m["load_unsupplied_s"] == 0.0
    # Dock: staged charging over CAN fills both batteries and finishes.
    assert ev.get("StageChanged", 0) >= 2 and ev.get("ChargeComplete", 0) == 1
    assert m["energy_in_wh"] > 100.0
    assert min(m["final_soc"]) > 0.95
    assert m["max_cell_v"] <= 4.2 + 1e-3
    # Balancing: the equalizers worked and the cells ended closer than they started.
    assert ev.get("BalancingUpdated", 0) > 10
    gv = res.trace.group_v
    spread0 = np.nanmax(gv[0], axis=1) - np.nanmin(gv[0], axis=1)
    spread1 = np.nanmax(gv[-1], axis=1) - np.nanmin(gv[-1], axis=1)
    assert np.all(spread1 < spread0)
    modes = {e.data.get("to") for e in res.events if e.kind == "ModeChanged"}
    assert {"discharge", "charge"} <= modes


def test_the_demo_logs_frames_so_its_setpoints_cross_a_python_can_bus(tmp_path: Path) -> None:
    """... while the demo (``--can-log``) keeps the python-can link: frames to log."""
    cfg = load_config(EXAMPLES / "uav_mission.toml")
    assert cfg.can is not None
    log = tmp_path / "demo_can.blf"
    cfg = cfg.model_copy(
        update={
            "can": cfg.can.model_copy(update={"log": str(log)}),
            "sim": cfg.sim.model_copy(update={"duration_s": 5.0, "progress": False}),
        }
    )
    runner = Runner(cfg)
    link = runner.charger_link
    assert isinstance(link, CanChargerLink)  # setpoints cross a python-can bus
    runner.run()
    assert link.client.counters.sent == 5 and link.emulator is not None
    assert link.emulator.counters.sent == 5 and log.stat().st_size > 0
