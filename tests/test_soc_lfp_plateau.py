"""Issue #28, the LFP telecom family of the SOC campaign (h28lfp): on the plateau under load the
groups of a battery read the same voltage within the noise, so the group the observer reads
must not follow that noise (``rules.WEAK_HYST_V``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from packpilot.campaign.spreads import Draw
from packpilot.config import parse_config, read_toml
from packpilot.config.scenario import ScenarioConfig
from packpilot.sim.loop import ClosedLoop
from packpilot.sim.sensors import soc_state

ROOT = Path(__file__).resolve().parents[1]


def telecom(duration_s: float) -> ScenarioConfig:
    """telecom_string with the observer and the acceptance's sensor errors (as the campaign)."""
    data: dict[str, Any] = read_toml(ROOT / "examples" / "telecom_string.toml")
    data["soc"] = {}
    data["sensors"] = {
        "seed": 28, "soc0_error": 0.10, "cell_v": {"noise_sigma": 0.005},
        "current": {"gain": 1.01, "offset": 0.2},
    }  # fmt: skip
    data["sim"]["progress"] = False
    data["sim"]["duration_s"] = duration_s
    return parse_config(data, "telecom_string")


# Campaign run 13 (seed 28): every group starts on the upper plateau (0.77..0.87), 7 degC.
RUN13 = Draw(run=13, seed=28, capacity_scale=0.9938, r0_scale=1.0199, soc0_offset=0.0736,
             ambient_c=6.92)  # fmt: skip


def group_trace(cfg: ScenarioConfig, draw: Draw) -> tuple[np.ndarray, np.ndarray]:
    """(the group the observer reads, the plant's SOC of that group less the weakest group's)
    at every step."""
    loop = ClosedLoop.of(cfg, 1, overrides=draw.pack_overrides())
    st = soc_state(loop.core)
    cpg = cfg.pack.batteries[0].cells_per_group
    read, gap = [], []
    try:
        for k in range(int(cfg.sim.duration_s / cfg.sim.dt_s)):
            loop.step(k, cfg.sim.dt_s)
            g = int(st.weak_g[0, 0])
            soc, _ = loop.plant.pack.cell_states()
            grp = soc[0].reshape(-1, cpg).mean(axis=1)
            read.append(g)
            gap.append(grp[g] - grp.min() if g >= 0 else np.nan)
    finally:
        loop.close()
    return np.array(read), np.array(gap)


def test_the_group_read_does_not_follow_the_noise_on_the_lfp_plateau() -> None:
    """At rest (t = 0) the weakest group reads 5-11 mV below the others and is chosen; under
    46 A the four groups, 11 % of SOC apart, read within ~2 mV (the OCV's 0.4-0.5 mV per %
    cancelled by the resistance's rise with SOC), below what separates them. Without the
    margin the choice changed 31 times in 20 minutes (measured), among groups up to 10 % of SOC
    above the weakest, and the observer's one SOC state was fed each in turn; with it, twice
    (one excursion to a group 8 % above, 160-680 s: which group is weakest is not observable
    there either, only less often mistaken)."""
    read, gap = group_trace(telecom(1200.0), RUN13)
    changes = int(np.sum(read[1:] != read[:-1]))
    assert read[0] == 3  # the weakest at rest
    assert changes <= 3, (
        f"the group read changed {changes} times (up to {100 * np.nanmax(gap):.1f} % of SOC "
        "above the weakest)"
    )
