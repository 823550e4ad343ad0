"""The compiled supervisor (in the core) against the scalar oracle it replaced.

Both compose the same parts: Python controllers that emit random opinions and events (trips,
resets, faults, unrelated kinds) and, in the second test, the SOC estimator (compiled in the
new core, the scalar oracle in the old one).
"""

from __future__ import annotations

import random
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config.soc import SocConfig
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.bms import (
    Commands,
    ControlOutput,
    Event,
    Measurements,
    SwitchKind,
)
from packpilot.contract.charger import ChargerCommand
from packpilot.contract.topology import PackInfo
from packpilot.control.soc import SocEstimator
from packpilot.control.supervisor import Supervisor
from tests.equivalence.common import assert_same_output, sequence
from tests.oracles.soc import SocEstimator as OracleSoc
from tests.oracles.supervisor import Supervisor as Oracle

KINDS = ["Fault", "ProtectionTripped", "LimitTripped", "ProtectionReset", "LimitReset", "Other"]


class RandomPart:
    """Opinions and events drawn from a seeded RNG: two instances with one seed agree."""

    def __init__(self, seed: int, n: int) -> None:
        self.rng = random.Random(seed)
        self.n = n

    def _flag(self) -> bool | None:
        return self.rng.choice([None, None, True, False])

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        r, n = self.rng, self.n
        charger = None
        if r.random() < 0.3:
            charger = ChargerCommand(r.uniform(0, 60), r.uniform(0, 20), r.random() < 0.7)
        events = tuple(
            Event(meas.t_s, r.choice(KINDS), r.choice([None, *range(n)]), "m", {"x": 1.0})
            for _ in range(r.choice([0, 0, 0, 1, 2]))
        )
        return ControlOutput(
            Commands(
                chg_on=tuple(self._flag() for _ in range(n)),
                dsg_on=tuple(self._flag() for _ in range(n)),
                charger=charger,
            ),
            events=events,
            status={"rnd": [r.random() for _ in range(n)]},
        )


def _info(n: int, relay: bool) -> PackInfo:
    kind = SwitchKind.RELAY if relay else SwitchKind.MOSFET_PAIR
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(2,) * n,
        cells_per_group=(3,) * n,
        switch_kind=(kind,) * n,
        capacity_ah=(5.0,) * n,
        ocv_soc=(0.0, 0.5, 1.0),
        ocv_v=(3.0, 3.7, 4.2),
    )


CONFIGS = st.builds(
    SupervisorConfig,
    init_time_s=st.sampled_from([0.0, 0.5, 2.0]),
    discharge_current_a=st.sampled_from([0.5, 5.0]),
    idle_after_s=st.sampled_from([0.0, 1.0, 5.0]),
    join_limit_v=st.sampled_from([0.05, 1.0, 3.0]),
    fault_hold_s=st.sampled_from([0.0, 0.3, 10.0]),
    shutdown_when_all_tripped=st.booleans(),
)


@settings(max_examples=200, deadline=None)
@given(
    data=st.data(),
    cfg=CONFIGS,
    n=st.integers(1, 4),
    relay=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_same_as_the_scalar_supervisor(
    data: Any, cfg: SupervisorConfig, n: int, relay: bool, seed: int
) -> None:
    info = _info(n, relay)
    new = Supervisor(cfg, info, methods=[RandomPart(seed, n)], safety=[RandomPart(seed + 1, n)])
    old = Oracle(cfg, info, methods=[RandomPart(seed, n)], safety=[RandomPart(seed + 1, n)])
    for k, (meas, dt) in enumerate(data.draw(sequence(n, 2, v_cell=(3.0, 4.2)))):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")
        assert str(new.mode) == str(old.mode)


@settings(max_examples=60, deadline=None)
@given(data=st.data(), cfg=CONFIGS, n=st.integers(1, 3), seed=st.integers(0, 2**16))
def test_same_with_a_compiled_part(data: Any, cfg: SupervisorConfig, n: int, seed: int) -> None:
    info = _info(n, True)
    soc = SocConfig(rest_time_s=1.0)
    new = Supervisor(
        cfg, info, methods=[RandomPart(seed, n)], safety=[SocEstimator.from_config(soc, info)]
    )
    old = Oracle(
        cfg,
        info,
        methods=[RandomPart(seed, n)],
        safety=[OracleSoc.from_config(soc, info, info.ocv_soc, info.ocv_v)],  # type: ignore[arg-type]
    )
    for k, (meas, dt) in enumerate(data.draw(sequence(n, 2, current=(-1.0, 1.0)))):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")
