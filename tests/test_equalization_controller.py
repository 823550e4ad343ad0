"""EqualizationController: commands, balancing time, ledger, gating, faults, status."""

from __future__ import annotations

import dataclasses
import math

import pytest

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.equalization import EqualizationConfig, EqualizationController


def pack(groups: tuple[int, ...] = (4,), balancers: bool = True) -> PackInfo:
    n = len(groups)
    return PackInfo(
        n_batteries=n,
        groups_per_battery=groups,
        cells_per_group=(6,) * n,
        switch_kind=(SwitchKind.RELAY,) * n,
        has_balancers=balancers,
    )


def batt(gv: tuple[float, ...], current_a: float, present: bool = True) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=sum(gv),
        current_a=current_a,
        temp_c=25.0,
        min_cell_v=min(gv) / 6,
        max_cell_v=max(gv) / 6,
        soc=0.5,
        full_capacity_ah=100.0,
        remaining_capacity_ah=50.0,
        group_voltages_v=gv,
        present=present,
    )


def meas(t: float, *bats: BatteryMeasurement) -> Measurements:
    return Measurements(t_s=t, batteries=bats, bus_v=bats[0].voltage_v)


LOW0 = (12.97, 13.0, 13.0, 13.0)  # group 0 lags by 22.5 mV


def test_first_update_grants_time_and_current() -> None:
    cfg = EqualizationConfig(equalizer_max_a=5.0)
    ctrl = EqualizationController(cfg, pack())
    outs = [ctrl.step(meas(float(k), batt(LOW0, 10.0)), 1.0) for k in range(121)]
    # t = 0..118: nothing; t = 119 the 120th sample fires formula 1.
    assert all(o.commands.balancer_a == ((0.0,) * 4,) for o in outs[:119])
    upd = [e for e in outs[119].events if e.kind == "BalancingUpdated"]
    assert len(upd) == 1
    assert upd[0].data == {
        "group": 0,
        "formula": "formula1",
        "old": 0.0,
        "new": 0.25,
        "dv_v": pytest.approx(0.0225),
    }
    assert outs[119].commands.balancer_a == ((5.0, 0.0, 0.0, 0.0),)
    # 3600·0.25/5 = 180 s granted, 1 s already used.
    assert list(outs[119].status["eq_time_s_g0"]) == [pytest.approx(179.0)]
    assert list(outs[119].status["eq_owed_ah_g0"]) == [pytest.approx(0.25 - 5.0 / 3600)]
    assert outs[119].status["eq_ah_g0"] == [0.25]
    assert list(outs[119].status["eq_dv_mv_g0"]) == [pytest.approx(22.5)]


def test_balancing_delivers_exactly_ah_when_undisturbed() -> None:
    # dv_set = 0.5 V makes group 0 sit exactly at ΔV = dv_set after the lag: no further updates,
    # so the granted time runs out and the ledger must show exactly AH = 0.25 Ah.
    cfg = EqualizationConfig(dv_set_v=0.5, equalizer_max_a=3.0, min_current_a=0.5)
    ctrl = EqualizationController(cfg, pack((2,)))
    for k in range(120):
        ctrl.step(meas(float(k), batt((11.0, 13.0), -2.5)), 1.0)  # ΔV0 = +1 V, charging
    st = ctrl.strings[0]
    assert st.ah == [0.25, 0.0]
    assert st.remaining_s[0] == pytest.approx(3600 * 0.25 / 2.5 - 1.0)
    total = 0.0
    for k in range(120, 2000):
        out = ctrl.step(meas(float(k), batt((12.0, 13.0), -2.5)), 1.0)
        assert out.commands.balancer_a is not None
        total += out.commands.balancer_a[0][0] / 3600.0
    assert st.ah == [0.25, 0.0]
    assert st.ledger_gross_ah[0] == pytest.approx(0.25)
    assert st.ledger_granted_ah[0] == 0.25
    assert st.owed_ah[0] == 0.0
    assert st.ledger_time_s[0] == pytest.approx(360.0)
    assert total + 2.5 / 3600 == pytest.approx(0.25)  # plus the first second at t = 119


def test_partial_last_step_is_prorated() -> None:
    cfg = EqualizationConfig(dv_set_v=0.5, time_mode="fixed_current", fixed_current_a=1.0)
    ctrl = EqualizationController(cfg, pack((2,)))
    ctrl.strings[0].ah = [0.001, 0.0]  # 3.6 s at 1 A
    ctrl.strings[0].owed_ah = [0.001, 0.0]
    cur = [
        ctrl.step(meas(k * 1.0, batt((12.0, 13.0), 5.0)), 1.0).commands.balancer_a[0][0]  # type: ignore[index]
        for k in range(5)
    ]
    assert cur == pytest.approx([1.0, 1.0, 1.0, 0.6, 0.0])
    assert ctrl.strings[0].ledger_gross_ah[0] == pytest.approx(0.001)


def test_gate_holds_remaining_time_below_min_current() -> None:
    cfg = EqualizationConfig(dv_set_v=0.5, min_current_a=1.0)
    ctrl = EqualizationController(cfg, pack((2,)))
    ctrl.strings[0].owed_ah = [1.5 * 100.0 / 3600.0, 0.0]  # 100 s at 1.5 A
    out = ctrl.step(meas(0.0, batt((12.0, 13.0), 0.5)), 1.0)
    assert out.commands.balancer_a == ((0.0, 0.0),)
    assert ctrl.strings[0].owed_ah[0] == 1.5 * 100.0 / 3600.0  # held, not lost
    # Quoted at the equalizer's rating while the gate is closed: 0.0417 Ah at 2 A.
    assert ctrl.strings[0].remaining_s[0] == pytest.approx(75.0)
    out = ctrl.step(meas(1.0, batt((12.0, 13.0), 1.5)), 1.0)
    assert out.commands.balancer_a == ((1.5, 0.0),)
    assert ctrl.strings[0].remaining_s[0] == pytest.approx(99.0)
    with pytest.raises(AttributeError):
        ctrl.strings[0].remaining_s = [1.0, 0.0]  # derived from owed_ah


def test_fixed_current_balance_at_rest() -> None:
    cfg = EqualizationConfig(
        dv_set_v=0.5,
        time_mode="fixed_current",
        fixed_current_a=0.8,
        balance_at_rest=True,
    )
    ctrl = EqualizationController(cfg, pack((2,)))
    ctrl.strings[0].owed_ah = [0.01, 0.0]
    out = ctrl.step(meas(0.0, batt((12.0, 13.0), 0.0)), 1.0)
    assert out.commands.balancer_a == ((0.8, 0.0),)


def test_nan_group_voltage_stops_string_and_faults_once() -> None:
    cfg = EqualizationConfig(equalizer_max_a=5.0)
    ctrl = EqualizationController(cfg, pack((4, 4)))
    for k in range(130):
        ctrl.step(meas(float(k), batt(LOW0, 10.0), batt(LOW0, 10.0)), 1.0)
    assert ctrl.strings[0].owed_ah[0] > 0
    bad = batt((math.nan, 13.0, 13.0, 13.0), 10.0)
    out = ctrl.step(meas(130.0, bad, batt(LOW0, 10.0)), 1.0)
    assert out.commands.balancer_a is not None
    assert out.commands.balancer_a[0] == (0.0, 0.0, 0.0, 0.0)
    assert out.commands.balancer_a[1][0] == 5.0  # the other string keeps balancing
    faults = [e for e in out.events if e.kind == "Fault"]
    assert len(faults) == 1 and faults[0].battery == 0
    assert out.status["eq_fault"] == [True, False]
    out = ctrl.step(meas(131.0, bad, batt(LOW0, 10.0)), 1.0)
    assert not [e for e in out.events if e.kind == "Fault"]
    assert ctrl.strings[0].ah[0] == 0.25  # learned AH kept
    owed = ctrl.strings[0].owed_ah[0]
    assert owed == pytest.approx(0.25 - 11 * 5.0 / 3600)  # owed Ah kept, not delivered
    assert ctrl.strings[0].hi_timer_s == [0.0] * 4
    out = ctrl.step(meas(132.0, batt(LOW0, 10.0), batt(LOW0, 10.0)), 1.0)
    assert [e.kind for e in out.events] == ["FaultCleared"]
    assert out.commands.balancer_a is not None and out.commands.balancer_a[0][0] == 5.0
    assert ctrl.strings[0].owed_ah[0] == pytest.approx(owed - 5.0 / 3600)
    assert out.status["eq_fault"] == [False, False]


@pytest.mark.parametrize(
    "bad",
    [
        batt((13.0, 13.0, 13.0), 1.0),  # wrong group count
        batt((13.0, 13.0, -1.0, 13.0), 1.0),  # negative voltage
        batt((13.0, 13.0, 13.0, 13.0), math.inf),  # current
    ],
)
def test_other_invalid_inputs_fault(bad: BatteryMeasurement) -> None:
    ctrl = EqualizationController(EqualizationConfig(), pack())
    out = ctrl.step(meas(0.0, bad), 1.0)
    assert out.commands.balancer_a == ((0.0,) * 4,)
    assert [e.kind for e in out.events] == ["Fault"]


def test_nan_temperature_does_not_stop_equalization() -> None:
    b = batt(LOW0, 10.0)
    b = dataclasses.replace(b, temp_c=math.nan)
    ctrl = EqualizationController(EqualizationConfig(), pack())
    out = ctrl.step(meas(0.0, b), 1.0)
    assert out.events == ()
    assert out.status["eq_fault"] == [False]


def test_absent_battery_idles_silently() -> None:
    ctrl = EqualizationController(EqualizationConfig(), pack())
    out = ctrl.step(meas(0.0, batt(LOW0, 10.0, present=False)), 1.0)
    assert out.events == ()
    assert out.commands.balancer_a == ((0.0,) * 4,)


def test_bidirectional_drives_the_minority() -> None:
    cfg = EqualizationConfig(dv_set_v=0.5, equalizer="bidirectional")
    ctrl = EqualizationController(cfg, pack())
    st = ctrl.strings[0]
    # Groups owed Ah lag the average a little (within dv_set: no update in one step); only a
    # group below the average is charged (issue #24).
    gv = (12.9, 13.0, 13.0, 13.1)
    st.owed_ah = [0.1, 0.0, 0.0, 0.0]  # one group to charge: unidirectional behaviour
    out = ctrl.step(meas(0.0, batt(gv, 1.5)), 1.0)
    assert out.commands.balancer_a == ((1.5, 0.0, 0.0, 0.0),)
    gv = (12.9, 12.9, 12.9, 13.3)
    st.owed_ah = [0.1, 0.1, 0.1, 0.0]  # three to charge: discharge the leader instead
    out = ctrl.step(meas(1.0, batt(gv, 1.5)), 1.0)
    assert out.commands.balancer_a == ((0.0, 0.0, 0.0, -1.5),)
    # Relative charge per group is the same as with a unidirectional equalizer.
    gross = st.ledger_gross_ah
    net = st.ledger_net_ah
    assert [g - gross[3] for g in gross] == pytest.approx([n - net[3] for n in net])


def test_sample_period_accumulates_short_steps() -> None:
    cfg = EqualizationConfig(sample_period_s=2.0)
    ctrl = EqualizationController(cfg, pack())
    ctrl.step(meas(0.0, batt(LOW0, 10.0)), 0.5)
    assert ctrl.strings[0].hi_timer_s[0] == 0.0
    for k in range(1, 4):
        ctrl.step(meas(0.5 * k, batt(LOW0, 10.0)), 0.5)
    assert ctrl.strings[0].hi_timer_s[0] == pytest.approx(2.0)


def test_no_balancers_means_no_opinion_but_status() -> None:
    ctrl = EqualizationController(EqualizationConfig(), pack(balancers=False))
    out = ctrl.step(meas(0.0, batt(LOW0, 10.0)), 1.0)
    assert out.commands.balancer_a is None
    assert "eq_ah_g3" in out.status


def test_mixed_group_counts_status_padding() -> None:
    ctrl = EqualizationController(EqualizationConfig(), pack((2, 3)))
    out = ctrl.step(meas(0.0, batt((13.0, 13.0), 1.0), batt((13.0, 13.0, 13.0), 1.0)), 1.0)
    assert out.status["eq_ah_g2"] == [None, 0.0]
    assert out.commands.balancer_a == ((0.0, 0.0), (0.0, 0.0, 0.0))


def test_deterministic() -> None:
    def run() -> list[tuple[object, object]]:
        ctrl = EqualizationController(EqualizationConfig(), pack())
        seq: list[tuple[object, object]] = []
        for k in range(400):
            v = (12.97 + 0.0001 * (k % 7), 13.0, 13.01, 13.0)
            out = ctrl.step(meas(float(k), batt(v, 5.0 - k * 0.02)), 1.0)
            seq.append((out.commands, out.events))
        return seq

    assert run() == run()


def test_saturated_ah_still_regrants_time() -> None:
    # At AH = N formula 1 leaves AH unchanged; the lagging group must still be balanced.
    cfg = EqualizationConfig(equalizer_max_a=5.0)
    ctrl = EqualizationController(cfg, pack())
    ctrl.strings[0].ah = [0.5, 0.0, 0.0, 0.0]
    outs = [ctrl.step(meas(float(k), batt(LOW0, 10.0)), 1.0) for k in range(125)]
    assert outs[118].commands.balancer_a == ((0.0,) * 4,)
    assert [e.kind for e in outs[119].events] == []  # no change, no event
    assert outs[119].commands.balancer_a == ((5.0, 0.0, 0.0, 0.0),)
    assert ctrl.strings[0].counts["formula1"] == 1
    # Owed raised from 0 to AH = 0.5 Ah: 360 s at 5 A, 6 s already delivered.
    assert ctrl.strings[0].remaining_s[0] == pytest.approx(360.0 - 6.0)


def test_passive_top_balancer_bleeds_high_groups_while_charging() -> None:
    from benchmarks.baselines import PassiveTopBalancer, PassiveTopBalancerConfig

    cfg = PassiveTopBalancerConfig(threshold_cell_v=3.40, delta_cell_v=0.005, bleed_ohm=10.0)
    info = PackInfo(1, (4,), (4,), (SwitchKind.RELAY,), has_balancers=True)
    bal = PassiveTopBalancer(cfg, info)
    gv = (13.70, 13.55, 13.62, 13.40)  # threshold 13.6 V, floor 13.40 + 0.02
    out = bal.step(meas(0.0, batt(gv, -20.0)), 2.0)
    assert out.commands.balancer_a is not None
    assert out.commands.balancer_a[0] == pytest.approx((-1.37, 0.0, -1.362, 0.0))
    assert bal.bled_ah[0][0] == pytest.approx(1.37 * 2.0 / 3600.0)
    assert out.status["passive_bleeding"] == [2]
    # Discharging: no bleeding (top balancing only).
    assert bal.step(meas(2.0, batt(gv, 20.0)), 2.0).commands.balancer_a == ((0.0,) * 4,)
    # A NaN voltage stops it with one Fault.
    bad = batt((math.nan, 13.55, 13.62, 13.40), -20.0)
    out = bal.step(meas(4.0, bad), 2.0)
    assert out.commands.balancer_a == ((0.0,) * 4,)
    assert [e.kind for e in out.events] == ["Fault"]


def test_a_fault_names_the_group_and_the_voltage_that_stopped_it() -> None:
    """The Fault event names the offending group and its voltage: group 2 at -1 V, not group
    0 (generated mutant da180cd102: the group index never written into the record)."""
    ctrl = EqualizationController(EqualizationConfig(), pack())
    out = ctrl.step(meas(0.0, batt((13.0, 13.0, -1.0, 13.0), 1.0)), 1.0)
    (ev,) = [e for e in out.events if e.kind == "Fault"]
    assert ev.battery == 0
    assert "group 2 voltage -1.0 is not a positive finite number" in ev.message


def test_a_one_group_string_is_sampled_and_shows_its_dv() -> None:
    """A battery of one group is sampled like any other: its only group is the average, so
    its ΔV is 0 mV and nothing is owed (generated mutant 70f2cf5fef: ``n > 0`` -> ``n > 1``
    never sampled it, its ΔV stayed unknown)."""
    ctrl = EqualizationController(EqualizationConfig(), pack((1,)))
    for k in range(5):
        out = ctrl.step(meas(float(k), batt((13.0,), 1.0)), 1.0)
    assert out.status["eq_dv_mv_g0"] == [0.0]
    assert out.status["eq_owed_ah_g0"] == [0.0]


def test_an_update_after_a_cleared_fault_is_reported_as_an_update() -> None:
    """A step's event records reuse the rows of earlier steps: the update must write its own
    code, not inherit the row's last one (generated mutant 53c2d1039f dropped that write; it
    survived because BalancingUpdated is code 0, the arrays' initial value, and no test had
    a fault record in the row first). A NaN current records a fault at t = 0, the next valid
    sample clears it (a second record in row 0), and formula 1 fires 120 samples later."""
    cfg = EqualizationConfig(equalizer_max_a=5.0)
    ctrl = EqualizationController(cfg, pack())
    outs = [ctrl.step(meas(0.0, batt(LOW0, math.nan)), 1.0)]
    outs += [ctrl.step(meas(float(k), batt(LOW0, 10.0)), 1.0) for k in range(1, 140)]
    kinds = [e.kind for o in outs for e in o.events]
    assert kinds.count("BalancingUpdated") == 1, kinds
    upd = next(e for o in outs for e in o.events if e.kind == "BalancingUpdated")
    assert upd.data["formula"] == "formula1" and upd.data["new"] == 0.25
    assert len(kinds) == 3, kinds  # the fault, its clearing, the update
