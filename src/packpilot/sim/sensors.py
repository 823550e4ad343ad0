"""From plant truth to what the BMS measures: the ``Measurements`` of one pack.

A smart battery reports its terminal voltage, current, hottest cell, min/max cell voltage,
relative SOC and full/remaining capacity (the weakest cell limits a series string). This module
is the only place that reads plant internals for the controller.
"""

from __future__ import annotations

from collections.abc import Sequence

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


def pack_info(pack: Pack, p: int = 0) -> PackInfo:
    """Static facts of pack ``p`` (capacities differ between the packs of a campaign batch)."""
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
            float(pack.capacity_ah[p, pack.cell_string == i].min()) for i in traction
        ),
    )


def traction_indices(pack: Pack) -> list[int]:
    """String indices of the traction batteries (everything but the aux battery), in order."""
    return [i for i in range(pack.n_strings) if not pack.is_aux[i]]


def _rows(pack: Pack, packs: Sequence[int] | None) -> slice | list[int]:
    """Row selector over packs: a slice (a view, no copy) for all packs or one pack."""
    if packs is None:
        return slice(None)
    if len(packs) == 1:
        return slice(packs[0], packs[0] + 1)
    return list(packs)


def battery_truth(pack: Pack, p: int = 0) -> list[BatteryMeasurement]:
    """Per-battery status of pack ``p`` at the present instant (all strings, aux included)."""
    return battery_truth_all(pack, [p])[0]


def battery_truth_all(
    pack: Pack, packs: Sequence[int] | None = None
) -> list[list[BatteryMeasurement]]:
    """:func:`battery_truth` of several packs (default: all), from one set of array reductions
    over the packs (what lockstep batches use; the per-pack loop calls it with one pack, so
    both read the same numbers)."""
    rows = _rows(pack, packs)
    cell_v = pack.cell_voltage_now()[rows]
    soc, temp = pack.cell_states()
    soc, temp = soc[rows], temp[rows]
    starts = pack.string_cell_starts
    cap = pack.capacity_ah[rows]
    remaining = np.minimum.reduceat(soc * cap, starts, axis=1)
    full = np.minimum.reduceat(cap, starts, axis=1)
    volts = np.add.reduceat(cell_v, starts, axis=1).tolist()
    vmin = np.minimum.reduceat(cell_v, starts, axis=1).tolist()
    vmax = np.maximum.reduceat(cell_v, starts, axis=1).tolist()
    tmax = np.maximum.reduceat(temp, starts, axis=1).tolist()
    tmin = np.minimum.reduceat(temp, starts, axis=1).tolist()
    group_v = np.add.reduceat(cell_v, pack.group_starts, axis=1).tolist()
    present = pack.present()[rows].tolist()
    chg, dsg = pack.effective_gates()
    chg_l, dsg_l = chg[rows].tolist(), dsg[rows].tolist()
    current = pack.string_a[rows].tolist()
    rem_l, full_l = remaining.tolist(), full.tolist()
    g_start = [int(x) for x in pack.string_group_starts]
    g_n = pack.groups_per_string
    out: list[list[BatteryMeasurement]] = []
    for r in range(len(volts)):
        bats: list[BatteryMeasurement] = []
        for i in range(pack.n_strings):
            f = full_l[r][i]
            bats.append(
                BatteryMeasurement(
                    voltage_v=volts[r][i],
                    current_a=current[r][i],
                    temp_c=tmax[r][i],
                    min_temp_c=tmin[r][i],
                    min_cell_v=vmin[r][i],
                    max_cell_v=vmax[r][i],
                    soc=rem_l[r][i] / f if f > 0 else float("nan"),
                    full_capacity_ah=f,
                    remaining_capacity_ah=rem_l[r][i],
                    group_voltages_v=tuple(group_v[r][g_start[i] : g_start[i] + g_n[i]]),
                    switch=SwitchState(chg_on=chg_l[r][i], dsg_on=dsg_l[r][i]),
                    present=present[r][i],
                )
            )
        out.append(bats)
    return out


def measure_all(
    pack: Pack, charger: ChargerStatus | None = None, packs: Sequence[int] | None = None
) -> list[Measurements]:
    """:func:`measure` of several packs (default: all) of a lockstep plant, from one set of
    reductions; :func:`measure` is this for one pack, so both paths see the same numbers."""
    rows = _rows(pack, packs)
    truth = battery_truth_all(pack, packs)
    traction = traction_indices(pack)
    docked = pack.charger_connected(pack.t_s)[rows].tolist()
    bus_v = pack.bus_v[rows].tolist()
    load_a = pack.string_a[rows][:, ~pack.is_aux].sum(axis=1).tolist()
    aux = pack.aux_index
    return [
        Measurements(
            t_s=pack.t_s,
            batteries=tuple(truth[r][i] for i in traction),
            bus_v=bus_v[r],
            load_current_a=load_a[r],
            charger=charger,
            aux=truth[r][aux] if aux is not None else None,
            docked=docked[r],
        )
        for r in range(len(truth))
    ]


def measure(pack: Pack, charger: ChargerStatus | None, p: int = 0) -> Measurements:
    """Measurements of pack ``p``: traction batteries in config order; the aux one apart."""
    return measure_all(pack, charger, [p])[0]
