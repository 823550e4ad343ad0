"""Battery switches: a relay, or a MOSFET pair whose body diodes each pass one direction.

A MOSFET pair is a charge FET and a discharge FET in series. Each FET, when off, still
conducts through its body diode in one direction:

* the **charge FET's** diode conducts when the battery *discharges*, so with the charge FET off
  the battery can still supply the bus (with a diode drop) but cannot be charged;
* the **discharge FET's** diode conducts when the battery is *charged*.

So discharge current needs the discharge FET on (its diode blocks that direction) and passes
the charge FET through the channel or the diode; the mirror holds for charge current. Each
string's current is therefore a monotone piecewise-linear function of the bus voltage, which
is what lets :mod:`packpilot.model.bus` solve the bus exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

KIND_RELAY = 0
KIND_MOSFET = 1


@dataclass(frozen=True)
class BranchArrays:
    """Per-string branch description for the bus solve (arrays of shape (..., n_strings)).

    Discharge branch: I = max(0, (E - dsg_drop_v - V) / dsg_ohm) where ``dsg_ok``.
    Charge branch:    I = min(0, (E + chg_drop_v - V) / chg_ohm) where ``chg_ok``.
    """

    dsg_ok: BoolArray
    dsg_drop_v: Array
    dsg_ohm: Array
    chg_ok: BoolArray
    chg_drop_v: Array
    chg_ohm: Array


def switch_branches(
    kind: NDArray[np.int64],
    on_ohm: Array,
    diode_drop_v: Array,
    diode_ohm: Array,
    chg_on: BoolArray,
    dsg_on: BoolArray,
    present: BoolArray,
    batt_ohm: Array,
) -> BranchArrays:
    """Translate gate states into the two conduction branches of each string.

    ``batt_ohm`` is the string's own series resistance (cells), added to both branches.
    A relay is closed iff both gates are on (see ``contract.bms.SwitchState``).
    """
    is_relay = kind == KIND_RELAY
    relay_closed = chg_on & dsg_on
    # MOSFET pair, discharge direction: needs DSG FET on; CHG FET via channel or diode.
    m_dsg_ok = dsg_on
    m_dsg_drop = np.where(chg_on, 0.0, diode_drop_v)
    m_dsg_ohm = on_ohm + np.where(chg_on, on_ohm, diode_ohm)
    # Charge direction: needs CHG FET on; DSG FET via channel or diode.
    m_chg_ok = chg_on
    m_chg_drop = np.where(dsg_on, 0.0, diode_drop_v)
    m_chg_ohm = on_ohm + np.where(dsg_on, on_ohm, diode_ohm)

    dsg_ok = np.where(is_relay, relay_closed, m_dsg_ok) & present
    chg_ok = np.where(is_relay, relay_closed, m_chg_ok) & present
    dsg_drop = np.where(is_relay, 0.0, m_dsg_drop)
    chg_drop = np.where(is_relay, 0.0, m_chg_drop)
    dsg_ohm = batt_ohm + np.where(is_relay, on_ohm, m_dsg_ohm)
    chg_ohm = batt_ohm + np.where(is_relay, on_ohm, m_chg_ohm)
    return BranchArrays(
        dsg_ok=np.asarray(dsg_ok, dtype=bool),
        dsg_drop_v=np.asarray(dsg_drop, dtype=np.float64),
        dsg_ohm=np.asarray(dsg_ohm, dtype=np.float64),
        chg_ok=np.asarray(chg_ok, dtype=bool),
        chg_drop_v=np.asarray(chg_drop, dtype=np.float64),
        chg_ohm=np.asarray(chg_ohm, dtype=np.float64),
    )


def diode_currents(
    kind: NDArray[np.int64], chg_on: BoolArray, dsg_on: BoolArray, current_a: Array
) -> tuple[Array, Array]:
    """Current carried by the charge-FET diode and the discharge-FET diode (both >= 0).

    The charge diode carries discharge current while the charge FET is off; the discharge
    diode carries charge current while the discharge FET is off. Relays have no diodes.
    """
    mos = kind == KIND_MOSFET
    chg_diode = np.where(mos & ~chg_on & (current_a > 0.0), current_a, 0.0)
    dsg_diode = np.where(mos & ~dsg_on & (current_a < 0.0), -current_a, 0.0)
    return chg_diode, dsg_diode
