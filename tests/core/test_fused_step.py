"""The one compiled step of a core gives what stepping its parts one by one gives."""

from __future__ import annotations

from typing import Any

from hypothesis import given
from hypothesis import strategies as st

from packpilot.config.charging import ChargingConfig
from packpilot.config.equalization import EqualizationConfig
from packpilot.config.limits import LimitsConfig
from packpilot.config.plausibility import PlausibilityConfig
from packpilot.config.protection import ProtectionConfig
from packpilot.config.sequencing import SequencingConfig
from packpilot.config.soc import SocConfig
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.bms import SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control import equalization
from packpilot.control.charging import METHOD as CHARGING
from packpilot.control.core import Core, Part
from packpilot.control.limits import method_for
from packpilot.control.plausibility import METHOD as PLAUSIBILITY
from packpilot.control.protection import METHOD as PROTECTION
from packpilot.control.sequencing import METHOD as SEQUENCING
from packpilot.control.soc import METHOD as SOC
from tests.budget import budget
from tests.core.drawn import assert_same_output, sequence


def _core(info: PackInfo) -> Core:
    fast = [
        {"name": "P1", "cutoff_v": 2.8, "t_max_s": 1.5},
        {"name": "P2", "cutoff_v": 3.0, "t_max_s": 1.0},
        {"name": "P3", "cutoff_v": 3.2, "t_max_s": 0.5},
    ]
    protection = ProtectionConfig.model_validate({"parameters": fast})
    parts = [
        Part.build(SEQUENCING, SequencingConfig(t_mode=0.3), [info]),
        Part.build(PROTECTION, protection, [info]),
        Part.build(CHARGING, ChargingConfig(), [info]),
        Part.build(
            equalization.method_for(EqualizationConfig(), [info]),
            EqualizationConfig(sample_period_s=0.5),
            [info],
        ),
        Part.build(method_for(LimitsConfig()), LimitsConfig(), [info]),
        Part.build(PLAUSIBILITY, PlausibilityConfig(), [info]),
        Part.build(SOC, SocConfig(rest_time_s=1.0), [info]),
    ]
    return Core([info], parts, SupervisorConfig())


@budget(200)
@given(data=st.data(), n=st.integers(1, 3), kind=st.sampled_from(list(SwitchKind)))
def test_fused_and_part_by_part_agree(data: Any, n: int, kind: SwitchKind) -> None:
    info = PackInfo(
        n_batteries=n,
        groups_per_battery=(2,) * n,
        cells_per_group=(3,) * n,
        switch_kind=(kind,) * n,
        capacity_ah=(5.0,) * n,
        ocv_soc=(0.0, 0.5, 1.0),
        ocv_v=(3.0, 3.7, 4.2),
    )
    fused, parts = _core(info), _core(info)
    assert fused.fused
    parts.fused = False
    for k, (meas, dt) in enumerate(data.draw(sequence(n, 2, current=(-1.0, 1.0)))):
        assert_same_output(fused.step(meas, dt), parts.step(meas, dt), n, f"step {k}")
