"""ChargingConfig validation and the per-cell voltage basis."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from packpilot.control.charging import REFERENCE_SERIES, ChargingConfig, ChargingController, Volts
from packpilot.errors import ConfigError
from tests.test_charging_helpers import pack_info


def test_defaults_are_the_spec_values() -> None:
    cfg = ChargingConfig()
    assert (cfg.delta_v1_v, cfg.d1_v, cfg.vc1_margin_v) == (3.0, 1.0, 3.0)
    assert (cfg.step_v, cfg.delta_v2_v, cfg.eps_eq_v, cfg.v_sat_v) == (10.0, 10.0, 0.5, 120.0)
    assert cfg.target_mode == "levels"


@pytest.mark.parametrize(
    ("kw", "fragment"),
    [
        ({"eps_eq_v": 3.0}, "eps_eq_v (3.0) must be smaller than delta_v1_v"),
        ({"d1_v": 3.5}, "d1_v (3.5) must be smaller than delta_v1_v"),
        ({"delta_v1_v": 0.0}, "delta_v1_v"),
        ({"d1_v": -1.0}, "d1_v"),
        ({"termination_current_a": 25.0}, "termination_current_a (25.0) must be smaller"),
        ({"aux_soc_floor": 0.9, "aux_soc_target": 0.8}, "aux_soc_floor"),
        ({"target_mode": "fastest"}, "target_mode"),
        ({"v_sat_v": float("nan")}, "v_sat_v"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_invalid_values_name_the_field(kw: dict[str, object], fragment: str) -> None:
    with pytest.raises(ValidationError) as err:
        ChargingConfig.model_validate(kw)
    assert fragment in str(err.value)


def test_cell_basis_scales_with_series_count() -> None:
    cfg = ChargingConfig(voltage_basis="cell", v_sat_v=4.1)
    assert cfg.delta_v1_v == pytest.approx(3.0 / REFERENCE_SERIES)
    vs = Volts.resolve(cfg, pack_info(2, series=28))
    assert vs.v_sat == pytest.approx(4.1 * 28)
    assert vs.delta_v1 == pytest.approx(3.0 * 28 / 30)
    assert vs.eps_eq == pytest.approx(0.5 * 28 / 30)
    # battery basis ignores the series count
    assert Volts.resolve(ChargingConfig(), pack_info(2, series=28)).v_sat == 120.0


def test_cell_basis_needs_one_series_count() -> None:
    info = pack_info(2)
    info = type(info)(
        n_batteries=2,
        groups_per_battery=(28, 30),
        cells_per_group=(1, 1),
        switch_kind=info.switch_kind,
    )
    with pytest.raises(ConfigError, match="one common series cell count"):
        ChargingController(ChargingConfig(voltage_basis="cell"), info)


def test_cell_basis_counts_cells_in_series_inside_groups() -> None:
    """A group is cells_per_group cells in *series*: 1 group of 6 cells is a 6S battery."""
    from dataclasses import replace

    info = replace(pack_info(2, series=1), cells_per_group=(6, 6))
    volts = Volts.resolve(ChargingConfig(voltage_basis="cell", v_sat_v=4.2), info)
    assert volts.v_sat == pytest.approx(6 * 4.2)
