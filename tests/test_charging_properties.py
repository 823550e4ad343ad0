"""Property tests: for any starting voltages the staged charger stays within its limits, never
connects batteries further apart than the staging allows, and finishes with every battery full."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import BatteryMeasurement, Measurements
from packpilot.control.charging import ChargingConfig, ChargingController, Stage
from tests.budget import budget
from tests.test_charging_helpers import ToyPack, pack_info

volts = st.floats(min_value=80.0, max_value=119.0, allow_nan=False)


@budget(200)
@given(
    v0=st.lists(volts, min_size=1, max_size=6),
    mode=st.sampled_from(["levels", "saturation"]),
    eps=st.floats(min_value=0.1, max_value=1.0),
    r_ohm=st.floats(min_value=0.02, max_value=0.3),
)
def test_charges_everything_within_limits(
    v0: list[float], mode: str, eps: float, r_ohm: float
) -> None:
    cfg = ChargingConfig(target_mode=mode, eps_eq_v=eps)
    ctrl = ChargingController(cfg, pack_info(len(v0)))
    toy = ToyPack(v0, r_ohm=r_ohm, slope_v_per_ah=40.0, capacity_ah=1.0)
    complete = False
    for _ in range(20_000):
        meas = toy.measure()
        out = ctrl.step(meas, 1.0)
        ch = out.commands.charger
        assert ch is not None
        if ch.enable:
            assert ch.voltage_v <= cfg.v_sat_v
            assert 0.0 < ch.current_a <= cfg.charger_current_limit_a
        closed = [i for i, c in enumerate(out.commands.chg_on) if c]
        # connected batteries never differ (at rest-equivalent voltage) by more than the
        # staging allows: one level + the regulation gap + the R-estimate error margin
        if len(closed) > 1 and ctrl.stage in (Stage.S20, Stage.S30):
            ocv = [toy.ocv[i] for i in closed]
            assert max(ocv) - min(ocv) <= cfg.delta_v1_v + eps + 0.5
        toy.apply(out)
        toy.step(1.0)
        if any(e.kind == "ChargeComplete" for e in out.events):
            complete = True
            break
    assert complete
    assert all(v >= cfg.v_sat_v - 1.0 for v in toy.ocv), toy.ocv
    # a battery carries at most the charger's limit plus the circulation across the largest
    # voltage gap the staging ever closes a relay on
    spread = cfg.delta_v1_v + eps + 0.5
    assert max(toy.peak_a) <= cfg.charger_current_limit_a + spread / r_ohm


@budget(200)
@given(
    seq=st.lists(
        st.tuples(
            st.sampled_from([math.nan, math.inf, -1.0, 0.0, 95.0, 130.0]),
            st.sampled_from([math.nan, 0.0, -30.0, 500.0]),
            st.booleans(),
            st.booleans(),
        ),
        min_size=1,
        max_size=40,
    )
)
def test_garbage_measurements_never_raise(
    seq: list[tuple[float, float, bool, bool]],
) -> None:
    ctrl = ChargingController(ChargingConfig(), pack_info(2, has_aux=True))
    for k, (v, cur, docked, present) in enumerate(seq):
        bm = BatteryMeasurement(
            voltage_v=v,
            current_a=cur,
            temp_c=25.0,
            min_cell_v=v / 30,
            max_cell_v=v / 30,
            soc=0.5,
            full_capacity_ah=5.0,
            remaining_capacity_ah=2.5,
            present=present,
        )
        meas = Measurements(t_s=float(k), batteries=(bm, bm), bus_v=v, aux=bm, docked=docked)
        out = ctrl.step(meas, math.nan if k % 7 == 3 else 1.0)
        assert len(out.commands.chg_on) == 2
        if not docked:
            assert out.commands.chg_on == (None, None)
        if not (present and math.isfinite(v) and math.isfinite(cur)):
            assert out.commands.chg_on in ((None, None), (False, False))
