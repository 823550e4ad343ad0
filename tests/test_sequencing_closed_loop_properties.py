"""Property-based closed-loop tests of sequencing on the project plant.

Random N (2-6), rest voltages spread over 0-4 V, resistances 15-35 mOhm, piecewise-constant load
profiles (including drops to zero), a hot insertion at a random time, control periods 0.1-0.5 s.
Each example is a short run (<= 600 steps) so the whole file stays fast.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config import parse_config
from packpilot.control.sequencing import SequencingConfig
from packpilot.model import loads
from packpilot.model.cell import ocv_v
from packpilot.sim.result import Result
from packpilot.sim.runner import Runner

CFG = SequencingConfig()
DURATION_S = 60.0


@dataclass(frozen=True)
class Case:
    ocv0_v: tuple[float, ...]
    r_ohm: tuple[float, ...]
    dt_s: float
    load_t_s: tuple[float, ...]
    load_a: tuple[float, ...]
    insert: tuple[int, float] | None


@st.composite
def cases(draw: st.DrawFn) -> Case:
    n = draw(st.integers(2, 6))
    low = draw(st.floats(21.0, 23.0))
    spread = draw(st.floats(0.0, 4.0))
    ocv0 = tuple(low + spread * draw(st.floats(0.0, 1.0)) for _ in range(n))
    r = tuple(draw(st.floats(0.015, 0.035)) for _ in range(n))
    dt = draw(st.sampled_from([0.1, 0.2, 0.5]))
    n_seg = draw(st.integers(1, 5))
    times = sorted({0.0, *(draw(st.floats(1.0, DURATION_S - 1.0)) for _ in range(n_seg - 1))})
    amps = tuple(draw(st.one_of(st.just(0.0), st.floats(0.5, 12.0 * n))) for _ in range(len(times)))
    insert = None
    if draw(st.booleans()):
        insert = (draw(st.integers(0, n - 1)), draw(st.floats(0.0, DURATION_S)))
    return Case(ocv0, r, dt, tuple(times), amps, insert)


def simulate(case: Case) -> tuple[Result, np.ndarray]:
    """Run the case; also return each battery's open-circuit voltage after every period."""
    bats = []
    for k, (v, r) in enumerate(zip(case.ocv0_v, case.r_ohm, strict=True)):
        b: dict[str, object] = {
            "name": f"B{k}",
            "cells_per_group": 6,
            "ocv0_v": v,
            "resistance_ohm": r,
        }
        if case.insert is not None and case.insert[0] == k:
            b["present_from_s"] = case.insert[1]
        bats.append(b)
    cfg = parse_config(
        {
            "pack": {
                "cell": "uav_5ah",
                "switch": {"kind": "mosfet_pair", "on_ohm": 0.0001, "diode_drop_v": 0.6},
                "batteries": bats,
            },
            "load": {"kind": "current", "value": 1.0, "v_min_v": 15.0},
            "controller": ["sequencing"],
            "sim": {"dt_s": case.dt_s, "duration_s": DURATION_S, "progress": False},
        }
    )
    runner = Runner(cfg)
    runner.profile = loads.LoadProfile(
        kind="current",
        t_s=np.array([*case.load_t_s, DURATION_S + 1.0]),
        value=np.array([*case.load_a, 0.0]),
    )
    n = len(bats)
    ocv_after: list[np.ndarray] = []

    def record_ocv(run: Runner, t_s: float) -> None:
        soc, temp = run.pack.cell_states()
        cell = ocv_v(run.pack.banks[0].params, soc[0], temp[0])
        ocv_after.append(np.bincount(run.pack.cell_string, weights=cell, minlength=n))

    runner.hooks = [record_ocv]
    res = runner.run()
    record_ocv(runner, runner.pack.t_s)
    return res, np.array(ocv_after[1:])


@settings(max_examples=50, deadline=None)
@given(cases())
def test_closed_loop_invariants(case: Case) -> None:
    res, ocv = simulate(case)
    tr = res.trace
    n = len(case.ocv0_v)
    cur = tr.channel("current_a")
    volt = tr.channel("voltage_v")
    chg = tr.channel("chg_on") > 0.5
    chg_diode = tr.channel("chg_diode_a")
    states = tr.status["seq_state"]
    into = np.maximum(-cur, 0.0)
    supplied = tr.load_a > 1e-3
    join_t = [e.t_s for e in res.events if e.kind == "BatteryJoined"]
    t_lo = tr.t_s - n * case.dt_s - 1e-9

    # The load is always supplied (every battery is far above the load's 15 V lock-out).
    assert res.metrics["load_unsupplied_s"] == 0.0
    assert res.metrics["events"].get("Fault", 0) == 0

    for k in range(len(tr.t_s)):
        for j in range(n):
            # A battery in STANDBY never has its charge FET on.
            if states[k][j] == "STANDBY":
                assert not chg[k, j]
            # Current into a battery while the pack discharges: only in the few periods after
            # a load drop (co-discharged batteries differ in OCV by their IR and polarisation
            # drops) or a join (spec section 7 caveat: the joiner may out-push a loaded
            # battery whose polarisation has not relaxed), and never for two periods running.
            if supplied[k] and into[k, j] > 1.0:
                recent = tr.load_demand_a[max(k - n, 0) : k + 1]
                joined = any(t_lo[k] <= t <= tr.t_s[k] + 1e-9 for t in join_t)
                assert joined or np.any(np.diff(recent) < 0.0), (k, j, into[k, j])
                if k + 1 < len(tr.t_s):
                    assert into[k + 1, j] <= CFG.i_rev, (k, j)

        # Co-discharge: batteries engaged together share the bus, so their OCV spread is
        # bounded by v_co plus the difference of their internal (IR + polarisation) drops.
        engaged = [j for j in range(n) if chg[k, j] and states[k][j] == "DISCHARGING"]
        drop = ocv[k] - volt[k]
        for a in engaged:
            for b in engaged:
                if a < b:
                    spread = abs(ocv[k, a] - ocv[k, b])
                    assert spread <= CFG.v_co + abs(drop[a] - drop[b]) + 0.01, (k, a, b)

    # R3 deadline on the plant: a charge diode never conducts for longer than t_on plus one
    # control period in a row.
    limit = math.ceil((CFG.t_on + case.dt_s) / case.dt_s - 1e-9)
    for j in range(n):
        run = 0
        for k in range(len(tr.t_s)):
            run = run + 1 if chg_diode[k, j] > CFG.i_det else 0
            assert run <= limit, (j, k, run)
