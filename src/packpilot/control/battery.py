"""Facts about one battery that several rules read (compiled): its capacity and whether its
switch can carry current in a direction."""

from __future__ import annotations

import math

from packpilot.contract.arrays import MeasArrays, PackArrays
from packpilot.jit import kernel


@kernel
def capacity_ah(tp: PackArrays, m: MeasArrays, p: int, i: int) -> float:
    """Nominal capacity from the pack facts, else the battery's reported full capacity, else
    NaN."""
    nominal = tp.capacity_ah[p, i]
    if math.isfinite(nominal) and nominal > 0:
        return float(nominal)
    full = m.bat.full_capacity_ah[p, i]
    if m.bat.reported[p, i] and math.isfinite(full) and full > 0:
        return float(full)
    return math.nan


@kernel
def conducts(tp: PackArrays, m: MeasArrays, p: int, i: int, charge_path: bool) -> bool:
    """Switch feedback says the battery can carry current in that direction.

    A relay conducts both ways only when closed; a MOSFET pair conducts discharge while its
    discharge FET is on (the charge FET's body diode passes it) and charge while its charge FET
    is on.
    """
    chg, dsg = m.bat.sw_chg[p, i], m.bat.sw_dsg[p, i]
    if tp.relay[i]:
        return bool(chg and dsg)
    return bool(chg) if charge_path else bool(dsg)


__all__ = ["capacity_ah", "conducts"]
