"""Supervisor: modes, safety layers override methods, the relay join limit."""

from __future__ import annotations

from packpilot.config import parse_config
from packpilot.contract.bms import (
    CLOSED,
    OPEN,
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Measurements,
    SwitchKind,
)
from packpilot.contract.topology import PackInfo
from packpilot.control.supervisor import Mode, Supervisor, SupervisorConfig
from packpilot.sim.runner import Runner
from tests.conftest import dual_pack


def _info(n: int, kind: SwitchKind = SwitchKind.RELAY) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(1,) * n,
        cells_per_group=(6,) * n,
        switch_kind=(kind,) * n,
        capacity_ah=(5.0,) * n,
    )


def _bat(v: float, i: float = 0.0, closed: bool = False) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=v,
        current_a=i,
        temp_c=25.0,
        min_cell_v=v / 6,
        max_cell_v=v / 6,
        soc=0.5,
        full_capacity_ah=5.0,
        remaining_capacity_ah=2.5,
        group_voltages_v=(v,),
        switch=CLOSED if closed else OPEN,
    )


class _CloseAll:
    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        n = len(meas.batteries)
        return ControlOutput(Commands(chg_on=(True,) * n, dsg_on=(True,) * n))


class _Veto:
    """A safety layer that opens battery 0's discharge path."""

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        return ControlOutput(Commands(dsg_on=(False, None, None)))


def test_relay_close_between_batteries_far_apart_is_refused_and_logged() -> None:
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(3), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(96.0), _bat(97.0), _bat(106.0)), bus_v=0.0)
    out = sup.step(meas, 0.1)
    assert out.commands.chg_on == (True, True, False)
    assert out.commands.dsg_on == (True, True, False)
    refused = [e for e in out.events if e.kind == "CommandRefused"]
    assert [e.battery for e in refused] == [2]
    assert refused[0].data["spread_v"] > 3.0
    # Logged once per refusal episode, not every period.
    out2 = sup.step(meas, 0.1)
    assert not [e for e in out2.events if e.kind == "CommandRefused"]


def test_join_limit_compares_with_the_batteries_already_on_the_bus() -> None:
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(100.0, closed=True), _bat(102.5)), bus_v=100.0)
    out = sup.step(meas, 0.1)
    assert out.commands.chg_on == (True, True)  # 2.5 V <= 3 V: allowed
    meas = Measurements(t_s=0.0, batteries=(_bat(100.0, closed=True), _bat(104.0)), bus_v=100.0)
    out = Supervisor(SupervisorConfig(), _info(2), methods=[_CloseAll()]).step(meas, 0.1)
    assert out.commands.chg_on == (True, False)


def test_safety_layer_overrides_the_method() -> None:
    sup = Supervisor(
        SupervisorConfig(),
        _info(3, SwitchKind.MOSFET_PAIR),
        methods=[_CloseAll()],
        safety=[_Veto()],
    )
    meas = Measurements(t_s=0.0, batteries=(_bat(24.0),) * 3, bus_v=24.0)
    out = sup.step(meas, 0.1)
    assert out.commands.dsg_on[0] is False
    assert out.commands.chg_on[0] is True


def test_modes_follow_the_pack_in_closed_loop() -> None:
    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=24.0,
        v_b=24.0,
        duration_s=40.0,
        load={"kind": "current", "value": 20.0, "start_s": 5.0},
    )
    d["charger"] = {"present": True, "connect_s": 30.0, "rated_v": 60.0, "rated_a": 10.0}
    d["controller"] = ["sequencing"]
    d["supervisor"] = {"idle_after_s": 2.0}
    d["load"]["profile"] = None
    res = Runner(parse_config(d)).run()
    path = [(e.data["from"], e.data["to"]) for e in res.events if e.kind == "ModeChanged"]
    assert path[0] == ("init", "idle")
    assert ("idle", "discharge") in path
    assert path[-1][1] == "charge"  # docked at 30 s
    mode = res.trace.status["mode"]
    assert mode[-1][0] == Mode.CHARGE


def test_every_trip_undocked_means_shutdown_with_all_paths_open() -> None:
    from packpilot.contract.bms import Event

    class _TripAll:
        def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
            ev = tuple(Event(meas.t_s, "ProtectionTripped", i) for i in range(2))
            return ControlOutput(Commands(), events=ev if meas.t_s < 0.15 else ())

    sup = Supervisor(
        SupervisorConfig(init_time_s=0.0), _info(2, SwitchKind.MOSFET_PAIR), methods=[_TripAll()]
    )
    meas = Measurements(t_s=0.1, batteries=(_bat(22.0), _bat(22.0)), bus_v=22.0)
    out = sup.step(meas, 0.1)
    assert sup.mode is Mode.SHUTDOWN
    assert out.commands.chg_on == (False, False) and out.commands.dsg_on == (False, False)


def test_join_limit_admits_a_difference_of_exactly_the_limit() -> None:
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(100.0, closed=True), _bat(103.0)), bus_v=100.0)
    assert sup.step(meas, 0.1).commands.chg_on == (True, True)  # 3.0 V == limit: allowed
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(100.0, closed=True), _bat(103.5)), bus_v=100.0)
    assert sup.step(meas, 0.1).commands.chg_on == (True, False)


def test_discharge_becomes_idle_after_exactly_idle_after_s_of_quiet() -> None:
    cfg = SupervisorConfig(init_time_s=0.0, idle_after_s=1.0)
    sup = Supervisor(cfg, _info(1, SwitchKind.MOSFET_PAIR))
    t = 0.0
    for _ in range(3):  # 10 A: discharging
        sup.step(Measurements(t_s=t, batteries=(_bat(24.0, i=10.0),), bus_v=24.0), 0.5)
        t += 0.5
    assert sup.mode is Mode.DISCHARGE
    modes = []
    for _ in range(4):  # quiet: 0.5 s, 1.0 s (== idle_after_s), ...
        sup.step(Measurements(t_s=t, batteries=(_bat(24.0, i=0.0),), bus_v=24.0), 0.5)
        modes.append(sup.mode)
        t += 0.5
    assert modes == [Mode.DISCHARGE, Mode.IDLE, Mode.IDLE, Mode.IDLE]


def test_an_empty_bus_seeds_the_largest_group_within_the_limit() -> None:
    """Nothing closed yet: the largest set of candidates within join_limit_v closes (100 and
    101 V), not the lowest battery alone (90 V)."""
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(3), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(90.0), _bat(100.0), _bat(101.0)), bus_v=0.0)
    out = sup.step(meas, 0.1)
    assert out.commands.chg_on == (False, True, True)
    assert [e.battery for e in out.events if e.kind == "CommandRefused"] == [0]


def test_a_reset_after_every_trip_ends_the_shutdown() -> None:
    """A ProtectionReset un-trips its battery: not every battery is tripped any more, so the
    supervisor leaves SHUTDOWN and stops forcing the paths open."""
    from packpilot.contract.bms import Event

    class _TripThenReset:
        def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
            if meas.t_s < 0.15:
                ev = tuple(Event(meas.t_s, "ProtectionTripped", i) for i in range(2))
            elif meas.t_s < 0.25:
                ev = (Event(meas.t_s, "ProtectionReset", 0),)
            else:
                ev = ()
            return ControlOutput(Commands(), events=ev)

    sup = Supervisor(
        SupervisorConfig(init_time_s=0.0),
        _info(2, SwitchKind.MOSFET_PAIR),
        methods=[_TripThenReset()],
    )
    bats = (_bat(22.0), _bat(22.0))
    sup.step(Measurements(t_s=0.1, batteries=bats, bus_v=22.0), 0.1)
    assert sup.mode is Mode.SHUTDOWN
    out = sup.step(Measurements(t_s=0.2, batteries=bats, bus_v=22.0), 0.1)
    assert sup.mode is not Mode.SHUTDOWN
    assert out.commands.dsg_on == (None, None)


def test_a_battery_of_unknown_voltage_never_joins() -> None:
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[_CloseAll()])
    meas = Measurements(
        t_s=0.0, batteries=(_bat(100.0, closed=True), _bat(float("nan"))), bus_v=100.0
    )
    out = sup.step(meas, 0.1)
    assert out.commands.chg_on == (True, False) and out.commands.dsg_on == (True, False)


class _ChargerOn:
    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        from packpilot.contract.charger import ChargerCommand

        return ControlOutput(Commands(charger=ChargerCommand(25.2, 5.0, enable=True)))


def test_the_charger_runs_only_in_charge_mode() -> None:
    from packpilot.contract.charger import CHARGER_OFF

    cfg = SupervisorConfig(init_time_s=0.0)
    sup = Supervisor(cfg, _info(1, SwitchKind.MOSFET_PAIR), methods=[_ChargerOn()])
    flying = Measurements(t_s=0.0, batteries=(_bat(24.0),), bus_v=24.0)
    out = sup.step(flying, 0.1)
    assert sup.mode is Mode.IDLE and out.commands.charger == CHARGER_OFF
    out = sup.step(Measurements(t_s=0.1, batteries=(_bat(24.0),), bus_v=24.0, docked=True), 0.1)
    assert sup.mode is Mode.CHARGE and out.commands.charger is not None
    assert out.commands.charger.enable


def test_a_fault_holds_fault_mode_for_fault_hold_s() -> None:
    from packpilot.contract.bms import Event

    class _FaultOnce:
        def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
            ev = (Event(meas.t_s, "Fault", 0),) if meas.t_s == 0.0 else ()
            return ControlOutput(Commands(), events=ev)

    cfg = SupervisorConfig(init_time_s=0.0, fault_hold_s=1.0)
    sup = Supervisor(cfg, _info(1, SwitchKind.MOSFET_PAIR), methods=[_FaultOnce()])
    modes = []
    for k in range(15):
        sup.step(Measurements(t_s=k * 0.1, batteries=(_bat(24.0),), bus_v=24.0), 0.1)
        modes.append(sup.mode)
    assert modes[:10] == [Mode.FAULT] * 10 and modes[-1] is Mode.IDLE


def test_init_lasts_init_time_s() -> None:
    sup = Supervisor(SupervisorConfig(init_time_s=1.0), _info(1, SwitchKind.MOSFET_PAIR))
    modes = []
    for k in range(15):
        sup.step(Measurements(t_s=k * 0.1, batteries=(_bat(24.0),), bus_v=24.0), 0.1)
        modes.append(sup.mode)
    assert modes[:9] == [Mode.INIT] * 9 and modes[-1] is Mode.IDLE


def test_an_empty_bus_seeds_by_voltage_whatever_the_battery_order() -> None:
    """The seed group is chosen over the candidates sorted by voltage, not in battery order:
    90 and 91.5 V (the lowest of two equal groups) close, 100 and 101 V wait (generated mutants
    6cd4f03bc4, 9927d7a5ba, 33049ab188: the insertion sort broken); each refusal names the
    limit and its widest distance to the group."""
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(4), methods=[_CloseAll()])
    bats = (_bat(101.0), _bat(90.0), _bat(100.0), _bat(91.5))
    out = sup.step(Measurements(t_s=0.0, batteries=bats, bus_v=0.0), 0.1)
    assert out.commands.chg_on == (False, True, False, True)
    refused = [e for e in out.events if e.kind == "CommandRefused"]
    assert sorted(e.battery for e in refused) == [0, 2]
    assert all(e.data["join_limit_v"] == 3.0 for e in refused)  # (mutant c337ef2cd4)
    # the widest distance to the group on the bus (mutant d503ce3d6b: vi + first)
    assert {e.battery: e.data["spread_v"] for e in refused} == {0: 11.0, 2: 10.0}


def test_each_admitted_battery_widens_the_span_the_next_must_fit() -> None:
    """On a bus at 100 V, 102 V joins (2 V); 98 V would be within 3 V of 100 alone but 4 V from
    102, which is now on the bus too: refused (generated mutant af0c930021)."""
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(3), methods=[_CloseAll()])
    bats = (_bat(100.0, closed=True), _bat(102.0), _bat(98.0))
    out = sup.step(Measurements(t_s=0.0, batteries=bats, bus_v=100.0), 0.1)
    assert out.commands.chg_on == (True, True, False)
    assert [e.battery for e in out.events if e.kind == "CommandRefused"] == [2]


def test_a_new_attempt_after_the_method_gave_up_is_logged_again() -> None:
    """A refusal is logged once per episode; the episode ends when nothing asks to close, so
    the next attempt is logged again (generated mutant 2cb2737e46)."""

    class _Toggle:
        close = True

        def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
            n = len(meas.batteries)
            on = (True,) * n if self.close else (False,) * n
            return ControlOutput(Commands(chg_on=on, dsg_on=on))

    method = _Toggle()
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[method])

    def refused(t: float) -> list[int | None]:
        bats = (_bat(100.0, closed=True), _bat(110.0))
        out = sup.step(Measurements(t_s=t, batteries=bats, bus_v=100.0), 0.1)
        return [e.battery for e in out.events if e.kind == "CommandRefused"]

    assert refused(0.0) == [1]
    assert refused(0.1) == []  # the same episode
    method.close = False
    assert refused(0.2) == []
    method.close = True
    assert refused(0.3) == [1]  # a new episode


def test_a_battery_refused_after_it_was_accepted_is_logged() -> None:
    """Acceptance ends a refusal episode: a battery that was admitted and then drifts out of
    the join limit is refused *and logged*, and so again after it was admitted in between
    (generated mutant 5e0683ef7a: an admitted battery was marked as already refused)."""

    class _Close:
        def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
            on = (True,) * len(meas.batteries)
            return ControlOutput(Commands(chg_on=on, dsg_on=on))

    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(2), methods=[_Close()])

    def refused(t: float, v1: float) -> list[int | None]:
        bats = (_bat(100.0, closed=True), _bat(v1))
        out = sup.step(Measurements(t_s=t, batteries=bats, bus_v=100.0), 0.1)
        return [e.battery for e in out.events if e.kind == "CommandRefused"]

    assert refused(0.0, 101.0) == []  # within 3 V: admitted
    assert refused(0.1, 110.0) == [1]
    assert refused(0.2, 110.0) == []  # the same episode
    assert refused(0.3, 101.0) == []
    assert refused(0.4, 110.0) == [1]  # admitted in between: a new episode


def test_init_ends_exactly_at_init_time_s() -> None:
    """INIT lasts init_time_s, not a tick more: with 0.25 s ticks (exact in binary) and 1 s of
    INIT the fourth tick, whose end is 1.0 s in the mode, is already IDLE (generated mutant
    7954b947f3: ``<`` -> ``<=`` held INIT one tick longer)."""
    sup = Supervisor(SupervisorConfig(init_time_s=1.0), _info(1, SwitchKind.MOSFET_PAIR))
    modes = []
    for k in range(5):
        sup.step(Measurements(t_s=k * 0.25, batteries=(_bat(24.0),), bus_v=24.0), 0.25)
        modes.append(sup.mode)
    assert modes == [Mode.INIT] * 3 + [Mode.IDLE] * 2


def test_a_compiled_layers_trip_event_shuts_the_pack_down() -> None:
    """The supervisor classes the events of compiled layers by their kind (the core's
    (source, code) table), not only those of Python layers: the protection layer's own
    ProtectionTripped, for the only battery undocked, means SHUTDOWN with both paths open
    (generated mutant 91fed9ca12: every compiled layer's event classed as nothing)."""
    from packpilot.control.protection import ProtectionConfig, ProtectionController

    info = _info(1, SwitchKind.MOSFET_PAIR)
    prot = ProtectionController(ProtectionConfig(), info)
    sup = Supervisor(SupervisorConfig(init_time_s=0.0), info, safety=[prot])
    low = BatteryMeasurement(voltage_v=6 * 3.1, current_a=10.0, temp_c=25.0, min_cell_v=3.1,
                             max_cell_v=3.1, soc=0.1, full_capacity_ah=5.0,
                             remaining_capacity_ah=0.5)  # fmt: skip
    for k in range(7):  # P3 (10 A, 25 degC, 3.1 V): trips at 5 s
        out = sup.step(Measurements(t_s=float(k), batteries=(low,), bus_v=18.6), 1.0)
    assert sup.mode is Mode.SHUTDOWN
    assert out.commands.chg_on == (False,) and out.commands.dsg_on == (False,)


def test_a_mosfet_pack_has_no_join_limit() -> None:
    """The join limit is a relay rule (closing a relay joins two voltages at once); MOSFET
    pairs join through their diodes: batteries 10 V apart all close (generated mutant
    0332cb7a04: a MOSFET battery with its discharge path on counted as a closing relay)."""
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(3, SwitchKind.MOSFET_PAIR),
                     methods=[_CloseAll()])  # fmt: skip
    meas = Measurements(t_s=0.0, batteries=(_bat(96.0), _bat(97.0), _bat(106.0)), bus_v=0.0)
    out = sup.step(meas, 0.1)
    assert out.commands.chg_on == (True, True, True)
    assert out.commands.dsg_on == (True, True, True)
    assert not [e for e in out.events if e.kind == "CommandRefused"]


def test_a_refusal_names_the_refused_batterys_voltage() -> None:
    """The CommandRefused event carries the refused battery's own voltage beside the spread
    and the limit (generated mutant 3c36832f9e: the voltage never written)."""
    sup = Supervisor(SupervisorConfig(join_limit_v=3.0), _info(3), methods=[_CloseAll()])
    meas = Measurements(t_s=0.0, batteries=(_bat(96.0), _bat(97.0), _bat(106.0)), bus_v=0.0)
    out = sup.step(meas, 0.1)
    (ev,) = [e for e in out.events if e.kind == "CommandRefused"]
    assert ev.battery == 2 and ev.data["voltage_v"] == 106.0
    assert ev.data["join_limit_v"] == 3.0
