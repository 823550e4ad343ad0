"""The report's state-of-power section (issue #28 item 3): the pack's 10 / 30 s discharge
limits along a recorded run, predicted from the recorded state as ``run`` predicts its
CCL/DCL (``sim/power_view.py``, the same function), beside the current drawn."""

from __future__ import annotations

import json
import re

import pytest

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import Trace
from packpilot.report.html import build_html
from packpilot.report.info import RunInfo
from packpilot.sim.power import params_of
from packpilot.sim.power_view import state_of_power_now, view_of_status
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES


def sop_30s_at(cfg: ScenarioConfig, tr: Trace, k: int) -> float:
    """The pack's 30 s discharge limit predicted from the state recorded at step ``k`` of a
    two-battery trace, by the function ``run`` publishes from."""

    def status(name: str, b: int) -> object:
        vals = tr.status.get(name)
        return vals[k][b] if vals is not None else None

    view = view_of_status(tr.battery[k], status, [0, 1], bus_v=float(tr.bus_v[k]),
                          load_a=float(tr.load_a[k]), mode=status("mode", 0))  # fmt: skip
    out = state_of_power_now(cfg, params_of(cfg), view)
    assert out is not None
    return float(out.pack_dsg_a[0, 2])


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
    # the same prediction from the first and the last recorded state (the batteries 2 V
    # apart before they share the load; the lowest SOC), by the function run publishes from
    tr = result.trace
    ends = min(sop_30s_at(cfg, tr, 0), sop_30s_at(cfg, tr, len(tr.t_s) - 1))
    assert lowest <= ends * (1.0 + 5e-4)  # the page prints 4 significant digits
    assert lowest == pytest.approx(ends, rel=0.05)
    # the pack carried far less than it could: headroom stays positive
    assert float(facts["least headroom, 30 s limit - current (A)"]) > 10.0
    assert json.dumps(lowest)  # a number, not a dash
