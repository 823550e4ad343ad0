"""`run` against `hil` over real python-can buses (``virtual``, one process).

Lock-step (deterministic): the BMS runtime and the twin alternate period by period on a virtual
bus, so the comparison with ``simulate`` sees only what the bus adds (the frames' resolution).
"""

from __future__ import annotations

import numpy as np

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.bms import Event
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.lockstep import run_lockstep
from packpilot.sim.loop import n_steps
from packpilot.sim.runner import Runner

EVENT_TOLERANCE_S = 2.0
"""How far an event of the CAN run may sit from the simulator's: the frames carry 0.1 mV /
1 mA, and equalization re-plans when a group's deviation crosses its set point, which the
rounding can move by a few periods (measured: ±1.0 s on uav_mission)."""


def scenario(name: str, duration_s: float) -> ScenarioConfig:
    cfg = load_config(scenario_path(__import__("pathlib").Path(name)))
    return cfg.model_copy(update={"sim": cfg.sim.model_copy(update={"duration_s": duration_s})})


def key(e: Event) -> tuple[str, int | None]:
    return (e.kind, e.battery)


def assert_same_events(sim: list[Event], can: list[Event]) -> None:
    assert [key(e) for e in can] == [key(e) for e in sim]
    worst = max((abs(a.t_s - b.t_s) for a, b in zip(sim, can, strict=True)), default=0.0)
    assert worst <= EVENT_TOLERANCE_S


def compare(cfg: ScenarioConfig, **opts: object) -> None:
    sim = Runner(cfg, progress=False).run()
    ls = run_lockstep(cfg, n_steps(cfg), RuntimeOptions(**opts))  # type: ignore[arg-type]
    assert_same_events(sim.events, ls.bms.events)
    n = len(ls.chg)
    assert n == n_steps(cfg)
    b = ls.hil.plant.infos[0].n_batteries
    tr = list(ls.hil.plant.topology.traction)
    sim_chg = sim.trace.channel("chg_on")[:, tr].astype(bool)
    sim_dsg = sim.trace.channel("dsg_on")[:, tr].astype(bool)
    assert_same_switching(sim_chg, np.array(ls.chg).reshape(n, b))
    assert_same_switching(sim_dsg, np.array(ls.dsg).reshape(n, b))
    c = ls.bms.plant.counters
    assert c.malformed == c.unexpected == c.send_errors == 0
    assert ls.hil.commands == c.sent  # no command lost
    assert sum(node.timeouts for node in ls.hil.switch) == 0


def transitions(x: np.ndarray) -> list[tuple[int, int, bool]]:
    """(period, battery, new state) of every switch transition."""
    d = np.nonzero(x[1:] != x[:-1])
    return [(int(k) + 1, int(i), bool(x[k + 1, i])) for k, i in zip(*d, strict=True)]


def assert_same_switching(sim: np.ndarray, can: np.ndarray) -> None:
    """The same transitions of the same switches, each at most one period apart: a decision
    that rests on the charger's status (one period old and 0.1 A on its CAN link, exact on
    the simulator's direct link) may come one period later."""
    a, b = transitions(sim), transitions(can)
    assert [x[1:] for x in a] == [x[1:] for x in b]
    assert max((abs(x[0] - y[0]) for x, y in zip(a, b, strict=True)), default=0) <= 1
    assert np.mean(sim == can) > 0.999


def test_uav_mission_flight_matches_simulate() -> None:
    """The flight part (20 min of flight and landing) of uav_mission, run over CAN."""
    cfg = scenario("uav_mission", 1250.0)
    sim = Runner(cfg, progress=False).run()
    assert sim.trace.load_demand_a.max() > 30  # the flight really flew
    compare(cfg)
    ls = run_lockstep(cfg, n_steps(cfg))
    assert all(ls.supplied)  # the load was never unsupplied in flight


def test_evtol_charging_matches_simulate() -> None:
    """The whole staged charge (5 h: every stage, every battery full) over CAN."""
    compare(scenario("evtol_charging", 18000.0), allow_unmonitored=True)
