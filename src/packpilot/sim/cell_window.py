"""Checks of a scenario against the cells it simulates: settings that pass their own section's
bounds but are absurd for this pack's cells (a protection cut-off of 4.5 V on cells that are
full at 4.2 V, a charging saturation voltage of 10 V per cell).

They need the cell set, which the config layer cannot read, so they run where the BMS is built
(:func:`packpilot.sim.loop.build_core`); each error names the field as the config formatter does.
"""

from __future__ import annotations

from collections.abc import Sequence

from packpilot.config import ScenarioConfig
from packpilot.config.base import CELL_V_MAX_V
from packpilot.config.charging import ChargingConfig
from packpilot.config.protection import ProtectionConfig
from packpilot.contract.topology import PackInfo
from packpilot.errors import ConfigError


def full_cell_v(infos: Sequence[PackInfo]) -> float | None:
    """The highest rest voltage of the traction cells (their OCV at full), if known."""
    tops = [max(info.ocv_v) for info in infos if info.ocv_v]
    return max(tops) if tops else None


def check_cell_window(cfg: ScenarioConfig, infos: Sequence[PackInfo]) -> None:
    """Refuse cut-offs and charge voltages outside the cells' voltage window."""
    full = full_cell_v(infos)
    if "protection" in cfg.controller and full is not None:
        _check_protection(cfg, full)
    if "charging" in cfg.controller:
        _check_charging(cfg, infos)


def _check_protection(cfg: ScenarioConfig, full_v: float) -> None:
    """A cut-off at or above a full cell trips on a battery that is not discharged at all."""
    prot = cfg.protection or ProtectionConfig()
    for k, par in enumerate(prot.parameters):
        if par.cutoff_v >= full_v:
            raise ConfigError(
                f"protection.parameters.{k}.cutoff_v: {par.cutoff_v:g} V is at or above a full "
                f"cell of this pack ({full_v:.3g} V at rest)"
            )


def _check_charging(cfg: ScenarioConfig, infos: Sequence[PackInfo]) -> None:
    """The saturation voltage per cell must stay at or below the cell voltage limit (itself at
    most :data:`~packpilot.config.base.CELL_V_MAX_V`): 10 V per cell is a typo, not a setting."""
    chg = cfg.charging or ChargingConfig()
    limit = min(chg.cell_v_limit_v, CELL_V_MAX_V)
    v_sat = chg.v_sat_v
    per_cell_basis = chg.voltage_basis == "cell"
    for info in infos:
        for b, groups in enumerate(info.groups_per_battery):
            cells = groups * info.cells_per_group[b]
            per_cell = v_sat if per_cell_basis else v_sat / cells
            if per_cell > limit + 1e-9:
                raise ConfigError(
                    f"charging.v_sat_v: {v_sat:g} V is {per_cell:.4g} V per cell on battery {b} "
                    f"({cells} cells in series), above the cell limit {limit:g} V"
                )


__all__ = ["check_cell_window", "full_cell_v"]
