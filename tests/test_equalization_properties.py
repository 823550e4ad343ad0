"""Property tests: AH bounds and the charge ledger."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.equalization import (
    EqualizationConfig,
    EqualizationController,
    balancing_time_s,
)
from tests.budget import budget


def _meas(t: float, gv: tuple[float, ...], cur: float) -> Measurements:
    b = BatteryMeasurement(
        voltage_v=sum(gv),
        current_a=cur,
        temp_c=25.0,
        min_cell_v=min(gv),
        max_cell_v=max(gv),
        soc=0.5,
        full_capacity_ah=10.0,
        remaining_capacity_ah=5.0,
        group_voltages_v=gv,
    )
    return Measurements(t_s=t, batteries=(b,), bus_v=b.voltage_v)


configs = st.builds(
    EqualizationConfig,
    dv_set_v=st.floats(0.001, 0.02),
    t2_s=st.floats(2.0, 20.0),
    t1_s=st.floats(21.0, 60.0),
    n_ah=st.floats(0.0, 1.0),
    time_mode=st.sampled_from(["string_current", "fixed_current"]),
    equalizer=st.sampled_from(["unidirectional", "bidirectional"]),
    ah_per=st.sampled_from(["cell", "group"]),
)


@st.composite
def runs(draw: st.DrawFn) -> tuple[int, list[tuple[float, tuple[float, ...], float]]]:
    m = draw(st.integers(1, 6))
    n = draw(st.integers(1, 60))
    segs = []
    for _ in range(n):
        gv = tuple(draw(st.floats(12.9, 13.1)) for _ in range(m))
        cur = draw(st.floats(-20.0, 20.0))
        dt = draw(st.floats(0.2, 30.0))
        segs.append((dt, gv, cur))
    return m, segs


@budget(200)
@given(cfg=configs, run=runs())
def test_ah_stays_within_zero_and_n(
    cfg: EqualizationConfig, run: tuple[int, list[tuple[float, tuple[float, ...], float]]]
) -> None:
    m, segs = run
    pack = PackInfo(1, (m,), (1,), (SwitchKind.RELAY,), has_balancers=True)
    ctrl = EqualizationController(cfg, pack)
    t = 0.0
    for dt, gv, cur in segs:
        # Hold each random condition for several steps so that the timers can fire.
        for _ in range(5):
            ctrl.step(_meas(t, gv, cur), dt)
            t += dt
            assert all(0.0 <= a <= cfg.n_ah for a in ctrl.strings[0].ah)
            # The owed Ah is set to AH at each update: it stays within 0..N too.
            assert all(0.0 <= a <= cfg.n_ah for a in ctrl.strings[0].owed_ah)


@budget(200)
@given(cfg=configs, run=runs())
def test_ledger_charge_equals_time_times_current(
    cfg: EqualizationConfig, run: tuple[int, list[tuple[float, tuple[float, ...], float]]]
) -> None:
    m, segs = run
    pack = PackInfo(1, (m,), (1,), (SwitchKind.RELAY,), has_balancers=True)
    ctrl = EqualizationController(cfg, pack)
    commanded = [0.0] * m
    t = 0.0
    for dt, gv, cur in segs:
        for _ in range(5):
            out = ctrl.step(_meas(t, gv, cur), dt)
            t += dt
            assert out.commands.balancer_a is not None
            for g, i in enumerate(out.commands.balancer_a[0]):
                assert abs(i) <= cfg.equalizer_max_a + 1e-12
                if cfg.equalizer == "unidirectional":
                    assert i >= 0.0
                commanded[g] += i * dt / 3600.0
    st_ = ctrl.strings[0]
    for g in range(m):
        # Nothing granted is dropped: granted = delivered + still owed.
        assert math.isclose(
            st_.ledger_granted_ah[g],
            st_.ledger_gross_ah[g] + st_.owed_ah[g],
            rel_tol=1e-9,
            abs_tol=1e-12,
        )
        # What the equalizers were told to move is what the ledger booked.
        assert math.isclose(commanded[g], st_.ledger_net_ah[g], rel_tol=1e-9, abs_tol=1e-12)
        if cfg.time_mode == "fixed_current":
            assert math.isclose(
                st_.ledger_gross_ah[g],
                st_.ledger_time_s[g] * cfg.fixed_current_a / 3600.0,
                rel_tol=1e-9,
                abs_tol=1e-12,
            )
        else:
            # Equalizer current never exceeds its rating: charge ≤ time × I_max.
            assert (
                st_.ledger_gross_ah[g]
                <= st_.ledger_time_s[g] * cfg.equalizer_max_a / 3600.0 + 1e-12
            )
        if cfg.equalizer == "unidirectional":
            assert st_.ledger_net_ah[g] == st_.ledger_gross_ah[g] or math.isclose(
                st_.ledger_net_ah[g], st_.ledger_gross_ah[g], rel_tol=1e-9, abs_tol=1e-12
            )
    if cfg.equalizer == "bidirectional" and m > 0:
        # The median shift is common-mode: relative charges are those of the AH rule.
        d_net = [x - st_.ledger_net_ah[0] for x in st_.ledger_net_ah]
        d_gross = [x - st_.ledger_gross_ah[0] for x in st_.ledger_gross_ah]
        assert all(math.isclose(a, b, abs_tol=1e-9) for a, b in zip(d_net, d_gross, strict=True))


@budget(200)
@given(
    ah=st.floats(0.0, 1.0),
    cur=st.floats(0.5, 50.0),
    mode=st.sampled_from(["string_current", "fixed_current"]),
)
def test_undisturbed_grant_delivers_ah(ah: float, cur: float, mode: str) -> None:
    """With constant current and no further AH update, a grant moves exactly AH."""
    cfg = EqualizationConfig(dv_set_v=0.5, time_mode=mode)
    pack = PackInfo(1, (2,), (1,), (SwitchKind.RELAY,), has_balancers=True)
    ctrl = EqualizationController(cfg, pack)
    ctrl.strings[0].owed_ah = [ah, 0.0]
    # Group 0 sits exactly at ΔV = dv_set (no update), group 1 leads with AH = 0.
    steps = int(balancing_time_s(ah, cur, cfg) / 7.0) + 2
    for k in range(steps):
        ctrl.step(_meas(7.0 * k, (12.0, 13.0), cur), 7.0)
    assert math.isclose(ctrl.strings[0].ledger_gross_ah[0], ah, rel_tol=1e-9, abs_tol=1e-12)
