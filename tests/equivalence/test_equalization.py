"""The compiled equalization method against the scalar oracle it replaced (see ``common.py``).

Random measurement sequences (short T1/T2/sample periods so that every rule fires within a
sequence; NaN/inf/zero/negative group voltages, wrong group counts, NaN/inf currents, absent
and unreported batteries, time going backwards, zero/negative/NaN dt), group voltages on a
binary lattice so that ΔV equals ``dv_set_v`` exactly, mixed group counts, preset AH and
remaining times; and closed loops on the plant (the examples that run the method, and variants
with sensor faults, string-current mode and bidirectional equalizers). Commands, events and
status equal at every step; AH, timers, ledger and counts equal at the end.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config import load_config
from packpilot.config.equalization import EqualizationConfig
from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core, Part
from packpilot.control.equalization import (
    EqualizationController,
    balancing_time_s,
    equalizer_current_a,
    formula1,
    formula2,
    lower_median,
    rules,
    sample_groups,
)
from packpilot.sim.runner import Runner
from tests.equivalence.common import assert_same_output, same, sequence
from tests.oracles import equalization as oracle
from tests.oracles.equalization import EqualizationController as Oracle

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@st.composite
def configs(draw: Any) -> EqualizationConfig:
    """Non-default configs whose timers fire within a short sequence, and the default."""
    if draw(st.integers(0, 7)) == 0:
        return EqualizationConfig()
    t2 = draw(st.sampled_from([0.3, 1.0, 2.5]))
    mode = draw(st.sampled_from(["string_current", "fixed_current"]))
    eq_max = draw(st.sampled_from([0.5, 2.0, 20.0]))
    return EqualizationConfig(
        dv_set_v=draw(st.sampled_from([0.001, 0.005, 0.03])),
        t1_s=t2 + draw(st.sampled_from([0.2, 1.0, 4.0])),
        t2_s=t2,
        n_ah=draw(st.sampled_from([0.0, 0.05, 0.5, 1.0])),
        sample_period_s=draw(st.sampled_from([0.1, 0.5, 1.0, 3.0])),
        time_mode=mode,
        min_current_a=draw(st.sampled_from([0.0, 0.5, 5.0])),
        equalizer_max_a=eq_max,
        fixed_current_a=draw(st.sampled_from([0.1, 0.5])),
        balance_at_rest=mode == "fixed_current" and draw(st.booleans()),
        max_balance_time_s=draw(st.sampled_from([None, 0.5, 5.0, 1000.0])),
        equalizer=draw(st.sampled_from(["unidirectional", "bidirectional"])),
    )


def _info(groups: Sequence[int], balancers: bool = True) -> PackInfo:
    n = len(groups)
    return PackInfo(
        n_batteries=n,
        groups_per_battery=tuple(groups),
        cells_per_group=(1,) * n,
        switch_kind=(SwitchKind.RELAY,) * n,
        has_balancers=balancers,
    )


ROWS = (
    "ah",
    "hi_timer_s",
    "lo_timer_s",
    "remaining_s",
    "dv_v",
    "ledger_time_s",
    "ledger_gross_ah",
    "ledger_net_ah",
)


def _assert_same_state(new: EqualizationController, old: Oracle) -> None:
    for b, (s_new, s_old) in enumerate(zip(new.strings, old.strings, strict=True)):
        for name in ROWS:
            assert same(getattr(s_new, name), getattr(s_old, name)), (b, name)
        assert s_new.counts == s_old.counts, b
        assert s_new.faulted == s_old.faulted, b
        assert same(s_new.since_sample_s, s_old.since_sample_s), b


def _preset(data: Any, new: EqualizationController, old: Oracle, groups: Sequence[int]) -> None:
    """Start some strings with AH (all positive: the subtraction fires at once) and
    remaining balancing times, as a long-running controller would have them."""
    for b, m in enumerate(groups):
        if data.draw(st.booleans()):
            ah = data.draw(st.lists(st.floats(0.0, 1.0), min_size=m, max_size=m))
            times = st.sampled_from([0.0, 0.3, 2.0, 50.0])
            rem = data.draw(st.lists(times, min_size=m, max_size=m))
            new.strings[b].ah = ah
            old.strings[b].ah = list(ah)
            new.strings[b].remaining_s = rem
            old.strings[b].remaining_s = list(rem)


def _run(
    new: EqualizationController, old: Oracle, seq: list[tuple[Measurements, float]], n: int
) -> None:
    for k, (meas, dt) in enumerate(seq):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")
    _assert_same_state(new, old)


@settings(max_examples=250, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 3),
    groups=st.integers(1, 5),
    cfg=configs(),
    balancers=st.booleans(),
)
def test_same_as_the_scalar_controller(
    data: Any, n: int, groups: int, cfg: EqualizationConfig, balancers: bool
) -> None:
    info = _info((groups,) * n, balancers)
    new, old = EqualizationController(cfg, info), Oracle(cfg, info)
    _preset(data, new, old, info.groups_per_battery)
    seq = data.draw(sequence(n, groups, steps=120, current=(-8.0, 8.0), bad_groups=12))
    _run(new, old, seq, n)


@settings(max_examples=100, deadline=None)
@given(data=st.data(), groups=st.lists(st.integers(1, 4), min_size=2, max_size=3), cfg=configs())
def test_mixed_group_counts(data: Any, groups: list[int], cfg: EqualizationConfig) -> None:
    info = _info(groups)
    new, old = EqualizationController(cfg, info), Oracle(cfg, info)
    _preset(data, new, old, groups)
    seq = data.draw(sequence(len(groups), groups, steps=80, current=(-8.0, 8.0), bad_groups=20))
    _run(new, old, seq, len(groups))


def _on_lattice(meas: Measurements) -> Measurements:
    """Group voltages rounded to 1/32 V: ΔV of 1/64 V multiples, exactly."""

    def snap(v: float) -> float:
        return round(v * 32.0) / 32.0 if math.isfinite(v) else v

    bats = tuple(
        dataclasses.replace(b, group_voltages_v=tuple(snap(v) for v in b.group_voltages_v))
        for b in meas.batteries
    )
    return dataclasses.replace(meas, batteries=bats)


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 2),
    groups=st.integers(2, 4),
    dv_set=st.sampled_from([1 / 64, 1 / 32]),
    t2=st.sampled_from([0.3, 1.0]),
)
def test_dv_equal_to_dv_set(data: Any, n: int, groups: int, dv_set: float, t2: float) -> None:
    cfg = EqualizationConfig(dv_set_v=dv_set, t1_s=t2 + 0.5, t2_s=t2, sample_period_s=0.1)
    info = _info((groups,) * n)
    new, old = EqualizationController(cfg, info), Oracle(cfg, info)
    _preset(data, new, old, info.groups_per_battery)
    seq = data.draw(sequence(n, groups, steps=80, current=(-8.0, 8.0), v_cell=(3.0, 3.2)))
    _run(new, old, [(_on_lattice(m), dt) for m, dt in seq], n)


@settings(max_examples=100, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 2),
    groups=st.integers(1, 4),
    tick=st.sampled_from([0.1, 0.2, 0.3, 0.7]),
    period=st.sampled_from([0.1, 0.3, 1.0, 2.1]),
    t2=st.sampled_from([0.5, 1.0, 2.0]),
    t1_more=st.sampled_from([0.5, 1.0]),
)
def test_fixed_tick(
    data: Any, n: int, groups: int, tick: float, period: float, t2: float, t1_more: float
) -> None:
    """A BMS with a fixed tick: sums of ticks that fall a rounding error short of the sample
    period or of T1/T2 (ten 0.1 s ticks make 0.9999999999999999 s) still fire."""
    cfg = EqualizationConfig(
        dv_set_v=0.005, t1_s=t2 + t1_more, t2_s=t2, sample_period_s=period, min_current_a=0.1
    )
    info = _info((groups,) * n)
    new, old = EqualizationController(cfg, info), Oracle(cfg, info)
    seq = data.draw(sequence(n, groups, steps=120, current=(-8.0, 8.0)))
    ticked = [(dataclasses.replace(m, t_s=k * tick), tick) for k, (m, _) in enumerate(seq)]
    _run(new, old, ticked, n)


# ------------------------------------------------------------------- the pure helpers


@settings(max_examples=300, deadline=None)
@given(
    cfg=configs(),
    volts=st.lists(st.floats(0.5, 60.0), min_size=1, max_size=12),
    data=st.data(),
    ts=st.sampled_from([0.1, 1.0, 7.0, 360.0]),
)
def test_sample_groups_same_as_the_scalar_function(
    cfg: EqualizationConfig, volts: list[float], data: Any, ts: float
) -> None:
    m = len(volts)
    ah = data.draw(st.lists(st.floats(0.0, 1.0), min_size=m, max_size=m))
    hi = data.draw(st.lists(st.floats(0.0, 10.0), min_size=m, max_size=m))
    lo = data.draw(st.lists(st.floats(0.0, 10.0), min_size=m, max_size=m))
    new = sample_groups(volts, ah, hi, lo, ts, cfg)
    old = oracle.sample_groups(volts, ah, hi, lo, ts, cfg)
    assert same(dataclasses.astuple(new), dataclasses.astuple(old))
    for u_new, u_old in zip(new.updates, old.updates, strict=True):
        assert same(dataclasses.astuple(u_new), dataclasses.astuple(u_old))


@settings(max_examples=300, deadline=None)
@given(
    cfg=configs(),
    ah=st.one_of(st.floats(-1.0, 2.0), st.just(0.0)),
    cur=st.one_of(st.floats(-50.0, 50.0), st.sampled_from([0.0, -0.0, math.nan, math.inf])),
    xs=st.lists(st.floats(-5.0, 5.0), min_size=1, max_size=9),
)
def test_helpers_same_as_the_scalar_functions(
    cfg: EqualizationConfig, ah: float, cur: float, xs: list[float]
) -> None:
    assert same(equalizer_current_a(cur, cfg), float(oracle.equalizer_current_a(cur, cfg)))
    assert same(balancing_time_s(ah, cur, cfg), float(oracle.balancing_time_s(ah, cur, cfg)))
    assert same(formula1(ah, cfg.n_ah), oracle.formula1(ah, cfg.n_ah))
    assert same(formula2(ah), oracle.formula2(ah))
    assert same(lower_median(xs), oracle.lower_median(xs))


@settings(max_examples=500, deadline=None)
@given(
    xs=st.lists(
        st.one_of(
            st.floats(-1e300, 1e300, allow_nan=False, allow_infinity=False),
            st.floats(-1.0, 1.0),
            st.floats(1e-300, 1e-290),
            st.sampled_from([1e16, 1.0, 1e-16, -1e16, 0.1, 2.0**-1074, -0.0]),
        ),
        max_size=20,
    )
)
def test_exact_sum_is_fsum(xs: list[float]) -> None:
    try:
        want = math.fsum(xs)
    except OverflowError:
        return  # math.fsum raises; the kernel returns inf (never reached by group voltages)
    a = np.array(xs, np.float64)
    got = rules.exact_sum(a, len(xs), np.empty(max(len(xs), 1)))
    assert same(float(got), want), (xs, got, want)


# ------------------------------------------------------------------- closed loops


class Twin:
    """The compiled controller drives the loop; the oracle sees the same measurements and
    must say exactly the same at every step."""

    def __init__(self, new: EqualizationController) -> None:
        self.new = new
        self.old = Oracle(new.config, new.pack)
        self.n = new.pack.n_batteries
        self.steps = 0

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        out = self.new.step(meas, dt_s)
        assert_same_output(out, self.old.step(meas, dt_s), self.n, f"t = {meas.t_s}")
        self.steps += 1
        return out


def _twin(runner: Runner) -> list[Twin]:
    """Put a :class:`Twin` where the runner's core runs the method."""
    core = runner.controller
    assert isinstance(core, Core)
    config = runner.cfg.equalization or EqualizationConfig()
    twins: list[Twin] = []
    parts: list[Any] = []
    for x in core.parts:
        if isinstance(x, Part) and x.method.name == "equalization":
            twins.append(Twin(EqualizationController(config, runner.info)))
            parts.append(twins[-1])
        else:
            parts.append(x)
    runner.controller = Core(core.infos, parts, core.supervisor_config)
    return twins


CLOSED_LOOPS: list[tuple[str, float, dict[str, Any], list[dict[str, Any]]]] = [
    ("equalization_uav12s", 960.0, {}, []),
    (
        "equalization_uav12s",
        960.0,
        {"time_mode": "string_current", "balance_at_rest": False, "equalizer": "bidirectional",
         "t1_s": 20.0, "t2_s": 10.0},
        [{"kind": "sensor_nan", "at_s": 300.0, "until_s": 340.0, "battery": "pack",
          "quantity": "current_a"}],
    ),
    (
        "telecom_string",
        15000.0,
        {},
        [{"kind": "sensor_dropout", "at_s": 2000.0, "until_s": 2600.0, "battery": "string"},
         {"kind": "sensor_nan", "at_s": 5000.0, "until_s": 5100.0, "battery": "string",
          "quantity": "current_a"}],
    ),
    ("uav_mission", 600.0, {}, []),
]  # fmt: skip


@pytest.mark.parametrize(("name", "duration_s", "eq", "faults"), CLOSED_LOOPS)
def test_closed_loop_on_the_plant(
    name: str, duration_s: float, eq: dict[str, Any], faults: list[dict[str, Any]]
) -> None:
    cfg = load_config(EXAMPLES / f"{name}.toml")
    data = cfg.model_dump(mode="json")
    data["sim"].update(duration_s=duration_s, progress=False)
    data["equalization"] = {**(data.get("equalization") or {}), **eq}
    data["faults"] = [*(data.get("faults") or []), *faults]
    cfg = type(cfg).model_validate(data)
    runner = Runner(cfg)
    twins = _twin(runner)
    assert len(twins) == 1
    res = runner.run()
    assert twins[0].steps == len(res.trace.t_s) > 0
    _assert_same_state(twins[0].new, twins[0].old)
