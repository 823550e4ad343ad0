"""Issue #24 item 6: every ΔV1 the source lists is accepted, with defaults that scale.

spec/staged_charging.md lists ΔV1 = 1, 3, 5, 8, 10 or 0.5 V. ``d1_v`` (Vr1 = V2 − d1) and
``eps_eq_v`` (the equal-voltage tolerance) must both stay below ΔV1; with their fixed defaults
(1 V, 0.5 V) ΔV1 = 0.5 V and 1 V were refused. Unset, they now default to
min(fixed default, ΔV1/3) and min(fixed default, ΔV1/6).
"""

from __future__ import annotations

import pytest

from packpilot.control.charging import ChargingConfig
from tests.test_charging_controller import charging_stages, controller, drive
from tests.test_charging_helpers import ToyPack

SOURCE_DELTA_V1 = (0.5, 1.0, 3.0, 5.0, 8.0, 10.0)


@pytest.mark.parametrize("dv1", SOURCE_DELTA_V1)
def test_every_source_delta_v1_is_accepted_with_defaults_below_it(dv1: float) -> None:
    cfg = ChargingConfig(delta_v1_v=dv1)
    assert cfg.d1_v == pytest.approx(min(1.0, dv1 / 3.0))
    assert cfg.eps_eq_v == pytest.approx(min(0.5, dv1 / 6.0))
    assert cfg.d1_v < dv1 and cfg.eps_eq_v < dv1
    cell = ChargingConfig(voltage_basis="cell", delta_v1_v=dv1 / 30.0)
    assert cell.d1_v == pytest.approx(min(1.0, dv1 / 3.0) / 30.0)
    assert cell.eps_eq_v == pytest.approx(min(0.5, dv1 / 6.0) / 30.0)


def test_the_fixed_defaults_hold_from_three_volts_up() -> None:
    # The example's 90 V → Vr1 = 89 V (d1 = 1 V) whatever ΔV1 >= 3 V; nothing moves there.
    for dv1 in (3.0, 5.0, 10.0):
        cfg = ChargingConfig(delta_v1_v=dv1)
        assert (cfg.d1_v, cfg.eps_eq_v) == (1.0, 0.5)


def test_explicit_values_are_kept_and_still_checked() -> None:
    cfg = ChargingConfig(delta_v1_v=0.5, d1_v=0.2, eps_eq_v=0.1)
    assert (cfg.d1_v, cfg.eps_eq_v) == (0.2, 0.1)
    with pytest.raises(ValueError, match="d1_v"):
        ChargingConfig(delta_v1_v=0.5, d1_v=0.6)
    with pytest.raises(ValueError, match="eps_eq_v"):
        ChargingConfig(delta_v1_v=0.5, eps_eq_v=0.5)


def test_half_a_volt_delta_v1_charges_the_example_pack() -> None:
    """The source's example 1 (80 V and 90 V) with ΔV1 = 0.5 V: S20 charges the low battery to
    Vr1 = 90 − 0.5/3 V (V2 − Vr1 < ΔV1), then S30 both, to the end."""
    toy = ToyPack([80.0, 90.0])
    ctrl = controller(2, delta_v1_v=0.5)
    run = drive(toy, ctrl, 4 * 3600)
    st = charging_stages(run)
    assert st[0]["stage"] == "S20" and st[0]["closed"] == "0"
    vr1 = float(st[0]["vr1_v"])  # type: ignore[arg-type]
    assert vr1 == pytest.approx(90.0 - 0.5 / 3.0, abs=1e-6)
    assert 0.0 < 90.0 - vr1 < 0.5
    assert st[1]["stage"] == "S30" and st[1]["closed"] == "0,1"
    assert run.kinds("ChargeComplete")
    assert all(v >= 119.5 for v in toy.ocv)
