"""Scalar forms of the battery facts, for a caller still on the scalar contract: the
plausibility monitor imports them from ``packpilot.control.limits`` until its own port uses
:mod:`packpilot.control.battery` (then this module goes). Not used by the limits rules."""

from __future__ import annotations

import math

from packpilot.config.base import load_section_model
from packpilot.config.limits import Path
from packpilot.contract.bms import BatteryMeasurement, SwitchKind
from packpilot.contract.topology import PackInfo


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


def capacity_ah(pack: PackInfo, i: int, bm: BatteryMeasurement | None) -> float:
    """Nominal capacity from the pack facts, else the battery's reported full capacity, else NaN."""
    if i < len(pack.capacity_ah) and _finite(pack.capacity_ah[i]) and pack.capacity_ah[i] > 0:
        return float(pack.capacity_ah[i])
    if bm is not None and _finite(bm.full_capacity_ah) and bm.full_capacity_ah > 0:
        return float(bm.full_capacity_ah)
    return math.nan


def conducts(pack: PackInfo, i: int, bm: BatteryMeasurement, path: Path) -> bool:
    """Switch feedback says the battery can carry current in ``path``'s direction.

    A relay conducts both ways only when closed; a MOSFET pair conducts discharge while its
    discharge FET is on (the charge FET's body diode passes it) and charge while its charge FET
    is on.
    """
    sw = bm.switch
    kind = pack.switch_kind[i] if i < len(pack.switch_kind) else SwitchKind.RELAY
    if kind == SwitchKind.RELAY:
        return sw.relay_closed
    return sw.chg_on if path == "charge" else sw.dsg_on


__all__ = ["capacity_ah", "conducts", "load_section_model"]
