"""The compiled plausibility monitor against the scalar oracle it replaced (see ``common.py``).

Besides ``step`` (commands, events, status at every step), the monitor's side doors are driven
too: the merged commands the supervisor notes after each step (``note_commands``, with
``None`` = no opinion, and tuples too short or too long), service resets (``clear_faults`` of
one battery, of every battery, of unknown kinds or batteries) and the read-outs
(``faults``, ``welded``, ``pack_fault``). Closed loops: the measurements and final merged
commands of real runs (the example mission, the fault-injection scenarios) replayed into both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config import load_config, parse_config
from packpilot.config.plausibility import PlausibilityConfig
from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.topology import PackInfo
from packpilot.control.plausibility import KINDS, PlausibilityMonitor
from packpilot.control.plausibility.rules import REACTIONS
from packpilot.sim.runner import Runner
from tests.equivalence.common import assert_same_output, sequence
from tests.oracles.plausibility import PlausibilityMonitor as Oracle

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

CONFIGS = [
    PlausibilityConfig(),
    # fast: every delay short, a stale limit the strategies cross, sensor faults clear quickly
    PlausibilityConfig(
        nonfinite_delay_s=0.0,
        range_delay_s=0.2,
        stuck_time_s=0.5,
        stuck_temp_time_s=1.0,
        stuck_current_c=0.2,
        max_sample_age_s=1.0,
        sum_delay_s=0.0,
        switch_delay_s=0.0,
        clear_after_s=0.5,
    ),
    # narrow ranges (out_of_range on cells, groups, battery, temperature, current, SOC), no
    # stuck checks, a tight sum tolerance
    PlausibilityConfig(
        cell_v_range=(3.0, 4.0),
        temp_range_c=(0.0, 50.0),
        current_range_c=(-2.0, 4.0),
        soc_range=(0.1, 0.9),
        range_delay_s=0.0,
        stuck_time_s=None,
        stuck_temp_time_s=None,
        sum_tolerance_v_per_group=0.01,
        clear_after_s=1.0,
    ),
    # stuck at once (even a NaN track: limit - EPS < 0), never loaded threshold, instant clear
    PlausibilityConfig(
        stuck_time_s=1e-10,
        stuck_temp_time_s=1e-10,
        stuck_current_c=0.0,
        nonfinite_delay_s=0.3,
        switch_delay_s=0.2,
        clear_after_s=0.0,
    ),
    # only the temperature stuck check, with a long voltage range on few cells
    PlausibilityConfig(stuck_time_s=None, stuck_temp_time_s=0.5, stuck_current_c=1.0),
]

FLAGS = st.lists(st.sampled_from([True, False, None]), max_size=5).map(tuple)
COMMANDS = st.builds(Commands, chg_on=FLAGS, dsg_on=FLAGS)
CLEAR = st.one_of(
    st.none(),
    st.tuples(
        st.sampled_from([None, 0, 1, 2, 5, -1]),
        st.one_of(
            st.none(),
            st.lists(st.sampled_from([*KINDS, "bogus"]), max_size=4),
        ),
    ),
)


def _infos(n: int, draw: Any) -> PackInfo:
    kinds = tuple(draw(st.sampled_from(list(SwitchKind))) for _ in range(n))
    caps = draw(
        st.sampled_from(
            [
                tuple(5.0 + 0.5 * i for i in range(n)),
                (),  # not given: the battery's reported full capacity counts
                (math.nan,) * n,
                (0.0,) * n,
            ]
        )
    )
    groups = draw(
        st.one_of(
            st.lists(st.integers(0, 5), min_size=n, max_size=n),
            st.just(None),
        )
    )
    return PackInfo(
        n_batteries=n,
        groups_per_battery=tuple(groups) if groups is not None else (3,) * n,
        cells_per_group=tuple(draw(st.integers(0, 3)) for _ in range(n)),
        switch_kind=kinds,
        capacity_ah=caps,
    )


def _same_readouts(new: PlausibilityMonitor, old: Oracle, n: int, where: str) -> None:
    for i in range(n):
        assert new.faults(i) == old.faults(i), (where, i)
    assert new.welded == old.welded, where
    assert new.pack_fault == old.pack_fault, where


SEEN: set[str] = set()
"""What the drawn sequences made the monitors do (see the coverage assertions)."""


def _note(out: ControlOutput) -> None:
    for e in out.events:
        d = e.data
        SEEN.add(f"{e.kind}:{d['kind']}")
        SEEN.add(f"{e.kind}:battery={'pack' if e.battery is None else 'battery'}")
        if e.kind == "Fault":
            SEEN.add(f"reaction:{d['reaction']}")
            SEEN.add(f"value:{type(d['value']).__name__}")
        else:
            SEEN.add(f"manual:{d['manual']}")
    if any(out.status["plaus_isolated"]):
        SEEN.add("isolated")


def _drive(
    info: PackInfo,
    cfg: PlausibilityConfig,
    seq: list[tuple[Measurements, float]],
    notes: list[Commands | None],
    clears: list[Any],
) -> None:
    n = info.n_batteries
    new = PlausibilityMonitor(cfg, info)
    old = Oracle(cfg, info)
    for k, (meas, dt) in enumerate(seq):
        where = f"step {k}"
        c = clears[k] if k < len(clears) else None
        if c is not None:
            battery, kinds = c
            assert new.clear_faults(battery, kinds) == old.clear_faults(battery, kinds), where
        out = new.step(meas, dt)
        assert_same_output(out, old.step(meas, dt), n, where)
        _note(out)
        _same_readouts(new, old, n, where)
        if new._m.bat.group_v.shape[2] > max(*info.groups_per_battery, 1):
            SEEN.add("grown")
        cmd = notes[k] if k < len(notes) else None
        if cmd is not None:
            new.note_commands(cmd)
            old.note_commands(cmd)


WANTED = (
    {f"Fault:{k}" for k in KINDS}
    | {f"FaultCleared:{k}" for k in ("nonfinite", "out_of_range", "stuck", "stale", "voltage_sum")}
    | {f"{e}:battery={b}" for e in ("Fault", "FaultCleared") for b in ("pack", "battery")}
    | {f"reaction:{r}" for r in REACTIONS}
    | {f"value:{t}" for t in ("float", "str", "bool", "int")}
    | {"manual:True", "manual:False", "isolated"}
)


@settings(max_examples=200, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 3),
    groups=st.integers(1, 4),
    cfg=st.sampled_from(CONFIGS),
)
def _same_on_drawn_sequences(data: Any, n: int, groups: int, cfg: PlausibilityConfig) -> None:
    info = _infos(n, data.draw)
    if data.draw(st.booleans()):  # the topology the measurements were drawn for
        info = PackInfo(
            n_batteries=n,
            groups_per_battery=(groups,) * n,
            cells_per_group=(1,) * n,
            switch_kind=info.switch_kind,
            capacity_ah=info.capacity_ah,
        )
    seq = data.draw(sequence(n, groups, current=(-20.0, 20.0)))
    notes = data.draw(st.lists(st.one_of(st.none(), COMMANDS), max_size=len(seq)))
    clears = data.draw(st.lists(CLEAR, max_size=len(seq)))
    _drive(info, cfg, seq, notes, clears)


def test_same_as_the_scalar_monitor() -> None:
    SEEN.clear()
    _same_on_drawn_sequences()
    # a guard against comparing two monitors that never do anything: every detector fired,
    # every reaction, every kind of value, manual and automatic clears, pack and battery
    assert not WANTED - SEEN, sorted(WANTED - SEEN)


# -- hostile inputs: any float anywhere, group tuples longer than the pack has groups -------

ANY = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 5e-324]),
    st.floats(-10.0, 10.0),
    st.floats(allow_nan=True, allow_infinity=True),
)


@st.composite
def hostile_battery(draw: Any, groups: int) -> BatteryMeasurement:
    sticky = draw(ANY)
    pick = st.one_of(st.just(sticky), ANY)
    return BatteryMeasurement(
        voltage_v=draw(pick),
        current_a=draw(pick),
        temp_c=draw(pick),
        min_cell_v=draw(pick),
        max_cell_v=draw(pick),
        soc=draw(pick),
        full_capacity_ah=draw(pick),
        remaining_capacity_ah=draw(pick),
        group_voltages_v=tuple(draw(st.lists(pick, max_size=groups + 3))),
        switch=SwitchState(draw(st.booleans()), draw(st.booleans())),
        min_temp_c=draw(pick),
        present=draw(st.sampled_from([True] * 5 + [False])),
        sample_age_s=draw(st.one_of(st.just(math.nan), ANY)),
    )


@st.composite
def hostile_sequence(draw: Any, n: int, groups: int) -> list[tuple[Measurements, float]]:
    out = []
    bats = [draw(hostile_battery(groups)) for _ in range(n + 1)]
    for _ in range(draw(st.integers(1, 25))):
        k = draw(st.integers(0, n + 1))
        if k <= n:
            bats[k] = draw(hostile_battery(groups))
        meas = Measurements(
            t_s=draw(ANY),
            batteries=tuple(bats[: draw(st.integers(0, n + 1))]),
            bus_v=draw(ANY),
            load_current_a=draw(ANY),
            docked=draw(st.booleans()),
        )
        out.append((meas, draw(st.one_of(st.sampled_from([0.1, 0.5, 1.0]), ANY))))
    return out


@settings(max_examples=200, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 3),
    groups=st.integers(0, 3),
    cfg=st.sampled_from(CONFIGS),
)
def _same_on_hostile_sequences(data: Any, n: int, groups: int, cfg: PlausibilityConfig) -> None:
    info = _infos(n, data.draw)
    seq = data.draw(hostile_sequence(n, groups))
    notes = data.draw(st.lists(st.one_of(st.none(), COMMANDS), max_size=len(seq)))
    clears = data.draw(st.lists(CLEAR, max_size=len(seq)))
    _drive(info, cfg, seq, notes, clears)


def test_same_on_hostile_inputs() -> None:
    SEEN.clear()
    _same_on_hostile_sequences()
    # group tuples longer than the arrays were built for; values shown as text and as floats
    assert {"grown", "value:str", "value:float", "value:int"} <= SEEN, sorted(SEEN)


# -- closed loops on the real plant ---------------------------------------------------------


class _Recording:
    """Wraps a run's controller: keeps each step's measurements, dt and final commands."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.log: list[tuple[Measurements, float, Commands]] = []

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        out: ControlOutput = self.inner.step(meas, dt_s)
        self.log.append((meas, dt_s, out.commands))
        return out


def _replay(runner: Runner, cfg: PlausibilityConfig) -> int:
    """Run ``runner`` recording, then feed its samples to both monitors (noting the final
    merged commands after each step, as the supervisor does); returns the events seen."""
    rec = _Recording(runner.controller)
    runner.controller = rec
    runner.run()
    info = runner.info
    n = info.n_batteries
    new, old = PlausibilityMonitor(cfg, info), Oracle(cfg, info)
    events = 0
    for k, (meas, dt, cmd) in enumerate(rec.log):
        a, b = new.step(meas, dt), old.step(meas, dt)
        assert_same_output(a, b, n, f"t = {meas.t_s}")
        events += len(a.events)
        new.note_commands(cmd)
        old.note_commands(cmd)
        if k % 500 == 0:
            _same_readouts(new, old, n, f"t = {meas.t_s}")
    _same_readouts(new, old, n, "end")
    return events


def test_closed_loop_uav_mission() -> None:
    cfg = load_config(EXAMPLES / "uav_mission.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 1500.0, "progress": False})}
    )
    runner = Runner(cfg, progress=False)
    _replay(runner, PlausibilityConfig())  # flight, landing, docking and the start of charging
    # the same samples with settings that do fire (stuck under load, tight sum, fast clears)
    runner = Runner(cfg, progress=False)
    assert _replay(runner, CONFIGS[3]) > 0


def _fault_scenarios() -> list[tuple[str, Callable[[], dict[str, Any]]]]:
    from tests.test_fault_injection import _dock, _flight

    def dropout_at_rest() -> dict[str, Any]:
        d = _flight({"kind": "sensor_dropout", "at_s": 5.0, "battery": "A"})
        d["load"] = {"kind": "none"}
        return d

    def shorted_chg() -> dict[str, Any]:
        d = _flight({"kind": "shorted_fet", "at_s": 5.0, "battery": "B", "fet": "chg"})
        d["pack"]["batteries"][1]["ocv0_v"] = 22.5
        return d

    return [
        ("sensor_nan", lambda: _flight({"kind": "sensor_nan", "at_s": 10.0, "battery": "B"})),
        ("sensor_stuck", lambda: _flight({"kind": "sensor_stuck", "at_s": 5.0, "battery": "A"})),
        (
            "sensor_dropout",
            lambda: _flight({"kind": "sensor_dropout", "at_s": 5.0, "battery": "A"}),
        ),
        ("dropout_at_rest", dropout_at_rest),
        ("shorted_chg_fet", shorted_chg),
        (
            "welded_relay_docked",
            lambda: _dock({"kind": "welded_relay", "at_s": 5.0, "battery": "A"}),
        ),
        (
            "charger_fault",
            lambda: _dock({"kind": "charger_fault", "at_s": 20.0, "flag": "hardware_failure"}),
        ),
        (
            "sensor_nan_docked",
            lambda: _dock({"kind": "sensor_nan", "at_s": 10.0, "battery": "A"}, 40.0),
        ),
    ]


@pytest.mark.parametrize(
    ("name", "make"), _fault_scenarios(), ids=[s[0] for s in _fault_scenarios()]
)
def test_closed_loop_fault_injection(name: str, make: Callable[[], dict[str, Any]]) -> None:
    d = make()
    runner = Runner(parse_config(d), progress=False)
    events = _replay(runner, PlausibilityConfig.model_validate(d["plausibility"]))
    if name.startswith(("sensor", "dropout", "shorted")):
        assert events > 0, "the injected fault was not seen"


@pytest.mark.parametrize("fault", ["welded_relay", "shorted_dsg_fet"])
def test_closed_loop_switch_faults_under_the_supervisor(fault: str) -> None:
    """tests/test_fault_injection.py's switch-fault runs: a method opens the faulty path."""
    from packpilot.control.supervisor import Supervisor, SupervisorConfig
    from tests.conftest import dual_pack
    from tests.test_fault_injection import _DsgOffAt, _OpenAt

    relay = fault == "welded_relay"
    d = dual_pack(
        switch={"kind": "relay" if relay else "mosfet_pair"},
        v_a=23.0,
        v_b=23.0,
        duration_s=10.0,
        load={"kind": "current", "value": 10.0},
    )
    d["faults"] = [
        {"kind": "welded_relay", "at_s": 1.0, "battery": "A"}
        if relay
        else {"kind": "shorted_fet", "at_s": 1.0, "battery": "B", "fet": "dsg"}
    ]
    d["plausibility"] = {}
    runner = Runner(parse_config(d), progress=False)
    runner.controller = Supervisor(
        SupervisorConfig(),
        runner.info,
        methods=[_OpenAt() if relay else _DsgOffAt()],
        safety=[PlausibilityMonitor(PlausibilityConfig(), runner.info)],
    )
    assert _replay(runner, PlausibilityConfig()) > 0


class _Spy:
    """Stands in for a monitor inside a hand-written supervisor: records what it is fed."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.log: list[tuple[Measurements, float]] = []
        self.notes: list[Commands] = []

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        self.log.append((meas, dt_s))
        out: ControlOutput = self.inner.step(meas, dt_s)
        return out

    def note_commands(self, commands: Commands) -> None:
        self.notes.append(commands)
        self.inner.note_commands(commands)


def test_closed_loop_scripted_switch_and_sensor_faults() -> None:
    """The closed loops of tests/test_plausibility_closed_loop.py (scripted commands, a welded
    relay, a shorted FET, a temperature sensor dying inside the supervisor), replayed from
    what the monitor was fed."""
    from tests.conftest import dual_pack
    from tests.test_plausibility_closed_loop import Supervisor

    def run(d: dict[str, Any], script: dict[float, Commands], **kw: Any) -> int:
        hooks = kw.pop("hooks", ())
        runner = Runner(parse_config(d), progress=False, hooks=hooks)
        sup = Supervisor(runner.info, script, **kw)
        spy = _Spy(sup.plaus)
        sup.plaus = spy  # type: ignore[assignment]
        runner.controller = sup
        runner.run()
        info = runner.info
        new, old = (
            PlausibilityMonitor(PlausibilityConfig(), info),
            Oracle(PlausibilityConfig(), info),
        )
        events = 0
        assert len(spy.notes) == len(spy.log)
        for (meas, dt), cmd in zip(spy.log, spy.notes, strict=True):
            a = new.step(meas, dt)
            assert_same_output(a, old.step(meas, dt), info.n_batteries, f"t = {meas.t_s}")
            events += len(a.events)
            new.note_commands(cmd)
            old.note_commands(cmd)
        _same_readouts(new, old, info.n_batteries, "end")
        return events

    d = dual_pack(switch={"kind": "relay", "on_ohm": 0.0}, v_a=23.0, v_b=23.0, duration_s=5.0)
    d["pack"]["batteries"][0]["switch"] = {"kind": "relay", "on_ohm": 0.0, "welded": True}
    d["load"] = {"kind": "current", "value": 10.0}
    script = {
        0.0: Commands((True, True), (True, True)),
        1.0: Commands((False, True), (False, True)),
    }
    assert run(d, script) > 0

    d = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0001}, v_a=23.0, v_b=23.0, duration_s=4.0
    )

    def short(runner: Runner, t: float) -> None:
        runner.pack.fet_shorted[0, 1, 0] = t >= 1.0

    assert run(d, {0.0: Commands((True, False), (True, True))}, hooks=[short]) > 0

    d = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 0.0001}, v_a=23.0, v_b=23.0, duration_s=6.0
    )
    d["load"] = {"kind": "current", "value": 10.0}
    assert run(d, {0.0: Commands((True, True), (True, True))}, corrupt=True) > 0
