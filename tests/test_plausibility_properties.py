"""Property: the plausibility monitor keeps the loop running for any input (NaN, inf, wrong
battery counts, odd dt, arbitrary commands) and always returns a well-formed ControlOutput."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import Commands, ControlOutput, Measurements
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo
from packpilot.control.plausibility import (
    KINDS,
    SENSOR_KINDS,
    PlausibilityConfig,
    PlausibilityMonitor,
)
from tests.budget import budget
from tests.test_limits_helpers import ANY_FLOAT, measurements, pack_infos

FLAGS = st.lists(st.sampled_from([True, False, None]), max_size=5).map(tuple)
COMMANDS = st.builds(Commands, chg_on=FLAGS, dsg_on=FLAGS)


def check_output(out: ControlOutput, n: int, mon: PlausibilityMonitor) -> None:
    assert isinstance(out, ControlOutput)
    cmd = out.commands
    assert len(cmd.chg_on) == n and len(cmd.dsg_on) == n
    assert all(x is None or x is False for x in cmd.chg_on + cmd.dsg_on)
    assert cmd.charger is None or cmd.charger == CHARGER_OFF
    for ev in out.events:
        assert ev.kind in ("Fault", "FaultCleared", "ReserveEngaged")
        assert ev.battery is None or 0 <= ev.battery < n
        if ev.kind == "ReserveEngaged":  # only a battery with a latched sensor fault
            assert ev.battery is not None and mon.faults(ev.battery) & set(SENSOR_KINDS)
            continue
        assert ev.data["kind"] in KINDS
    for name, vals in out.status.items():
        assert len(vals) == n, name
    for i in range(n):
        assert out.status["plaus_faults"][i] == ",".join(sorted(mon.faults(i)))
        if mon.welded[i]:
            assert cmd.chg_on[i] is None or "relay_stuck_open" in mon.faults(i)


@budget(200)
@given(
    info=pack_infos(),
    steps=st.lists(
        st.tuples(measurements(), ANY_FLOAT, st.none() | COMMANDS), min_size=1, max_size=15
    ),
    clears=st.lists(st.integers(-1, 4), max_size=3),
)
def test_arbitrary_inputs_never_raise(
    info: PackInfo,
    steps: list[tuple[Measurements, float, Commands | None]],
    clears: list[int],
) -> None:
    mon = PlausibilityMonitor(
        PlausibilityConfig(nonfinite_delay_s=0.0, switch_delay_s=0.0, stuck_time_s=1.0), info
    )
    for k, (meas, dt, cmd) in enumerate(steps):
        if k < len(clears):
            mon.clear_faults(None if clears[k] < 0 else clears[k])
        out = mon.step(meas, dt)
        check_output(out, info.n_batteries, mon)
        if cmd is not None:
            mon.note_commands(cmd)
