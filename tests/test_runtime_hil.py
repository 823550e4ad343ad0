"""`run` against `hil` over real python-can buses (``virtual``, one process).

Lock-step (deterministic): the BMS runtime and the twin alternate period by period on a virtual
bus, so the comparison with ``simulate`` sees only what the bus adds (the frames' resolution).
"""

from __future__ import annotations

from collections.abc import Collection

import numpy as np
import pytest

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.bms import Event
from packpilot.contract.record import Result
from packpilot.model.pack import Pack
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.lockstep import (
    Lockstep,
    Transition,
    match_transitions,
    run_lockstep,
    transitions,
)
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


def float16_step_v(v: float) -> float:
    """The spacing of float16 at ``v`` (DroneCAN BatteryInfo's voltage): 2^-6 V = 15.6 mV at
    16-32 V. A difference of two roundings is off by at most one step."""
    return float(np.spacing(np.float16(v)))


def r2_join_tolerance_s(sim: Result, cfg: ScenarioConfig, battery: int) -> float:
    """How late (or early) ``battery``'s R2 join may come over DroneCAN, derived from float16.

    R2 joins a standby battery once its fast voltage (its voltage: no current) is within
    ``v_co`` of the reference, the admitted battery's fast voltage ``E = V + I R``, where R is
    sequencing's estimate ``-dV/dI`` over the last current step of at least ``i_step``. Over
    float16 each voltage is off by half a step ``h``, so the quotient's ``dV`` by up to ``h``
    and R by up to ``h / dI``: at load current ``I`` the reference is off by up to
    ``I h / dI + h`` (the R term, then the two voltages' half steps). In uav_mission's flight
    this is the R term: the step before simulate's join is 1.64 A (16.08 -> 17.72 A at 80.0 s),
    so ``I h / dI`` = 17.7 A x 15.6 mV / 1.64 A = 169 mV, + 15.6 mV = 184 mV (the run over
    DroneCAN estimated R_A 28.6 mOhm against simulate's 20.8 mOhm: 133 mV high until the
    next current step re-estimated it at 85.2 s). The reference closes on the standby
    battery's voltage at simulate's rate over the 10 s before its join (4.4 mV/s: 95.5 -> 51.4
    mV), so the join may move by the voltage error over that rate: 42 s here; measured 4.4 s late
    (80.8 -> 85.2 s, since #27's reference temperature; within 2 s before it). Computed from
    simulate's own trace, so it follows the scenario."""
    assert cfg.sequencing is not None
    dt = cfg.sim.dt_s
    join = next(e for e in sim.events if e.kind == "BatteryJoined" and e.battery == battery)
    k = round(join.t_s / dt)
    cur = sim.trace.channel("current_a")[:, 0]  # the admitted battery: A (index 0)
    volt = sim.trace.channel("voltage_v")
    steps = np.nonzero(np.abs(np.diff(cur[:k])) >= cfg.sequencing.i_step)[0]
    d_i = abs(float(cur[steps[-1] + 1] - cur[steps[-1]]))
    h = float16_step_v(float(volt[k - 1, 0]))
    err_v = abs(float(cur[k - 1])) * h / d_i + h
    ref = np.array([float(x[0]) for x in sim.trace.status["seq_v_ref_v"]])  # type: ignore[arg-type]
    gap = ref - volt[:, battery]
    n = round(10.0 / dt)
    rate = (gap[k - 1 - n] - gap[k - 1]) / (n * dt)
    assert rate > 0.0  # the gap closes before the join
    return float(err_v / rate)


def assert_same_events(
    sim: list[Event], can: list[Event], tol_s: float = EVENT_TOLERANCE_S
) -> None:
    assert [key(e) for e in can] == [key(e) for e in sim]
    worst = max((abs(a.t_s - b.t_s) for a, b in zip(sim, can, strict=True)), default=0.0)
    assert worst <= tol_s


def compare(cfg: ScenarioConfig, **opts: object) -> Lockstep:
    """``run`` against ``hil`` over CAN against ``simulate``; returns the lock-step run (its
    caller checks more of it without running it again)."""
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
    return ls


def assert_same_switching(sim: np.ndarray, can: np.ndarray) -> None:
    """The same transitions of the same switches, each at most one period apart: a decision
    that rests on the charger's status (one period old and 0.1 A on its CAN link, exact on
    the simulator's direct link) may come one period later."""
    a, b = transitions(sim), transitions(can)
    assert [x[1:] for x in a] == [x[1:] for x in b]
    assert max((abs(x[0] - y[0]) for x, y in zip(a, b, strict=True)), default=0) <= 1
    assert np.mean(sim == can) > 0.999


@pytest.mark.long(cpu_s=31)
def test_uav_mission_flight_matches_simulate() -> None:
    """The flight part (20 min of flight and landing) of uav_mission, run over CAN."""
    cfg = scenario("uav_mission", 1250.0)
    sim = Runner(cfg, progress=False).run()
    assert sim.trace.load_demand_a.max() > 30  # the flight really flew
    ls = compare(cfg)  # lock-step is deterministic: the compared run is the one to check
    assert all(ls.supplied)  # the load was never unsupplied in flight


@pytest.mark.long(cpu_s=389)
def test_evtol_charging_matches_simulate() -> None:
    """The whole staged charge (5 h: every stage, every battery full) over CAN."""
    compare(scenario("evtol_charging", 18000.0), allow_unmonitored=True)


# ---------------------------------------------------------------- batteries on DroneCAN
# BatteryInfo carries voltage, current and temperature as float16 and SOC as an integer
# percent; BatteryInfoAux the cell voltages as float16. Measured against the twin's sensing
# (uav_mission's flight, 6S at 20.8-24.7 V, up to 35 A; evtol_charging, 28S at 96-117 V,
# 50 A per battery): voltage off by at most 7.8 mV (6S) / 31 mV (28S), half a float16 step
# (2^-6 V between 16 and 32 V, 2^-4 V between 64 and 128 V); current 12.5 / 15.6 mA; temperature
# 0.125 K (float16 kelvin: 0.25 K steps near 293 K); cells 1.95 mV (3.9 mV steps above 4 V,
# 1.95 mV below); SOC 0.5 % (rounded to whole percent). The DBC path: 0.05 mV, 0.5 mA.

DRONECAN_ADVISORY: dict[str, str] = {
    "CrossCurrentRisk": (
        "a warning on the sequencing's zero-load prediction, which acts on nothing; the "
        "prediction divides fast-voltage differences by resistances the sequencing estimates "
        "as -dV/dI over a current step of >= i_step (1 A), and a 15.6 mV float16 voltage "
        "step on a 1 A step moves that estimate by up to 15.6 mOhm: measured 8.7-31 mOhm over "
        "DroneCAN against 15.4-22.3 mOhm from simulate, so the prediction crosses the 2.4 A "
        "charge limit 22 times instead of 2 (peak 4.3 A against 2.6 A)"
    ),
    "BalancingUpdated": (
        "equalization re-plans when a group's deviation crosses dv_set (5 mV), which cell "
        "voltages in 1.95 / 3.9 mV steps move by minutes: 38 re-plans instead of 42, the "
        "matched ones up to 135 s apart; the outcome is pinned instead (GROUP_SOC_SPREAD_TOL)"
    ),
    "ReverseCurrent": (
        "the reverse cut is a switch decision: simulate's cut is pinned with the switches "
        "(assert_switching_with_reverse_cycles); the DroneCAN run adds the cuts that end "
        "its extra close / cut cycles"
    ),
}
"""Event kinds a DroneCAN-fed flight has more or fewer of, or elsewhere, than ``simulate``,
and why; every other kind (the supervisor's and sequencing's state and mode changes, joins,
faults, protection, limits) is compared as on the DBC path (kind, battery, order, within
EVENT_TOLERANCE_S; measured: identical times)."""

MAX_REVERSE_CYCLES = 3
"""Extra close / cut cycles of a charge FET in the DroneCAN flight (measured: 3, battery A in
the landing's last 6 s at 0.8 A of load). simulate's reverse cut opens A's charge FET at
1192.0 s and it stays open; over DroneCAN the engage rule closes it again (periods 5970, 5982,
5995) because at 0.8 A its test (would A discharge?) rests on fast-voltage differences of a
few mV, below the 15.6 mV float16 step. The first two cycles end with the slow cut (0.25 A into
A, below i_rev, for q_rev_as = 0.5 A s: 2.0 s); the third is open when the flight's load ends
at 1200.0 s, so the current into A rises to the whole circulating current, 0.69 A (B's fast
voltage over both resistances, no load share left), above i_rev 0.5 A: the fast cut opens it
at the next measurement, 1200.2 s, one period, as sequencing promises. Not a defect: the
engage rule allows a close whose zero-load current stays under the charge limit (2.25 A here,
0.9 x 0.5 C x 5 Ah), and i_rev is the cut's threshold. assert_switching_with_reverse_cycles
checks exactly that for each cycle."""

SWITCH_AGREEMENT = 0.995
"""Share of (period, battery) at which the DroneCAN run's switches stand as simulate's
(measured 0.99784: the 27 battery-periods of the three cycles among 12,500)."""

ENERGY_REL_TOL = 1e-4
"""Energy delivered to the load (plant truth) relative to simulate's: it differs only through
the bus voltage while the switches stand differently (measured 2e-6)."""

GROUP_SOC_SPREAD_TOL = 0.005
"""End-of-flight spread of the group SOCs (max - min, plant truth) of each battery, against
simulate's (what equalization achieved): one float16 cell step (1.95 mV below 4 V) where the
flight ends (SOC 0.29-0.36, uav_5ah's OCV rising 0.38-0.50 V per unit SOC) is about 0.5 % SOC
(measured: 0.19 % on A, 0.00 % on B)."""

ALLOWANCE_TOL = 0.01
"""Protection's allowance used at the end, against simulate's (measured: 0 in both: the
flight's lowest cell, 3.45 V, stays above every cut-off, so this guards a regression)."""


def without(events: list[Event], kinds: Collection[str]) -> list[Event]:
    return [e for e in events if e.kind not in kinds]


def extra_transitions(sim: np.ndarray, can: np.ndarray, periods: int) -> list[Transition]:
    """Every transition of ``sim`` is in ``can`` (same switch, same new state, in order, at
    most ``periods`` apart); returns the transitions ``can`` has beyond them."""
    missing, extra = match_transitions(sim, can, periods)
    assert not missing, f"simulate's transitions {missing} are not in the CAN run"
    return extra


def test_match_transitions() -> None:
    """In order, same switch and state, within the given periods; the rest is extra."""
    ref = np.zeros((30, 2), bool)
    ref[10:, 0] = True
    ref[20:, 1] = True
    got = np.zeros((30, 2), bool)
    got[11:15, 0] = got[16:, 0] = True
    got[25:, 1] = True
    assert transitions(got) == [(11, 0, True), (15, 0, False), (16, 0, True), (25, 1, True)]
    extra = [(15, 0, False), (16, 0, True)]
    assert match_transitions(ref, got, 1) == ([(20, 1, True)], [*extra, (25, 1, True)])
    assert match_transitions(ref, got, 5) == ([], extra)
    assert match_transitions(ref, ref, 0) == ([], [])


def assert_switching_with_reverse_cycles(
    sim: np.ndarray,
    can: np.ndarray,
    cuts: list[Event],
    dt_s: float,
    i_rev_a: float,
    periods: int = 1,
    measured_a: np.ndarray | None = None,
    i_lim_a: list[float] | None = None,
) -> int:
    """simulate's charge-FET transitions, each within ``periods``, plus close / cut cycles:
    a close, then the BMS's own reverse cut of that battery; returns the number of cycles.

    A cut is either the slow one (a reverse current below ``i_rev_a`` for ``q_rev_as``) or
    the fast one: the first period the BMS measured more than ``i_rev_a`` into the battery
    (``measured_a``, periods x batteries: the period before it measured less), at no more
    than the charge limit ``i_lim_a`` the engage rule allowed for a closed FET even if the
    load vanished. That is what sequencing promises (docs/parallel_discharge.md: any reverse
    current cut within one control period; none above the charge limit)."""
    extra = extra_transitions(sim, can, periods)
    closes, opens = extra[0::2], extra[1::2]
    assert len(closes) == len(opens)
    assert all(c[2] and not o[2] and c[1] == o[1] and c[0] < o[0]
               for c, o in zip(closes, opens, strict=True))  # fmt: skip
    cut_at = {(round(e.t_s / dt_s), e.battery): e for e in cuts}
    for o in opens:
        cut = cut_at[(o[0], o[1])]  # the BMS opened it: a reverse cut in that period
        into = -float(cut.data["current_a"])
        if into < i_rev_a:
            continue  # the slow cut
        assert measured_a is not None and i_lim_a is not None, f"fast cut at {into} A"
        assert -measured_a[o[0] - 1, o[1]] <= i_rev_a  # the first period above i_rev
        assert into <= i_lim_a[o[1]]
    assert np.mean(sim == can) >= SWITCH_AGREEMENT
    return len(opens)


def group_soc_spread(pack: Pack) -> np.ndarray:
    """Per battery, max - min of its cells' SOC (plant truth; uav_mission: one cell a group)."""
    soc = pack.cell_states()[0][0]
    return np.array([np.ptp(soc[pack.cell_string == s]) for s in range(pack.n_strings)])


@pytest.mark.long(cpu_s=39)
def test_uav_mission_flight_over_dronecan_matches_simulate() -> None:
    """The flight part of uav_mission with both batteries on DroneCAN BatteryInfo +
    BatteryInfoAux: the same safety-relevant events and switch decisions as simulate, the
    differences bounded by float16 (docs/runtime.md, "Batteries on DroneCAN")."""
    cfg = scenario("uav_mission", 1250.0)
    runner = Runner(cfg, progress=False)
    sim = runner.run()
    measured: list[np.ndarray] = []  # the BMS's battery currents, period by period

    def record(ls: Lockstep, k: int) -> None:
        if k > 0:
            measured.append(ls.bms.core.m.bat.current_a[0].copy())

    ls = run_lockstep(cfg, n_steps(cfg), RuntimeOptions(dronecan_ids=(21, 22)), hook=record)
    energy_j = ls.load_j
    c = ls.bms.plant.counters
    assert c.received > 0 and c.malformed == c.unexpected == 0
    assert ls.bms.plant.assembler.errors == 0 and ls.hil.commands == c.sent
    assert sum(node.timeouts for node in ls.hil.switch) == 0
    safety = without(sim.events, DRONECAN_ADVISORY)
    can = without(ls.bms.events, DRONECAN_ADVISORY)
    assert {"BatteryJoined", "ModeChanged", "StateChanged"} <= {e.kind for e in safety}
    assert [key(e) for e in can] == [key(e) for e in safety]
    join_tol_s = r2_join_tolerance_s(sim, cfg, 1)
    for a, x in zip(safety, can, strict=True):
        tol = join_tol_s if a.kind == "BatteryJoined" else EVENT_TOLERANCE_S
        assert abs(a.t_s - x.t_s) <= tol, (a, x, tol)
    n, b = len(ls.chg), ls.hil.plant.infos[0].n_batteries
    tr = list(ls.hil.plant.topology.traction)
    sim_chg = sim.trace.channel("chg_on")[:, tr].astype(bool)
    sim_dsg = sim.trace.channel("dsg_on")[:, tr].astype(bool)
    assert_same_switching(sim_dsg, np.array(ls.dsg).reshape(n, b))
    assert cfg.sequencing is not None
    cuts = [e for e in ls.bms.events if e.kind == "ReverseCurrent"]
    sim_cuts = [e for e in sim.events if e.kind == "ReverseCurrent"]
    assert sim_cuts and all(any(key(a) == key(x) and abs(a.t_s - x.t_s) <= EVENT_TOLERANCE_S
                                for x in cuts) for a in sim_cuts)  # fmt: skip
    seq = cfg.sequencing
    i_lim = [seq.charge_limit_margin * seq.charge_limit_c * cap
             for cap in ls.hil.plant.infos[0].capacity_ah]  # fmt: skip
    cycles = assert_switching_with_reverse_cycles(
        sim_chg,
        np.array(ls.chg).reshape(n, b),
        cuts,
        cfg.sim.dt_s,
        seq.i_rev,
        round(join_tol_s / cfg.sim.dt_s),  # B's charge FET closes with its join
        np.array(measured),
        i_lim,
    )
    assert cycles <= MAX_REVERSE_CYCLES
    assert len(cuts) == len(sim_cuts) + cycles
    sim_energy_j = float(np.sum(sim.trace.bus_v * sim.trace.load_a)) * cfg.sim.dt_s
    assert sim_energy_j > 3.6e5  # the flight really flew (> 100 Wh)
    assert abs(energy_j / sim_energy_j - 1.0) <= ENERGY_REL_TOL
    spread = group_soc_spread(ls.hil.plant.pack) - group_soc_spread(runner.pack)
    assert np.all(np.abs(spread) <= GROUP_SOC_SPREAD_TOL)
    used = ls.bms.core.status_of(0)["protection_fraction"]
    sim_used = sim.trace.status["protection_fraction"][-1]
    assert all(abs(float(x) - float(y)) <= ALLOWANCE_TOL  # type: ignore[arg-type]
               for x, y in zip(used, sim_used, strict=True))  # fmt: skip
    assert all(ls.supplied)


CHARGE_STAGE_TOLERANCE_S = 56.0
"""How far a staged-charging decision over DroneCAN may sit from simulate's in evtol_charging's
first hand-over. The method's open-circuit estimate V + I R is off by up to 156 mV: half a
float16 step at 64-128 V (h = 31 mV) plus 50 A times its resistance estimate's error, which
the settled -dV/dI over the 50 A current step (four voltage readings' worth: 4 h / 50 A =
2.5 mOhm) makes up to 125 mV (measured 0.89 mOhm: 33.75 against 32.86 mOhm). Before the
hand-over the lowest estimate rises by 2.8 mV/s (simulate), so 156 mV is 56 s (measured: 10 s
later). Over the whole 5 h charge the rise slows near V_sat: measured 8-92 s late
(docs/runtime.md)."""


@pytest.mark.long(cpu_s=144)
def test_evtol_charging_over_dronecan_first_hand_over() -> None:
    """evtol_charging's six batteries and its aux battery on DroneCAN: the staged charge to
    its first hand-over (S20 → S30, then S30 regroups as the second pair joins: since issue
    #24 item 4 S30 charges to Vt = V2 + step_v, so the join comes at ~6,440 s) makes the same
    decisions as simulate, the same relay transitions, within CHARGE_STAGE_TOLERANCE_S."""
    cfg = scenario("evtol_charging", 6600.0)
    sim = Runner(cfg, progress=False).run()
    opts = RuntimeOptions(dronecan_ids=tuple(range(21, 28)), allow_unmonitored=True)
    ls = run_lockstep(cfg, n_steps(cfg), opts)
    assert ls.bms.plant.counters.malformed == 0 and ls.bms.plant.assembler.errors == 0
    stages = [e.data["stage"] for e in sim.events]
    assert stages == ["rest", "S20", "S30", "S30"]  # the hand-over is inside the run
    assert [key(e) for e in ls.bms.events] == [key(e) for e in sim.events]
    assert [e.data["stage"] for e in ls.bms.events] == stages
    worst = max(abs(a.t_s - b.t_s) for a, b in zip(sim.events, ls.bms.events, strict=True))
    assert worst <= CHARGE_STAGE_TOLERANCE_S
    n, b = len(ls.chg), ls.hil.plant.infos[0].n_batteries
    tr = list(ls.hil.plant.topology.traction)
    periods = round(CHARGE_STAGE_TOLERANCE_S / cfg.sim.dt_s)
    for name, got in (("chg_on", ls.chg), ("dsg_on", ls.dsg)):
        want = sim.trace.channel(name)[:, tr].astype(bool)
        assert transitions(want)  # the relays of the second pair closed
        assert extra_transitions(want, np.array(got).reshape(n, b), periods) == []
