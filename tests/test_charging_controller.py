"""ChargingController: the spec's worked examples (§6) and the safety/fail-safe behaviour."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pytest

from packpilot.contract.bms import BatteryMeasurement, ControlOutput, Event, Measurements
from packpilot.contract.charger import CHARGER_OFF, ChargerCommand, ChargerStatus
from packpilot.control.charging import ChargingConfig, ChargingController, Stage, rules
from tests.test_charging_helpers import ToyPack, pack_info


@dataclass
class Run:
    outputs: list[ControlOutput] = field(default_factory=list)
    events: list[Event] = field(default_factory=list)

    def stages(self) -> list[Mapping[str, object]]:
        return [e.data for e in self.events if e.kind == "StageChanged"]

    def kinds(self, kind: str) -> list[Event]:
        return [e for e in self.events if e.kind == kind]


def drive(
    toy: ToyPack,
    ctrl: ChargingController,
    seconds: float,
    dt_s: float = 1.0,
    run: Run | None = None,
) -> Run:
    run = run or Run()
    for _ in range(round(seconds / dt_s)):
        out = ctrl.step(toy.measure(), dt_s)
        toy.apply(out)
        run.outputs.append(out)
        run.events.extend(out.events)
        if out.commands.charger is not None and out.commands.charger.enable:
            assert out.commands.charger.voltage_v <= ctrl.volts.v_sat
            assert out.commands.charger.current_a <= ctrl.config.charger_current_limit_a
        toy.step(dt_s)
        if ctrl.stage is Stage.COMPLETE and run.kinds("ChargeComplete"):
            break
    return run


def controller(n: int, **cfg: object) -> ChargingController:
    return ChargingController(ChargingConfig.model_validate(cfg), pack_info(n))


def charging_stages(run: Run) -> list[Mapping[str, object]]:
    return [s for s in run.stages() if s["stage"] in ("S20", "S30", "S40", "top_off")]


# --- worked examples ------------------------------------------------------------------------


def test_example1_one_first_one_second() -> None:
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2)
    run = drive(toy, ctrl, 4 * 3600)
    st = charging_stages(run)
    assert st[0]["stage"] == "S20" and st[0]["first"] == "0" and st[0]["second"] == "1"
    assert st[0]["vr1_v"] == 89.0 and st[0]["cmd_v"] == 92.0
    assert st[0]["closed"] == "0"
    assert st[1]["stage"] == "S30" and st[1]["closed"] == "0,1"
    assert st[1]["vt_v"] == 100.0 and st[1]["cmd_v"] == 100.0
    # while S20 ran, only battery 0 was connected
    s20 = [o for o in run.outputs if o.status["chg_stage"][0] == "S20"]
    assert s20 and all(o.commands.chg_on == (True, False) for o in s20)
    assert run.kinds("ChargeComplete")
    assert all(v >= 119.5 for v in toy.ocv)
    assert ctrl.stage is Stage.COMPLETE
    final = ctrl.step(toy.measure(), 1.0).commands
    assert final.chg_on == (False, False) and final.charger == CHARGER_OFF


def test_example2_two_first_batteries() -> None:
    toy = ToyPack([80.0, 80.0, 90.0])
    run = drive(toy, controller(3), 3600)
    st = charging_stages(run)
    assert st[0]["stage"] == "S20" and st[0]["first"] == "0,1" and st[0]["second"] == "2"
    assert (st[0]["vr1_v"], st[0]["cmd_v"]) == (89.0, 92.0)
    assert st[1]["stage"] == "S30" and st[1]["closed"] == "0,1,2"
    assert (st[1]["vt_v"], st[1]["cmd_v"]) == (100.0, 100.0)


@pytest.mark.parametrize(("mode", "vt2"), [("levels", 110.0), ("saturation", 120.0)])
def test_example3_and_4_six_batteries(mode: str, vt2: float) -> None:
    toy = ToyPack([80.0, 80.0, 90.0, 90.0, 100.0, 100.0])
    ctrl = controller(6, target_mode=mode)
    run = drive(toy, ctrl, 6 * 3600)
    st = charging_stages(run)
    # stage 1: first = the 80s, second = the 90s, Vt = V2 + 10 = 100 V
    assert (st[0]["stage"], st[0]["first"], st[0]["second"]) == ("S20", "0,1", "2,3")
    assert (st[0]["vr1_v"], st[0]["cmd_v"]) == (89.0, 92.0)
    assert (st[1]["stage"], st[1]["closed"], st[1]["vt_v"]) == ("S30", "0,1,2,3", 100.0)
    # stage 2: the four batteries are first, the 100s second; Vt = 110 / 120 (issue #24
    # item 4: stage 1's S30 charges the four towards its Vt, 100 V, and regroups once they are
    # at the next pair's Vr1 = 99 V, so S20 is skipped, spec §5's note: the text's "four 90 V"
    # is its own inconsistency, §7.3). The 100s join once the bus will charge them (item 3).
    assert (st[2]["stage"], st[2]["first"], st[2]["second"]) == ("S30", "0,1,2,3", "4,5")
    assert (st[2]["vr1_v"], st[2]["vt_v"]) == (99.0, vt2)
    assert (st[3]["stage"], st[3]["closed"], st[3]["vt_v"]) == ("S30", "0,1,2,3,4,5", vt2)
    # 110 V reached: 120 - 110 is not > ΔV2, so no S40 (example 3's last sentence)
    assert [s["stage"] for s in st[4:]] == ["top_off"] and st[-1]["cmd_v"] == 120.0
    assert run.kinds("ChargeComplete")
    # the 100 V batteries were never connected before stage 2's S30
    first_s30_all = next(k for k, o in enumerate(run.outputs) if o.commands.chg_on == (True,) * 6)
    assert all(not o.commands.chg_on[4] for o in run.outputs[:first_s30_all])


def test_example5_s40_then_top_off() -> None:
    toy = ToyPack([100.0, 100.0, 100.0])
    run = drive(toy, controller(3, v_sat_v=120.0, delta_v2_v=10.0), 4 * 3600)
    st = charging_stages(run)
    assert (st[0]["stage"], st[0]["vr2_v"], st[0]["cmd_v"], st[0]["closed"]) == (
        "S40",
        110.0,
        110.0,
        "0,1,2",
    )
    assert (st[1]["stage"], st[1]["cmd_v"]) == ("top_off", 120.0)
    assert run.kinds("ChargeComplete")


@pytest.mark.parametrize(
    ("v0", "hyst", "first"),
    [
        (109.8, 0.0, "S40"),  # 10.2 > ΔV2: S40 (the old ΔV2 + 0.5 V test topped off here)
        (110.0, 0.0, "top_off"),  # 10.0 is not > ΔV2 (a >= would start S40)
        (110.2, 0.0, "top_off"),
        (109.8, 0.5, "top_off"),  # the hysteresis is a separate setting, added to ΔV2
        (109.4, 0.5, "S40"),
    ],
)
def test_s40_threshold_is_delta_v2_exactly(v0: float, hyst: float, first: str) -> None:
    """Issue #15 §3: S40 fires at V_sat − V > ΔV2, the hysteresis is ``s40_hysteresis_v``."""
    toy = ToyPack([v0, v0])
    ctrl = controller(2, v_sat_v=120.0, delta_v2_v=10.0, s40_hysteresis_v=hyst)
    st = charging_stages(drive(toy, ctrl, 10))
    assert st[0]["stage"] == first
    if first == "S40":
        assert st[0]["vr2_v"] == pytest.approx(min(120.0, v0 + 10.0))


def test_saturation_s30_charges_to_v_sat_through_the_merge() -> None:
    """Issue #15 §3 / spec example 4: in saturation mode stage 2's S30 commands V_sat (120 V)
    and keeps it when its groups merge; no hand-over to S40 (levels mode does hand over)."""

    def six() -> ToyPack:
        return ToyPack([80.0, 80.0, 90.0, 90.0, 100.0, 100.0])

    sat = charging_stages(
        drive(six(), controller(6, target_mode="saturation"), 6 * 3600)
    )
    names = [s["stage"] for s in sat]
    last_s30 = max(k for k, n in enumerate(names) if n == "S30")
    assert (sat[last_s30]["vt_v"], sat[last_s30]["cmd_v"]) == (120.0, 120.0)
    assert sat[last_s30]["closed"] == "0,1,2,3,4,5"
    assert "S40" not in names
    assert names[last_s30 + 1 :] and set(names[last_s30 + 1 :]) == {"top_off"}
    lv = charging_stages(
        drive(six(), controller(6, target_mode="levels"), 6 * 3600)
    )
    # levels mode too charges through the merge, to V2 + step_v = 110 V (issue #24 item 4)
    assert [(s["stage"], s["vt_v"]) for s in lv if s["stage"] == "S30"][-1] == ("S30", 110.0)


def test_s30_charges_both_groups_to_vt_through_the_merge() -> None:
    """Issue #24 item 4: S30 charges the first and second batteries "until both reach Vt"
    (Vt = V2 + step_v, 90 -> 100 V in example 1). Before, 'levels' mode left S30 when the two
    groups merged (~90.5 V) and Vt was never reached: the next stage was an S40 step to
    ~100.5 V instead of one from 100 V to 110 V."""
    toy = ToyPack([80.0, 90.0])
    run = Run()
    ctrl = controller(2)
    while not any(s["stage"] == "S40" for s in run.stages()):
        drive(toy, ctrl, 60, run=run)
        assert len(run.outputs) < 4 * 3600
    st = charging_stages(run)
    assert [s["stage"] for s in st] == ["S20", "S30", "S40"]
    assert st[1]["vt_v"] == 100.0
    s40_at = next(k for k, o in enumerate(run.outputs) if o.status["chg_stage"][0] == "S40")
    est = run.outputs[s40_at].status["chg_est_v"]
    assert min(est) >= 100.0 - 0.5  # both reached Vt (within reach_tol) before S30 ended
    assert st[2]["vr2_v"] == pytest.approx(min(est) + 10.0, abs=0.6)
    assert st[2]["vr2_v"] >= 109.5


def test_single_battery_pack_charges() -> None:
    toy = ToyPack([85.0])
    run = drive(toy, controller(1), 4 * 3600)
    st = charging_stages(run)
    # 85 -> 95, then (exit at Vr2 - reach_tol) 94.5 -> 104.5, 104 -> 114, then top-off: the
    # step that ended within reach_tol of 114 counts as at 114 for the S40 test, 120 - 114 = 6
    assert [s["stage"] for s in st] == ["S40", "S40", "S40", "top_off"]
    assert [s["vr2_v"] for s in st[:3]] == pytest.approx([95.0, 104.5, 114.0], abs=0.05)
    assert run.kinds("ChargeComplete") and toy.ocv[0] > 119.0


def test_staging_cuts_peak_current_versus_all_closed() -> None:
    """The point of the method: no battery sees the all-relays-closed inrush."""
    v0 = [80.0, 80.0, 90.0, 90.0, 100.0, 100.0]
    staged = ToyPack(v0)
    drive(staged, controller(6), 6 * 3600)
    base = ToyPack(v0, closed=[True] * 6)
    base.charger_cmd = ChargerCommand(120.0, 20.0)
    for _ in range(6 * 3600):
        base.step(1.0)
    assert max(staged.peak_a) < 0.5 * max(base.peak_a)
    assert sum(staged.heat_j) < 0.5 * sum(base.heat_j)


# --- grouping, latching, IR compensation ----------------------------------------------------


def cluster_levels(values: Sequence[tuple[int, float]], eps_v: float) -> list[list[int]]:
    """Group ``(index, voltage)`` pairs into levels of span ≤ ``eps_v``, lowest level first.

    Sorting is by voltage then index, so ties are deterministic. A level is anchored at its
    lowest voltage (not single-linkage), so a chain of small gaps cannot grow one level wider
    than ``eps_v`` (:func:`rules.cluster`, which this calls).
    """
    n = len(values)
    vals = np.array([float(v) for _, v in values], np.float64)
    keys = np.array([int(i) for i, _ in values], np.int64)
    order = np.zeros(n, np.int64)
    level = np.zeros(n, np.int64)
    n_levels = rules.cluster(vals, keys, n, float(eps_v), order, level)
    out: list[list[int]] = [[] for _ in range(n_levels)]
    for k in range(n):
        out[int(level[k])].append(int(keys[order[k]]))
    return out


def test_cluster_levels_anchor_and_ties() -> None:
    vals = [(0, 80.0), (1, 80.4), (2, 80.8), (3, 90.0), (4, 79.9)]
    assert cluster_levels(vals, 0.5) == [[4, 0, 1], [2], [3]]
    assert cluster_levels([(1, 5.0), (0, 5.0)], 0.5) == [[0, 1]]
    assert cluster_levels([], 0.5) == []


def test_resistance_is_learned_from_relay_steps() -> None:
    toy = ToyPack([80.0, 90.0], r_ohm=0.08)
    ctrl = controller(2)
    drive(toy, ctrl, 60)
    assert ctrl.r_ohm[0] == pytest.approx(0.08, rel=0.05)


def test_noise_does_not_make_relays_chatter() -> None:
    toy = ToyPack([80.0, 80.0, 90.0, 90.0, 100.0, 100.0], noise_v=0.1, seed=3)
    ctrl = controller(6)
    run = drive(toy, ctrl, 6 * 3600)
    toggles = sum(
        a.commands.chg_on[i] != b.commands.chg_on[i]
        for a, b in zip(run.outputs, run.outputs[1:], strict=False)
        for i in range(6)
    )
    assert run.kinds("ChargeComplete")
    assert toggles <= 30, toggles
    assert len(run.stages()) <= 20


# --- docking, faults, fail-safes ------------------------------------------------------------


def test_not_docked_no_relay_opinion_and_charger_off() -> None:
    toy = ToyPack([80.0, 90.0], docked=False)
    out = controller(2).step(toy.measure(), 1.0)
    assert out.commands.chg_on == (None, None) and out.commands.dsg_on == (None, None)
    assert out.commands.charger == CHARGER_OFF


def test_rest_after_docking_then_undock_resets() -> None:
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2, dock_rest_s=3.0)
    run = drive(toy, ctrl, 3)
    assert all(o.status["chg_stage"][0] == "rest" for o in run.outputs)
    assert all(o.commands.chg_on == (False, False) for o in run.outputs)
    drive(toy, ctrl, 2, run=run)
    assert run.outputs[-1].status["chg_stage"][0] == "S20"
    toy.docked = False
    out = ctrl.step(toy.measure(), 1.0)
    assert out.status["chg_stage"][0] == "idle" and out.commands.chg_on == (None, None)


@pytest.mark.parametrize(
    "flag",
    [
        "hardware_failure",
        "over_temperature",
        "input_voltage_fault",
        "battery_not_detected",
        "communication_timeout",
    ],
)
def test_charger_flag_stops_charging_and_opens_relays(flag: str) -> None:
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2, charger_fault_clear_s=5.0)
    run = drive(toy, ctrl, 20)
    assert run.outputs[-1].commands.charger.enable  # type: ignore[union-attr]
    toy.charger_flags = {flag: True}
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.chg_on == (False, False) and out.commands.dsg_on == (False, False)
    assert out.commands.charger is not None and not out.commands.charger.enable
    faults = [e for e in out.events if e.kind == "Fault"]
    assert faults and faults[0].data[flag] is True
    # stays stopped while the flag is up and for charger_fault_clear_s after it clears
    run2 = drive(toy, ctrl, 10)
    assert all(o.commands.chg_on == (False, False) for o in run2.outputs)
    toy.charger_flags = {}
    run3 = drive(toy, ctrl, 8)
    assert run3.outputs[0].commands.chg_on == (False, False)
    assert run3.outputs[-1].commands.charger.enable  # type: ignore[union-attr]
    assert run3.stages()[0]["previous"] == "fault"


def test_charger_offline_and_lost() -> None:
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2, charger_status_timeout_s=3.0)
    drive(toy, ctrl, 10)
    toy.charger_online = False
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.chg_on == (False, False) and any(e.kind == "Fault" for e in out.events)
    # no status at all: tolerated for charger_status_timeout_s, then a Fault
    ctrl = controller(2, charger_status_timeout_s=3.0)
    meas = ToyPack([80.0, 90.0]).measure()
    meas = Measurements(t_s=0.0, batteries=meas.batteries, bus_v=math.nan, docked=True)
    outs = [ctrl.step(meas, 1.0) for _ in range(5)]
    faults = [e for o in outs for e in o.events if e.kind == "Fault"]
    assert len(faults) == 1 and "lost" in faults[0].message
    assert outs[-1].commands.chg_on == (False, False)


def test_nan_battery_left_out_with_relay_open() -> None:
    toy = ToyPack([80.0, 90.0, 80.0])
    ctrl = controller(3)
    drive(toy, ctrl, 5)
    meas = toy.measure()
    bad = BatteryMeasurement(
        voltage_v=math.nan,
        current_a=0.0,
        temp_c=25.0,
        min_cell_v=3.0,
        max_cell_v=3.0,
        soc=0.5,
        full_capacity_ah=5.0,
        remaining_capacity_ah=2.5,
    )
    meas = Measurements(
        t_s=meas.t_s,
        batteries=(bad, *meas.batteries[1:]),
        bus_v=meas.bus_v,
        charger=meas.charger,
        docked=True,
    )
    out = ctrl.step(meas, 1.0)
    assert out.commands.chg_on[0] is False
    assert out.commands.chg_on[2] is True  # the other 80 V battery keeps charging
    assert [e.battery for e in out.events if e.kind == "Fault"] == [0]
    assert out.status["chg_group"][0] == -1
    out = ctrl.step(meas, 1.0)  # the fault event is raised once, not every period
    assert not [e for e in out.events if e.kind == "Fault"]


def test_cell_limit_opens_relay() -> None:
    toy = ToyPack([80.0, 90.0], cell_offset_v=[0.4, 0.0])
    ctrl = controller(2, cell_v_limit_v=3.1)  # battery 0's top cell hits it once V > 81 V
    run = drive(toy, ctrl, 600)
    full = run.kinds("BatteryFull")
    assert full and full[0].battery == 0 and full[0].data["reason"] == "cell_limit"
    k = next(j for j, o in enumerate(run.outputs) if full[0] in o.events)
    assert all(not o.commands.chg_on[0] for o in run.outputs[k:])


def test_aux_battery_charged_independently() -> None:
    toy = ToyPack([80.0, 90.0], aux_soc=0.5)
    ctrl = ChargingController(ChargingConfig(), pack_info(2, has_aux=True))
    run = drive(toy, ctrl, 30)
    assert run.outputs[0].commands.aux_relay_closed is True
    assert run.outputs[0].commands.aux_charge_a == pytest.approx(5.0)
    # the aux battery never appears in the sort
    assert all(len(o.status["chg_group"]) == 2 for o in run.outputs)
    toy.aux_soc = 0.95
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.aux_relay_closed is False and out.commands.aux_charge_a == 0.0
    # undocked: never by default (the source charges battery 230 from the dock only) ...
    toy.docked = False
    toy.aux_soc = 0.2
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.aux_relay_closed is False and out.commands.aux_charge_a == 0.0
    # ... and an undocking while it charges stops it
    toy.docked = True
    assert ctrl.step(toy.measure(), 1.0).commands.aux_relay_closed is True
    toy.docked = False
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.aux_relay_closed is False and out.commands.aux_charge_a == 0.0


def test_aux_charged_from_the_traction_bus_only_as_an_option() -> None:
    """``aux_charge_from_bus``: undocked, below the floor only, up to floor + hysteresis."""
    toy = ToyPack([80.0, 90.0], aux_soc=0.5)
    cfg = ChargingConfig(aux_charge_from_bus=True)
    ctrl = ChargingController(cfg, pack_info(2, has_aux=True))
    toy.docked = False
    assert ctrl.step(toy.measure(), 1.0).commands.aux_charge_a == 0.0
    toy.aux_soc = 0.29
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.aux_relay_closed is True
    assert (out.commands.aux_charge_a or 0.0) > 0.0
    toy.aux_soc = 0.34  # below floor + hysteresis (0.35): keeps charging
    assert ctrl.step(toy.measure(), 1.0).commands.aux_relay_closed is True
    toy.aux_soc = 0.35
    assert ctrl.step(toy.measure(), 1.0).commands.aux_relay_closed is False
    toy.aux_soc = 0.31  # above the floor: does not restart
    assert ctrl.step(toy.measure(), 1.0).commands.aux_relay_closed is False


def test_aux_cv_taper() -> None:
    toy = ToyPack([80.0, 90.0], aux_soc=0.5)
    ctrl = ChargingController(ChargingConfig(aux_cv_v=13.1), pack_info(2, has_aux=True))
    out = ctrl.step(toy.measure(), 1.0)  # aux at 13.0 V, 0.1 V below CV of a 0.2 V band
    assert out.commands.aux_charge_a == pytest.approx(2.5)


def test_status_channels_per_battery() -> None:
    toy = ToyPack([80.0, 90.0, 100.0])
    run = drive(toy, controller(3), 10)
    status = run.outputs[-1].status
    for ch in ("chg_stage", "chg_group", "chg_relay", "chg_est_v", "chg_r_ohm", "chg_cmd_v"):
        assert len(status[ch]) == 3, ch
    assert list(status["chg_group"]) == [1, 2, 0]


def test_charger_status_none_before_timeout_still_charges() -> None:
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2)
    meas = toy.measure()
    meas = Measurements(t_s=0.0, batteries=meas.batteries, bus_v=math.nan, docked=True)
    outs = [ctrl.step(meas, 1.0) for _ in range(3)]
    assert outs[-1].commands.charger is not None and outs[-1].commands.charger.enable


def test_offline_status_object() -> None:
    st = ChargerStatus(output_v=math.nan, output_a=math.nan, online=False)
    toy = ToyPack([80.0])
    meas = toy.measure()
    meas = Measurements(t_s=0.0, batteries=meas.batteries, bus_v=1.0, charger=st, docked=True)
    out = controller(1).step(meas, 1.0)
    assert out.commands.charger == CHARGER_OFF


def test_dock_stays_on_for_aux_after_complete_then_off() -> None:
    toy = ToyPack([119.8], aux_soc=0.5)
    ctrl = ChargingController(ChargingConfig(), pack_info(1, has_aux=True))
    run = drive(toy, ctrl, 10)
    assert run.kinds("ChargeComplete")
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.chg_on == (False,)
    assert out.commands.charger is not None and out.commands.charger.enable
    assert out.commands.charger.voltage_v == 120.0 and out.commands.aux_relay_closed
    toy.aux_soc = 0.95
    out = ctrl.step(toy.measure(), 1.0)
    assert out.commands.charger == CHARGER_OFF and out.commands.aux_relay_closed is False
