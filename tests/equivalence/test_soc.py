"""The compiled SOC estimator against the scalar oracle it replaced (see ``common.py``)."""

from __future__ import annotations

from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config.soc import SocConfig
from packpilot.contract.bms import SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.soc import SocEstimator
from tests.equivalence.common import assert_same_output, sequence
from tests.oracles.soc import SocEstimator as Oracle

OCV_SOC = (0.0, 0.1, 0.5, 0.9, 1.0)
OCV_V = (3.0, 3.45, 3.7, 4.05, 4.2)


def _info(n: int, groups: int) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(groups,) * n,
        cells_per_group=(1,) * n,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
        capacity_ah=tuple(5.0 + 0.5 * i for i in range(n)),
    )


@settings(max_examples=150, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 3),
    groups=st.integers(1, 4),
    voltage=st.sampled_from(["min", "avg"]),
    blend=st.sampled_from([1.0, 0.5, 0.0]),
    rest_time_s=st.sampled_from([0.5, 2.0, 600.0]),
    soc0=st.sampled_from([None, 0.3, float("nan")]),
)
def test_same_as_the_scalar_estimator(
    data: Any, n: int, groups: int, voltage: str, blend: float, rest_time_s: float, soc0: Any
) -> None:
    cfg = SocConfig(rest_current_a=0.5, rest_time_s=rest_time_s, blend=blend, voltage=voltage)
    info = _info(n, groups)
    s0 = None if soc0 is None else [soc0] * n
    new = SocEstimator.from_config(cfg, info, OCV_SOC, OCV_V, s0)
    old = Oracle.from_config(cfg, info, OCV_SOC, OCV_V, s0)  # type: ignore[arg-type]
    seq = data.draw(sequence(n, groups, current=(-2.0, 2.0)))
    for k, (meas, dt) in enumerate(seq):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")
