"""The report's state-of-power section (issue #28 item 3): the pack's 10 / 30 s discharge
limits along a recorded run, predicted from the recorded state as ``run`` predicts its
CCL/DCL, beside the current drawn."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from packpilot.config import load_config
from packpilot.control.power import state_of_power
from packpilot.report.html import build_html
from packpilot.report.info import RunInfo
from packpilot.sim.power import inputs_from_core, params_of
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES


def test_the_report_draws_the_state_of_power_along_the_run() -> None:
    cfg = load_config(EXAMPLES / "uav_dual_parallel.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 20.0, "progress": False})}
    )
    result = Runner(cfg, progress=False).run()
    page = build_html(result, RunInfo.from_config(cfg.model_dump(mode="json")))
    assert '<section id="power">' in page and 'data-chart="power"' in page
    facts = dict(re.findall(r"<tr><td>([^<]+)</td><td>([^<]+)</td></tr>", page))
    lowest = float(facts["lowest 30 s discharge limit (A)"])
    # the same prediction from the last recorded state (the lowest SOC of the run)
    tr = result.trace
    k = len(tr.t_s) - 1

    def row(name: str) -> np.ndarray:
        return np.asarray(tr.channel(name)[k], np.float64)

    prm = params_of(cfg)
    inp = inputs_from_core(
        cfg, soc=row("soc"), temp_c=row("temp_c"), current_a=row("current_a"),
        voltage_v=row("voltage_v"), min_cell_v=row("min_cell_v"), max_cell_v=row("max_cell_v"),
        present=np.ones(2, bool), chg_on=row("chg_on") > 0.5, dsg_on=row("dsg_on") > 0.5,
        prm=prm,
    )  # fmt: skip
    last = float(state_of_power(prm, inp).pack_dsg_a[0, 2])
    assert lowest <= last + 1e-6
    assert lowest == pytest.approx(last, rel=0.05)
    # the pack carried far less than it could: headroom stays positive
    assert float(facts["least headroom, 30 s limit - current (A)"]) > 10.0
    assert json.dumps(lowest)  # a number, not a dash
