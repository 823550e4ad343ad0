"""From plant truth to what the BMS measures: the ``Measurements`` of one pack.

A smart battery reports its terminal voltage, current, hottest cell, min/max cell voltage,
relative SOC and full/remaining capacity (the weakest cell limits a series string). This module
is the only place that reads plant internals for the controller.
"""

from __future__ import annotations

import numpy as np

from packpilot.control.types import (
    BatteryMeasurement,
    ChargerStatus,
    Measurements,
    PackInfo,
    SwitchKind,
    SwitchState,
)
from packpilot.model.pack import Pack
from packpilot.model.switches import KIND_RELAY


def pack_info(pack: Pack) -> PackInfo:
    cfg = pack.cfg
    bats = cfg.pack.batteries
    traction = traction_indices(pack)
    return PackInfo(
        n_batteries=len(traction),
        groups_per_battery=tuple(bats[i].series_groups for i in traction),
        cells_per_group=tuple(bats[i].cells_per_group for i in traction),
        switch_kind=tuple(
            SwitchKind.RELAY if pack.sw_kind[i] == KIND_RELAY else SwitchKind.MOSFET_PAIR
            for i in traction
        ),
        has_aux=pack.aux_index is not None,
        has_charger=cfg.charger.present,
        has_balancers=cfg.balancer.present,
        capacity_ah=tuple(
            float(pack.capacity_ah[0, pack.cell_string == i].min()) for i in traction
        ),
    )


def traction_indices(pack: Pack) -> list[int]:
    """String indices of the traction batteries (everything but the aux battery), in order."""
    return [i for i in range(pack.n_strings) if not pack.is_aux[i]]


def battery_truth(pack: Pack, p: int = 0) -> list[BatteryMeasurement]:
    """Per-battery status of pack ``p`` at the present instant (all strings, aux included)."""
    cell_v = pack.cell_voltage_now()[p]
    soc, temp = pack.cell_states()
    starts = pack.string_cell_starts
    cap = pack.capacity_ah[p]
    remaining = np.minimum.reduceat(soc[p] * cap, starts)
    full = np.minimum.reduceat(cap, starts)
    volts = np.add.reduceat(cell_v, starts)
    vmin = np.minimum.reduceat(cell_v, starts)
    vmax = np.maximum.reduceat(cell_v, starts)
    tmax = np.maximum.reduceat(temp[p], starts)
    tmin = np.minimum.reduceat(temp[p], starts)
    group_v = np.add.reduceat(cell_v, pack.group_starts).tolist()
    present = pack.present()[p]
    chg, dsg = pack.effective_gates()
    current = pack.string_a[p]
    out: list[BatteryMeasurement] = []
    for i in range(pack.n_strings):
        g0 = int(pack.string_group_starts[i])
        f = float(full[i])
        out.append(
            BatteryMeasurement(
                voltage_v=float(volts[i]),
                current_a=float(current[i]),
                temp_c=float(tmax[i]),
                min_temp_c=float(tmin[i]),
                min_cell_v=float(vmin[i]),
                max_cell_v=float(vmax[i]),
                soc=float(remaining[i]) / f if f > 0 else float("nan"),
                full_capacity_ah=f,
                remaining_capacity_ah=float(remaining[i]),
                group_voltages_v=tuple(group_v[g0 : g0 + pack.groups_per_string[i]]),
                switch=SwitchState(chg_on=bool(chg[p, i]), dsg_on=bool(dsg[p, i])),
                present=bool(present[i]),
            )
        )
    return out


def measure(pack: Pack, charger: ChargerStatus | None, p: int = 0) -> Measurements:
    """Measurements of pack ``p``: traction batteries in config order; the aux one apart."""
    truth = battery_truth(pack, p)
    aux = truth[pack.aux_index] if pack.aux_index is not None else None
    return Measurements(
        t_s=pack.t_s,
        batteries=tuple(truth[i] for i in traction_indices(pack)),
        bus_v=float(pack.bus_v[p]),
        load_current_a=float(pack.string_a[p, ~pack.is_aux].sum()),
        charger=charger,
        aux=aux,
        docked=bool(pack.charger_connected(pack.t_s)[p]),
    )
