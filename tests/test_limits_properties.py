"""Property: any measurement sequence (NaN, inf, wrong battery counts, absent batteries, odd
dt) runs through LimitsController without raising and yields a well-formed ControlOutput."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import ControlOutput, Measurements
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo
from packpilot.control.limits import TIER_EVENT, LimitsConfig, LimitsController
from tests.budget import budget
from tests.test_limits_helpers import ANY_FLOAT, Driver, healthy, measurements, pack_infos

LIMIT_EVENTS = {*TIER_EVENT.values(), "LimitReset"}


def check_output(out: ControlOutput, n: int, ctl: LimitsController) -> None:
    assert isinstance(out, ControlOutput)
    cmd = out.commands
    assert len(cmd.chg_on) == n and len(cmd.dsg_on) == n
    assert all(x is None or x is False for x in cmd.chg_on + cmd.dsg_on)  # never closes
    assert cmd.charger is None or cmd.charger == CHARGER_OFF
    assert cmd.balancer_a is None and cmd.aux_relay_closed is None
    for i in range(n):
        assert (cmd.chg_on[i] is False) == ctl.tripped(i, "charge")
        assert (cmd.dsg_on[i] is False) == ctl.tripped(i, "discharge")
    for ev in out.events:
        assert ev.kind in LIMIT_EVENTS
        assert ev.battery is not None and 0 <= ev.battery < n
    for name, vals in out.status.items():
        assert len(vals) == n, name
    for x in list(out.status["limit_chg_a"]) + list(out.status["limit_dsg_a"]):
        assert isinstance(x, float) and (math.isnan(x) or x >= 0.0)


@budget(200)
@given(
    info=pack_infos(),
    steps=st.lists(st.tuples(measurements(), ANY_FLOAT), min_size=1, max_size=15),
    resets=st.lists(st.integers(-1, 4), max_size=3),
)
def test_arbitrary_measurements_never_raise(
    info: PackInfo, steps: list[tuple[Measurements, float]], resets: list[int]
) -> None:
    ctl = LimitsController(LimitsConfig(), info)
    for k, (meas, dt) in enumerate(steps):
        if k < len(resets):
            ctl.reset_trips(None if resets[k] < 0 else resets[k])
        check_output(ctl.step(meas, dt), info.n_batteries, ctl)


@budget(200)
@given(
    steps=st.lists(
        st.tuples(
            st.floats(3.0, 4.15),
            st.floats(-1.5, 12.0),
            st.floats(7.0, 38.0),
            st.floats(0.0, 1.0),
        ),
        min_size=1,
        max_size=40,
    ),
    docked=st.booleans(),
)
def test_inside_the_operating_window_nothing_fires(
    steps: list[tuple[float, float, float, float]], docked: bool
) -> None:
    """Below every warn threshold: no event, no command (the MOL is the edge of normal)."""
    d = Driver()
    for v, c_rate, temp, soc in steps:
        bm = healthy(
            min_cell_v=v,
            max_cell_v=v,
            current_a=c_rate * 5.0,
            temp_c=temp,
            min_temp_c=temp,
            soc=soc,
        )
        out = d.step(bm, docked=docked)
        assert not out.events
        assert out.commands.chg_on == (None,) and out.commands.dsg_on == (None,)
