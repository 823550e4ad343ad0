"""Issue #15 §2: the charge each group's equalizer delivers follows its AH.

S43 gives each updated group its AH as charge owed; the balancing time is 3600·AH/I (I the
current the equalizer carries: the string current within its rating, else the rating) and
what one update period cannot deliver is carried over as owed Ah, never dropped. Also: no
no-op ``BalancingUpdated`` events, and ``ah_per`` (cell or group).
"""

from __future__ import annotations

import pytest

from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.equalization import (
    EVENT_RESOLUTION_AH,
    EqualizationConfig,
    EqualizationController,
)
from tests.test_equalization_properties import _meas

LAG = (11.0, 13.0)  # with dv_set = 0.5 V: ΔV0 = +1 V > dv_set (group 0 lags)
HOLD = (12.0, 13.0)  # ΔV0 = +0.5 V = dv_set exactly: no timer runs, AH is not updated


def pack(groups: int = 2) -> PackInfo:
    return PackInfo(1, (groups,), (1,), (SwitchKind.RELAY,), has_balancers=True)


def meas(t: float, gv: tuple[float, ...], current_a: float) -> Measurements:
    """One battery of 10 Ah at 25 C with these group voltages (the properties' helper)."""
    return _meas(t, gv, current_a)


def one_grant(n_ah: float, ah0: float, current_a: float) -> EqualizationController:
    """Group 0 lags for exactly one T1 (one formula-1 update: AH ← (ah0 + N)/2), then sits
    at ΔV = dv_set (no further update) until everything owed is delivered."""
    cfg = EqualizationConfig(dv_set_v=0.5, n_ah=n_ah, equalizer_max_a=2.0, min_current_a=0.5)
    ctrl = EqualizationController(cfg, pack())
    ctrl.strings[0].ah = [ah0, 0.0]
    for k in range(120):
        ctrl.step(meas(float(k), LAG, current_a), 1.0)
    assert ctrl.strings[0].counts["formula1"] == 1
    k = 120
    while ctrl.strings[0].owed_ah[0] > 0.0:
        ctrl.step(meas(float(k), HOLD, current_a), 1.0)
        k += 1
        assert k < 10_000
    return ctrl


def test_issue_example_time_follows_ah_at_10_a() -> None:
    # Issue #15: at 10 A, AH 0.25 and 0.4375 Ah both gave 120 s (clamped to T1 at 2 A).
    # Now: 3600·AH/2 A = 450 s and 787.5 s, and the group receives exactly its AH.
    low = one_grant(0.5, 0.0, 10.0).strings[0]
    high = one_grant(0.5, 0.375, 10.0).strings[0]
    assert (low.ah[0], high.ah[0]) == (0.25, 0.4375)
    assert low.ledger_time_s[0] == pytest.approx(450.0)
    assert high.ledger_time_s[0] == pytest.approx(787.5)
    assert low.ledger_gross_ah[0] == pytest.approx(0.25)
    assert high.ledger_gross_ah[0] == pytest.approx(0.4375)


@pytest.mark.parametrize("current_a", [1.5, 10.0])
def test_balancing_time_grows_with_ah_proportionally(current_a: float) -> None:
    # Below the rating (1.5 A) the time is the claims' 3600·AH/|I_batt|; above it (10 A) the
    # equalizer carries its 2 A rating for 3600·AH/2: in both cases proportional to AH.
    i_eq = min(current_a, 2.0)
    ns = [0.02, 0.05, 0.1, 0.2, 0.5, 0.875]
    times = []
    for n in ns:
        st = one_grant(n, 0.0, current_a).strings[0]
        ah = n / 2.0
        assert st.ah[0] == ah
        assert st.ledger_gross_ah[0] == pytest.approx(ah, rel=1e-9)
        assert st.ledger_granted_ah[0] == ah
        times.append(st.ledger_time_s[0])
        assert st.ledger_time_s[0] == pytest.approx(3600.0 * ah / i_eq, rel=1e-9)
    assert times == sorted(times) and len(set(times)) == len(times)  # strictly monotone


def test_persistent_lag_carries_owed_and_delivers_it() -> None:
    # Issue #15: 600 s of lagging at 10 A took AH to 0.48 Ah but delivered only 0.27 Ah (the
    # rest was dropped at each update). Now the owed balance is carried and delivered.
    cfg = EqualizationConfig(dv_set_v=0.5, equalizer_max_a=2.0)
    ctrl = EqualizationController(cfg, pack())
    st = ctrl.strings[0]
    for k in range(600):
        out = ctrl.step(meas(float(k), LAG, 10.0), 1.0)
    assert st.ah[0] == pytest.approx(0.484375)
    # Continuous at the 2 A rating from the first update (t = 119 s) on: 481 s.
    assert st.ledger_gross_ah[0] == pytest.approx(2.0 * 481 / 3600)
    # Raised to AH at the last update (t = 599 s), then one step delivered.
    assert st.owed_ah[0] == pytest.approx(0.484375 - 2.0 / 3600)
    assert out.status["eq_owed_ah_g0"] == [pytest.approx(st.owed_ah[0])]
    assert st.ledger_granted_ah[0] == pytest.approx(st.ledger_gross_ah[0] + st.owed_ah[0])
    k = 600
    while st.owed_ah[0] > 0.0:
        out = ctrl.step(meas(float(k), HOLD, 10.0), 1.0)
        k += 1
    assert out.commands.balancer_a is not None
    # Delivered = granted, and more than the AH the group reached: nothing was dropped.
    assert st.ledger_gross_ah[0] == pytest.approx(st.ledger_granted_ah[0])
    assert st.ledger_gross_ah[0] >= st.ah[0]
    assert k == pytest.approx(599 + 3600 * 0.484375 / 2.0, abs=1.0)


def test_a_group_above_the_average_gets_nothing_and_formula2_cuts_what_it_is_owed() -> None:
    # Issue #24 item 2. Group 0 stands above the average (ΔV0 = -0.5 V < dv_set): it receives
    # nothing, and formula 2, halving its AH every T2, halves what it is owed with it (S43: the
    # balancing time follows AH). Before: the 0.3 Ah were delivered in full (1080 s at 1 A).
    cfg = EqualizationConfig(
        dv_set_v=0.5, time_mode="fixed_current", fixed_current_a=1.0, balance_at_rest=True
    )
    ctrl = EqualizationController(cfg, pack())
    st = ctrl.strings[0]
    st.ah = [0.3, 0.0]
    st.owed_ah = [0.3, 0.0]
    gv = (13.0, 12.0)  # ΔV0 = -0.5 V, ΔV1 = +0.5 V = dv_set (no update of group 1)
    for k in range(60):
        out = ctrl.step(meas(float(k), gv, 0.0), 1.0)
        assert out.commands.balancer_a is None or out.commands.balancer_a[0][0] == 0.0
    assert st.counts["formula2"] == 1 and st.ah[0] == 0.15
    assert st.owed_ah[0] == 0.15  # lowered with AH, nothing delivered
    assert st.ledger_granted_ah[0] == pytest.approx(-0.15)  # the cut is booked
    for k in range(60, 1200):
        ctrl.step(meas(float(k), gv, 0.0), 1.0)
    assert st.ledger_gross_ah[0] == 0.0
    assert st.owed_ah[0] == st.ah[0] == pytest.approx(0.3 / 2**20)
    assert st.ledger_granted_ah[0] == pytest.approx(st.ledger_gross_ah[0] + st.owed_ah[0] - 0.3)


def test_formula2_cuts_what_a_group_below_the_average_is_still_owed() -> None:
    # ΔV0 = +0.25 V: below the average but within dv_set: delivered at 1 A, and at T2 what is
    # owed becomes the halved AH (0.15), not 0.3 less the 60 s delivered.
    cfg = EqualizationConfig(
        dv_set_v=0.5, time_mode="fixed_current", fixed_current_a=1.0, balance_at_rest=True
    )
    ctrl = EqualizationController(cfg, pack())
    st = ctrl.strings[0]
    st.ah = [0.3, 0.0]
    st.owed_ah = [0.3, 0.0]
    gv = (12.75, 13.25)
    for k in range(60):
        ctrl.step(meas(float(k), gv, 0.0), 1.0)
    assert st.counts["formula2"] >= 1 and st.ah[0] == 0.15
    # The update sample's own step delivers after the cut: 0.15 less one second at 1 A.
    assert st.owed_ah[0] == pytest.approx(0.15 - 1 / 3600)
    assert st.ledger_gross_ah[0] == pytest.approx(60 / 3600)
    for k in range(60, 3000):
        ctrl.step(meas(float(k), gv, 0.0), 1.0)
        assert st.owed_ah[0] <= st.ah[0] + 1e-12  # never more than AH is owed
    assert st.ledger_gross_ah[0] < 0.3


def test_the_subtraction_cuts_what_is_owed() -> None:
    # S42 resets every AH by the minimum; what each group is owed falls with its AH.
    cfg = EqualizationConfig(dv_set_v=0.5, time_mode="fixed_current", fixed_current_a=1.0)
    ctrl = EqualizationController(cfg, pack(3))
    st = ctrl.strings[0]
    st.ah = [0.2, 0.3, 0.25]
    st.owed_ah = [0.2, 0.3, 0.25]
    ctrl.step(meas(0.0, (12.0, 12.0, 12.0), 0.0), 1.0)
    assert st.counts["subtract_min"] == 1
    assert st.ah == pytest.approx([0.0, 0.1, 0.05])
    assert st.owed_ah == pytest.approx([0.0, 0.1, 0.05])


def test_an_update_above_what_is_owed_raises_it_and_books_the_raise() -> None:
    cfg = EqualizationConfig(dv_set_v=0.5, time_mode="fixed_current", fixed_current_a=1.0)
    ctrl = EqualizationController(cfg, pack())
    st = ctrl.strings[0]
    st.owed_ah = [0.1, 0.0]
    for k in range(120):
        ctrl.step(meas(float(k), LAG, 5.0), 1.0)
    # 119 s delivered at 1 A before the update, then raised to AH = 0.25 (booked: 0.25 - owed).
    before = 0.1 - 119 / 3600
    assert st.ah[0] == 0.25
    assert st.ledger_granted_ah[0] == pytest.approx(0.25 - before)
    assert st.owed_ah[0] == pytest.approx(0.25 - 1 / 3600)


def _updates(out: ControlOutput) -> list[tuple[float, float]]:
    return [
        (float(e.data["old"]), float(e.data["new"]))  # type: ignore[arg-type]
        for e in out.events
        if e.kind == "BalancingUpdated"
    ]


def test_no_op_events_are_not_emitted() -> None:
    # Halving AH = 2e-4 Ah changes it by exactly the 1e-4 Ah resolution: not more, no event;
    # from 2.5e-4 Ah it is 1.25e-4 > 1e-4: an event.
    assert EVENT_RESOLUTION_AH == 1e-4
    for ah0, emitted in ((2e-4, False), (2.5e-4, True), (1e-5, False)):
        cfg = EqualizationConfig(dv_set_v=0.5)
        ctrl = EqualizationController(cfg, pack())
        ctrl.strings[0].ah = [ah0, 0.0]
        outs = [ctrl.step(meas(float(k), (13.0, 12.0), 5.0), 1.0) for k in range(60)]
        assert ctrl.strings[0].counts["formula2"] == 1  # the rule was applied either way
        assert ctrl.strings[0].ah[0] == ah0 / 2
        assert [u for o in outs for u in _updates(o)] == ([(ah0, ah0 / 2)] if emitted else [])


def test_no_event_renders_an_unchanged_ah() -> None:
    ctrl = EqualizationController(EqualizationConfig(), pack(4))
    seen = 0
    for k in range(3000):
        v = (12.97 + 0.01 * ((k // 500) % 2), 13.0, 13.01 - 0.02 * ((k // 700) % 2), 13.0)
        out = ctrl.step(meas(float(k), v, 5.0), 1.0)
        for e in out.events:
            if e.kind == "BalancingUpdated":
                seen += 1
                old, new = float(e.data["old"]), float(e.data["new"])  # type: ignore[arg-type]
                assert abs(new - old) > EVENT_RESOLUTION_AH
                assert f"{old:.4f}" != f"{new:.4f}", e.message
    assert seen > 5


def test_ah_per_cell_and_per_group_command_the_same_on_group_hardware() -> None:
    # This plant measures group voltages and has one equalizer per group: the cells of a group
    # share its ΔV (the claims' S1 samples groups) and, in series, its equalizer's charge, so
    # per-cell AH (the claims, the default) and per-group AH give identical commands.
    def run(ah_per: str) -> list[object]:
        cfg = EqualizationConfig(ah_per=ah_per)  # type: ignore[arg-type]
        info = PackInfo(1, (4,), (4,), (SwitchKind.RELAY,), has_balancers=True)
        ctrl = EqualizationController(cfg, info)
        seq: list[object] = []
        for k in range(400):
            v = (12.97 + 0.0001 * (k % 7), 13.0, 13.01, 13.0)
            out = ctrl.step(meas(float(k), v, 5.0), 1.0)
            seq.append((out.commands, out.events, out.status))
        return seq

    assert run("cell") == run("group")
