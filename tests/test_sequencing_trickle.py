"""Issue #24 item 7, closed loop on the plant: no trickle into an engaged battery after a load drop.

Two 6S 5 Ah batteries (20 and 22 mOhm, equal 23.0 V: both admitted by R1 and engaged) hover at
10 A; at 200 s the load drops to zero. The polarisation the lower-resistance battery carried
relaxes differently, and one battery charged the other at 0.17 falling to 0.10 A for the whole
rest with its charge FET on: the slow reverse cut asked the sibling to source more than i_det
(0.5 A), which a trickle never does. Embodiment 5 keeps the charge FET on only while discharge
current flows: the cut now counts the charge the siblings supply, however small, and opens the
charge FET once ``q_rev_as`` (0.5 A s) has flowed in one episode. When the load returns at
300 s both batteries discharge again.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

from packpilot.config import load_config
from packpilot.contract.record import Result
from packpilot.model import loads
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
DT_S = 0.1
DROP_S, BACK_S, END_S = 200.0, 300.0, 340.0


@cache
def run() -> Result:
    cfg = load_config(EXAMPLES / "sequencing_dual_hover.toml")
    a, b = cfg.pack.batteries
    bats = [
        a.model_copy(update={"ocv0_v": 23.0, "resistance_ohm": 0.020}),
        b.model_copy(update={"ocv0_v": 23.0, "resistance_ohm": 0.022}),
    ]
    sim = cfg.sim.model_copy(update={"duration_s": END_S, "dt_s": DT_S, "progress": False})
    cfg = cfg.model_copy(update={"pack": cfg.pack.model_copy(update={"batteries": bats}),
                                 "sim": sim})  # fmt: skip

    def hook(r: Runner, t_s: float) -> None:
        idle = DROP_S <= t_s < BACK_S
        r.profile = loads.constant("none" if idle else "current", 10.0)

    return Runner(cfg, hooks=[hook]).run()


def test_no_trickle_into_an_engaged_battery_after_a_load_drop() -> None:
    res = run()
    tr = res.trace
    t = tr.t_s
    cur = tr.channel("current_a")
    chg = tr.channel("chg_on").astype(bool)
    rest = (t >= DROP_S) & (t < BACK_S)
    into = np.where(chg, np.maximum(-cur, 0.0), 0.0)
    # Both were engaged and discharging before the drop (the case of the issue).
    before = (t > DROP_S - 20.0) & (t < DROP_S)
    assert chg[before].all() and (cur[before] > 1.0).all()
    # At rest: at most q_rev_as (0.5 A s) plus one period flows into a battery whose charge FET
    # is on (before the fix: 0.17 -> 0.10 A for all 100 s, 13 A s), and none after the cut.
    q_as = into[rest].sum(axis=0) * DT_S
    assert float(q_as.max()) <= 0.5 + 0.2 * DT_S
    late = t >= DROP_S + 10.0
    assert not np.any(into[rest & late] > 0.02)
    cuts = [e for e in res.events if e.kind == "ReverseCurrent" and DROP_S <= e.t_s < BACK_S]
    assert len(cuts) == 1
    # The load returns: both discharge again with both FET pairs on.
    back = t >= BACK_S + 5.0
    assert chg[back].all() and (cur[back] > 1.0).all()
    assert res.metrics["load_unsupplied_s"] == 0.0
