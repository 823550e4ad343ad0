"""Property-based tests of SequencingController on arbitrary measurement sequences.

Whatever the inputs (N = 2..6, any voltages/currents, insertions, removals, docking, NaN), the
commands must satisfy the method's safety invariants period by period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.sequencing import (
    SequencingConfig,
    SequencingController,
    battery_measurement,
)
from tests.budget import budget

CFG = SequencingConfig()
STATES = {"DISCHARGING", "STANDBY", "CHARGING", "OFF"}


@dataclass(frozen=True)
class Sample:
    volts: tuple[float, ...]
    currs: tuple[float, ...]
    present: tuple[bool, ...]
    docked: bool


@st.composite
def scenarios(draw: st.DrawFn, allow_nan: bool = True) -> tuple[int, float, list[Sample]]:
    n = draw(st.integers(2, 6))
    dt = draw(st.sampled_from([0.01, 0.02, 0.05, 0.1, 0.2, 0.5]))
    steps = draw(st.integers(1, 40))
    base = [draw(st.floats(18.0, 26.0)) for _ in range(n)]
    voltage = st.floats(-0.6, 0.6)
    current = st.one_of(st.just(0.0), st.floats(-15.0, 40.0))
    samples: list[Sample] = []
    present = [draw(st.booleans()) or k == 0 for k in range(n)]
    for _ in range(steps):
        if draw(st.integers(0, 9)) == 0:
            k = draw(st.integers(0, n - 1))
            present[k] = not present[k]
        volts = []
        currs = []
        for k in range(n):
            base[k] += draw(voltage) * 0.2
            v = base[k] + draw(voltage)
            i = draw(current)
            if allow_nan and draw(st.integers(0, 24)) == 0:
                if draw(st.booleans()):
                    v = math.nan
                else:
                    i = draw(st.sampled_from([math.nan, math.inf, -math.inf]))
            volts.append(v)
            currs.append(i)
        samples.append(
            Sample(tuple(volts), tuple(currs), tuple(present), draw(st.integers(0, 14)) == 0)
        )
    return n, dt, samples


def _pack(n: int) -> PackInfo:
    return PackInfo(n, (6,) * n, (1,) * n, (SwitchKind.MOSFET_PAIR,) * n)


def _meas(t: float, s: Sample) -> Measurements:
    return Measurements(
        t_s=t,
        batteries=tuple(
            battery_measurement(v, i, p)
            for v, i, p in zip(s.volts, s.currs, s.present, strict=True)
        ),
        bus_v=math.nan,
        docked=s.docked,
    )


def _bad(s: Sample) -> bool:
    return any(
        p and not (math.isfinite(v) and v >= 0.0 and math.isfinite(i))
        for v, i, p in zip(s.volts, s.currs, s.present, strict=True)
    )


def _check_patterns(out: ControlOutput, s: Sample, n: int) -> None:
    states = list(out.status["seq_state"])
    chg, dsg = out.commands.chg_on, out.commands.dsg_on
    assert len(states) == len(chg) == len(dsg) == n
    for k, (state, c, d) in enumerate(zip(states, chg, dsg, strict=True)):
        assert state in STATES
        assert isinstance(c, bool) and isinstance(d, bool)
        if state == "STANDBY":
            assert not c and d, "STANDBY: charge FET never on, discharge FET on (diode-OR)"
        elif state == "OFF":
            assert not c and not d
        elif state == "DISCHARGING":
            assert d
        else:
            assert c
        if not s.present[k]:
            assert state == "OFF" and not c and not d, "an absent battery is OFF"


@budget(200)
@given(scenarios())
def test_commanded_states_are_consistent_and_nan_fails_safe(
    case: tuple[int, float, list[Sample]],
) -> None:
    n, dt, samples = case
    ctrl = SequencingController(CFG, _pack(n))
    in_fault = False
    for step, s in enumerate(samples):
        out = ctrl.step(_meas(step * dt, s), dt)
        _check_patterns(out, s, n)
        faults = [e for e in out.events if e.kind == "Fault"]
        if _bad(s):
            assert out.commands.chg_on == (False,) * n, "fail-safe: every charge FET off"
            assert out.commands.dsg_on == s.present, "fail-safe: present batteries' dsg FET on"
            assert set(out.status["seq_mode"]) == {"fault"}
            assert len(faults) == (0 if in_fault else 1)
            in_fault = True
        else:
            assert not faults
            assert out.status["seq_mode"][0] in {"discharge", "charge"}
            in_fault = False


@budget(200)
@given(scenarios(allow_nan=False))
def test_r3_r4_deadline_is_respected(case: tuple[int, float, list[Sample]]) -> None:
    """Once a FET-off path is seen conducting, the FET is on no later than t_on after."""
    _check_deadline(case)


_V = (25.0, 18.0, 18.0, 23.0, 18.0, 26.0)
_P = (True, False, False, True, False, True)
_Z = (0.0,) * 6


def test_r3_r4_deadline_known_counterexample() -> None:
    """Issue #18's shrunk case (was a strict xfail): a diode conducting at 2.8 s was closed by
    the load merge and reopened by the cross-current guard in the same period, so R3's timer
    restarted past t_on. Both rules are gone (issue #15); kept as a regression test."""
    samples = [Sample(_V, _Z, _P, True) for _ in range(7)]
    samples += [Sample(_V, _Z, _P, False) for _ in range(5)]
    samples += [
        Sample((25.0, 18.0, 18.0, 23.25, 18.0, 26.0), _Z, _P, False),
        Sample(_V, (0.0, 0.0, 0.0, 2.5, 0.0, 0.0), _P, False),
        Sample(_V, (1.0, 0.0, 0.0, 20.0, 0.0, 0.0), _P, False),
    ]
    _check_deadline((6, 0.2, samples))


_V1 = (23.0, 23.362741493785908, 18.0, 18.0, 25.0)
_V2 = (23.0, 23.262741493785906, 18.0, 18.0, 25.0)
_P1 = (True, True, False, False, False)
_P2 = (True, True, False, False, True)
_Z5 = (0.0,) * 5


def test_r3_deadline_when_the_engage_rule_closed_a_conducting_battery() -> None:
    """Found by the random deadline property after the co-discharge change (dt 0.5 s > t_on):
    at 12.5 s battery 0's diode carries 3 A; the engage rule closes its charge FET, R3 closes
    battery 4's, and the hand-over reopened battery 0 on a prediction that battery 4 would
    charge it: the diode kept conducting past t_on. A battery whose diode carried discharge
    current over the last period sources, whichever rule closes it (rules.py, R3 loop)."""
    rows = [Sample(_V1, _Z5, _P1, True)] * 10 + [Sample(_V1, _Z5, _P2, True)] * 5
    rows += [Sample(_V2, _Z5, _P2, True)] * 4 + [Sample(_V2, _Z5, _P2, False)] * 3
    rows += [
        Sample(_V2, (1.0, 0.0, 0.0, 0.0, -1.0), _P2, False),
        Sample(_V2, (-1.0, 0.0, 0.0, 0.0, 0.0), _P2, False),
        Sample((22.9, 23.762741493785906, 18.0, 18.0, 25.0), (0.0, 4.0, 0.0, 0.0, 0.0), _P2, False),
        Sample((23.407873584811522, *_V2[1:]), (3.0, 21.0, 0.0, 0.0, 1.0), _P2, False),
    ]
    _check_deadline((5, 0.5, rows))


def _check_deadline(case: tuple[int, float, list[Sample]]) -> None:
    n, dt, samples = case
    ctrl = SequencingController(CFG, _pack(n))
    prev: ControlOutput | None = None
    since: list[float | None] = [None] * n
    for step, s in enumerate(samples):
        t = step * dt
        out = ctrl.step(_meas(t, s), dt)
        mode = out.status["seq_mode"][0]
        for k in range(n):
            if prev is None or prev.status["seq_mode"][0] != mode or not s.present[k]:
                since[k] = None
                continue
            pc, pd = prev.commands.chg_on[k], prev.commands.dsg_on[k]
            if mode == "discharge":
                conducting = pd and not pc and s.currs[k] > CFG.i_det
                still_off = out.commands.dsg_on[k] and not out.commands.chg_on[k]
            else:
                conducting = bool(pc) and not pd and s.currs[k] < -CFG.i_det
                still_off = out.commands.chg_on[k] and not out.commands.dsg_on[k]
            if not conducting:
                since[k] = None
                continue
            if since[k] is None:
                since[k] = t
            if still_off:
                start = since[k]
                assert start is not None
                # Waiting until the next sample must not overrun the deadline.
                assert t - start + dt <= CFG.t_on + 1e-6, (k, t, start, dt)
            else:
                since[k] = None
        prev = out


I_LIM = CFG.charge_limit_c * CFG.default_capacity_ah
"""Charge limit of a battery of unknown capacity (the PackInfo here states none): 2.5 A."""


@budget(200)
@given(scenarios(allow_nan=False))
def test_charge_fet_follows_the_new_invariant(case: tuple[int, float, list[Sample]]) -> None:
    """Issue #15's invariant, period by period on arbitrary samples:

    * STANDBY never has its charge FET on;
    * a charge FET closes (discharge mode) only on a battery sourcing current through its
      diode (R3), or when afterwards the controller's zero-load prediction puts no engaged
      battery above its charge limit (unless R3 closed some battery in the same period, which
      outranks it and is flagged ``seq_at_risk``);
    * an engaged battery charged by more than i_rev while a sibling sources current has its
      charge FET opened in that same period (the reverse cut: one control period).
    """
    n, dt, samples = case
    ctrl = SequencingController(CFG, _pack(n))
    prev_chg: tuple[bool | None, ...] = (False,) * n
    prev_state: list[str] = ["OFF"] * n
    prev_mode = "discharge"
    for step, s in enumerate(samples):
        t = step * dt
        out = ctrl.step(_meas(t, s), dt)
        states = list(out.status["seq_state"])
        chg = out.commands.chg_on
        for state, c in zip(states, chg, strict=True):
            if state == "STANDBY":
                assert c is False
        mode = str(out.status["seq_mode"][0])
        if mode == prev_mode == "discharge":
            sourcing = [s.present[k] and s.currs[k] > CFG.i_det for k in range(n)]
            newly = [bool(chg[k]) and not prev_chg[k] for k in range(n)]
            by_r3 = any(newly[k] and sourcing[k] for k in range(n))
            zl = out.status["seq_zero_load_into_a"]
            for k in range(n):
                if newly[k] and not sourcing[k] and not by_r3:
                    assert states[k] == "DISCHARGING"
                    for j in range(n):
                        if chg[j]:
                            z = zl[j]
                            assert isinstance(z, float) and z <= I_LIM + 1e-9, (k, j, z)
                fed = any(j != k and sourcing[j] for j in range(n))
                was_engaged = prev_chg[k] and prev_state[k] == "DISCHARGING"
                if was_engaged and s.present[k] and fed and s.currs[k] < -CFG.i_rev:
                    assert chg[k] is False, (k, s.currs)
        prev_chg, prev_mode, prev_state = chg, mode, states


@budget(200)
@given(scenarios(allow_nan=True))
def test_controller_is_a_pure_function_of_its_inputs(
    case: tuple[int, float, list[Sample]],
) -> None:
    n, dt, samples = case
    a = SequencingController(CFG, _pack(n))
    b = SequencingController(CFG, _pack(n))
    for step, s in enumerate(samples):
        m = _meas(step * dt, s)
        oa, ob = a.step(m, dt), b.step(m, dt)
        assert oa.commands == ob.commands
        assert oa.events == ob.events
