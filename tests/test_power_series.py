"""A battery's resistance in the state of power and the join planner (issue #28 items 3-4) as
the real plant has it: its leads, connectors and shunt (``series_ohm``, issue #27), and its
stated ``resistance_ohm`` away from the temperature it is stated at.

The plant puts ``series_ohm`` in the battery's branch, outside its cells: the bus sits
``I x series_ohm`` lower, the split between batteries moves towards the one with less of it,
and a join's loop resistance grows. Until 2026-11-29 the prediction left it out. With 20 mOhm
per battery on two 20 mOhm batteries (``bench_power.py --series-ohm 0.02``) the join planner's
peak was 98 % above the plant's, and the published 10 s limit of a cold, nearly empty fresh +
aged pair drove the aged battery's cells below the cut-off (1.14 x the true limit)."""

from __future__ import annotations

import copy
import json
import tomllib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import tomli_w
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.config import ScenarioConfig
from packpilot.config.scenario import parse_config
from packpilot.control import power as pw
from packpilot.model.pack import Pack
from packpilot.sim.power import current_limits, inputs_from_core, inputs_from_plant, params_of
from tests.conftest import EXAMPLES

LEADS_OHM = 0.02
"""As much as the cells' own R0 (6 x 3.3 mOhm at 25 degC): a long harness and a shunt."""
DT_S = 0.1
H10 = 1  # index of the 10 s horizon


def _cfg(bats: list[dict[str, Any]], ambient_c: float = 25.0, kind: str = "mosfet_pair",
         limits: bool = False) -> ScenarioConfig:  # fmt: skip
    data: dict[str, Any] = {
        "pack": {"name": "leads", "cell": "uav_5ah", "ambient_c": ambient_c,
                 "switch": {"kind": kind, "on_ohm": 0.0005}, "batteries": bats},
        "load": {"kind": "current", "value": 0.0},
        "sim": {"dt_s": DT_S, "duration_s": 10.0},
    }  # fmt: skip
    if limits:
        data["limits"] = {}
    return parse_config(data, "test_power_series")


def test_params_carry_the_plants_series_resistance() -> None:
    """One definition (``model.pack.battery_series_ohm``): the prediction's per-battery
    series resistance is the plant's, stated or not."""
    cfg = _cfg([
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "series_ohm": 0.013},
        {"name": "B", "cells_per_group": 6, "soc0": 0.5},
    ])  # fmt: skip
    assert params_of(cfg).series_ohm.tolist() == Pack(cfg).series_ohm.tolist() == [0.013, 0.0]


@pytest.mark.parametrize(("kind", "load_a"), [("relay", 0.0), ("mosfet_pair", 0.0),
                                              ("relay", 20.0)])  # fmt: skip
def test_join_peak_with_leads_is_the_plants(kind: str, load_a: float) -> None:
    """B (0.2 SOC above A, its switch open) joins A, both with leads as resistive as their
    cells; at rest and while A carries 20 A for 10 s before (its bus then sits 0.4 V lower
    through its leads). The planner's peak through B's switch within 15 % of the plant's."""
    off = {"kind": kind, "on_ohm": 0.0005, "chg_on": False, "dsg_on": False}
    cfg = _cfg([
        {"name": "A", "cells_per_group": 6, "soc0": 0.5, "resistance_ohm": 0.02,
         "series_ohm": LEADS_OHM},
        {"name": "B", "cells_per_group": 6, "soc0": 0.7, "resistance_ohm": 0.02,
         "series_ohm": LEADS_OHM, "switch": off},
    ], kind=kind)  # fmt: skip
    pack = Pack(cfg, n_packs=1)
    load = np.array([load_a])
    for _ in range(100):
        pack.step(DT_S, "current", load)
    prm = params_of(cfg)
    inp = inputs_from_plant(cfg, pack)
    inp.chg_on[0, 1] = inp.dsg_on[0, 1] = True
    plan = pw.plan_join(prm, inp, 1, float("nan"), load_a=load_a, horizon_s=2.0, n_steps=20)
    pack.chg_on[0, 1] = pack.dsg_on[0, 1] = True
    peak = 0.0
    for _ in range(20):
        x = float(pack.step(DT_S, "current", load).string_a[0, 1])
        peak = x if abs(x) > abs(peak) else peak
    assert peak > 5.0
    assert plan.peak_a == pytest.approx(peak, rel=0.15)


def test_the_10s_limit_with_leads_holds_on_the_plant_and_reaches_90_percent() -> None:
    """A fresh and an aged battery (1.8 x R, 0.8 x capacity, less charge), nearly empty at
    5 degC, each with 20 mOhm of leads: the leads push the split towards the aged battery,
    whose cells reach the cut-off first. The published 10 s limit drawn on the plant for 10 s
    crosses no cut-off and no current limit; 1/0.9 of it crosses one (so it reaches >= 90 %
    of the true limit)."""
    cfg = _cfg([
        {"name": "A", "cells_per_group": 6, "soc0": 0.2, "resistance_ohm": 0.02,
         "series_ohm": LEADS_OHM},
        {"name": "B", "cells_per_group": 6, "soc0": 0.12, "resistance_ohm": 0.036,
         "capacity_ah": 4.0, "series_ohm": LEADS_OHM},
    ], ambient_c=5.0, limits=True)  # fmt: skip
    prm = params_of(cfg)
    out = pw.state_of_power(prm, inputs_from_plant(cfg, Pack(cfg)), alone=False)
    why = pw.WHY_NAMES[int(out.why_dsg[0, H10])]
    limit = float(out.pack_dsg_a[0, H10])
    drawn = np.array([limit, limit / 0.9])
    pack = Pack(cfg, n_packs=2)
    lim_d, _ = current_limits(cfg, np.array([5.0, 4.0]))
    low = np.full(2, np.inf)
    over = np.zeros(2, bool)
    for _ in range(round(10.0 / DT_S)):
        iv = pack.step(DT_S, "current", drawn)
        assert iv.supplied.all()
        for i in range(2):
            sl = slice(pack.string_cell_starts[i], pack.string_cell_starts[i] + 6)
            low = np.minimum(low, iv.cell_v[:, sl].min(axis=1))
            over |= iv.string_a[:, i] > lim_d[i]
    crossed = (low < prm.cell_v_min[0]) | over
    assert not crossed[0], f"{limit:.1f} A ({why}): lowest cell {low[0]:.3f} V, over {over[0]}"
    assert crossed[1], f"{drawn[1]:.1f} A crosses nothing: the limit is under 90 % of it"
    assert (why, int(out.who_dsg[0, H10])) == ("cell voltage", 1)  # the aged battery's cells


@pytest.mark.parametrize("ambient_c", [5.0, 25.0, 40.0])
def test_the_cell_set_inputs_have_the_plants_resistance_away_from_25_degc(
    ambient_c: float,
) -> None:
    """Without a trusted observer R0 the core's inputs take R0 from the cell set, scaled to a
    battery's stated ``resistance_ohm`` as the plant scales it: stated at ``resistance_temp_c``
    (25 degC), the cells' temperature law from there. Until 2026-11-29 the scale was taken at
    the ambient: at 5 degC R0 came out 1.8 x below the plant's (a limit too high)."""
    cfg = _cfg([
        {"name": "A", "cells_per_group": 6, "soc0": 0.3, "resistance_ohm": 0.02},
        {"name": "B", "cells_per_group": 6, "ocv0_v": 22.2, "resistance_ohm": 0.036},
    ], ambient_c=ambient_c)  # fmt: skip
    pack = Pack(cfg)
    truth = inputs_from_plant(cfg, pack)
    n = 2
    v = np.array([float(pack.e_cell[0, :6].sum()), float(pack.e_cell[0, 6:].sum())])
    core = inputs_from_core(
        cfg, soc=truth.soc[0], temp_c=np.full(n, ambient_c), current_a=np.zeros(n),
        voltage_v=v, min_cell_v=v / 6, max_cell_v=v / 6, present=np.ones(n, bool),
        chg_on=np.ones(n, bool), dsg_on=np.ones(n, bool),
    )  # fmt: skip
    assert core.r0_ohm[0] == pytest.approx(truth.r0_ohm[0], rel=1e-6)


def test_plan_join_counts_the_leads_in_the_loop(tmp_path: Path) -> None:
    """``packpilot plan-join`` on uav_dual_parallel with 20 mOhm of leads per battery: the loop
    resistance, the admissible dV and the peak at the fixed 3 V are the leads' too."""
    base = tomllib.loads((EXAMPLES / "uav_dual_parallel.toml").read_text())
    wired = copy.deepcopy(base)
    for b in wired["pack"]["batteries"]:
        b["series_ohm"] = LEADS_OHM
    rows = {}
    for name, data in (("plain", base), ("wired", wired)):
        path = tmp_path / f"{name}.toml"
        path.write_text(tomli_w.dumps(data))
        res = CliRunner().invoke(app, ["plan-join", str(path), "--soc", "0.5", "--temp", "25",
                                       "--json"])  # fmt: skip
        assert res.exit_code == 0, (res.output, res.exception)
        rows[name] = json.loads(res.stdout)
    for plain, wired_row in zip(rows["plain"], rows["wired"], strict=True):
        # B's leads in series, A's in the other arm: 2 x 20 mOhm more in the loop
        r = plain["r_loop_ohm"] + 2 * LEADS_OHM
        assert wired_row["r_loop_ohm"] == pytest.approx(r, rel=1e-9)
        assert wired_row["dv_up_v"] == pytest.approx(15.0 * r, rel=1e-6)
        assert wired_row["peak_at_fixed_a"] == pytest.approx(3.0 / r, rel=1e-6)
