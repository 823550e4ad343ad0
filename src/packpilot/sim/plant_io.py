"""The simulated plant behind the loop's port: what the BMS's sensors read, what its commands
do, and one period of physics. The only code that touches the plant's internals.

A smart battery reports its terminal voltage, current, hottest and coldest cell, min/max cell
voltage, relative SOC and full/remaining capacity (the weakest cell limits a series string).
The port fills those into the batch measurements of all P packs with a few array reductions
(the same reductions a one-pack run uses, so P = 1 and P = N read identical numbers).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.contract.arrays import NO_OPINION, BatteryArrays, CmdArrays, MeasArrays
from packpilot.contract.bms import SwitchKind
from packpilot.contract.topology import PackInfo, Topology
from packpilot.model.pack import Interval, Pack
from packpilot.model.switches import KIND_RELAY

Array = NDArray[np.float64]


def topology(cfg: ScenarioConfig) -> Topology:
    bats = cfg.pack.batteries
    return Topology(names=tuple(b.name for b in bats), roles=tuple(b.role for b in bats))


class SimulatedPlant:
    """``n_packs`` simulated packs of one scenario (campaign draws in ``overrides``)."""

    def __init__(
        self, cfg: ScenarioConfig, n_packs: int = 1, overrides: Mapping[str, Any] | None = None
    ) -> None:
        self.cfg = cfg
        self.pack = Pack(cfg, n_packs=n_packs, **dict(overrides or {}))
        self.n_packs = n_packs
        self.topology = topology(cfg)
        self.traction = np.array(self.topology.traction, np.intp)
        self.aux = self.topology.aux
        self.infos = [self.pack_info(p) for p in range(n_packs)]

    @property
    def t_s(self) -> float:
        return self.pack.t_s

    # ------------------------------------------------------------------ static facts
    def pack_info(self, p: int = 0) -> PackInfo:
        """What the BMS of pack ``p`` is configured with (capacities differ in campaigns)."""
        pack, cfg = self.pack, self.cfg
        bats = cfg.pack.batteries
        tr = self.topology.traction
        params = self._traction_cell_params()
        return PackInfo(
            n_batteries=len(tr),
            groups_per_battery=tuple(bats[i].series_groups for i in tr),
            cells_per_group=tuple(bats[i].cells_per_group for i in tr),
            switch_kind=tuple(
                SwitchKind.RELAY if pack.sw_kind[i] == KIND_RELAY else SwitchKind.MOSFET_PAIR
                for i in tr
            ),
            has_aux=pack.aux_index is not None,
            has_charger=cfg.charger.present,
            has_balancers=cfg.balancer.present,
            capacity_ah=tuple(
                float(pack.capacity_ah[p, pack.cell_string == i].min()) for i in tr
            ),
            ocv_soc=tuple(float(x) for x in params.ocv_soc),
            ocv_v=tuple(float(x) for x in params.ocv_table_v),
        )

    def _traction_cell_params(self) -> Any:
        """Cell parameters of the first traction cell (the BMS's OCV table)."""
        pack = self.pack
        first = int(np.nonzero(~pack.is_aux[pack.cell_string])[0][0])
        return next(b.params for b in pack.banks if np.any(b.idx % pack.n_cells == first))

    # ------------------------------------------------------------------ sensing
    def measure(self, m: MeasArrays, packs: Sequence[int] | None = None) -> None:
        """Fill ``m`` with what the sensors read now (all packs; the charger status is the
        link's business). ``packs``: only these rows (the others keep their values)."""
        pack = self.pack
        rows: slice | list[int] = slice(None) if packs is None else list(packs)
        cell_v = pack.cell_voltage_now()[rows]
        soc, temp = pack.cell_states()
        soc, temp = soc[rows], temp[rows]
        starts = pack.string_cell_starts
        cap = pack.capacity_ah[rows]
        remaining = np.minimum.reduceat(soc * cap, starts, axis=1)
        full = np.minimum.reduceat(cap, starts, axis=1)
        chg, dsg = pack.effective_gates()
        s = _Strings(
            voltage_v=np.add.reduceat(cell_v, starts, axis=1),
            current_a=pack.string_a[rows],
            temp_c=np.maximum.reduceat(temp, starts, axis=1),
            min_temp_c=np.minimum.reduceat(temp, starts, axis=1),
            min_cell_v=np.minimum.reduceat(cell_v, starts, axis=1),
            max_cell_v=np.maximum.reduceat(cell_v, starts, axis=1),
            remaining=remaining,
            full=full,
            group_v=np.add.reduceat(cell_v, pack.group_starts, axis=1),
            chg=chg[rows],
            dsg=dsg[rows],
            present=pack.present()[rows],
        )
        m.t_s[rows] = pack.t_s
        _put(m.bat, rows, s, self.traction, pack)
        if self.aux is not None:
            _put(m.aux, rows, s, np.array([self.aux], np.intp), pack)
        m.has_aux[rows] = self.aux is not None
        m.bus_v[rows] = pack.bus_v[rows]
        m.load_current_a[rows] = pack.string_a[rows][:, ~pack.is_aux].sum(axis=1)
        m.docked[rows] = pack.charger_connected(pack.t_s)[rows]

    # ------------------------------------------------------------------ actuation
    def apply(self, cmd: CmdArrays) -> None:
        """Gates, balancer currents and the aux DC/DC as commanded (no opinion: unchanged).
        The charger setpoint is not a plant input: it travels over the charger link."""
        pack = self.pack
        tr = self.traction
        chg = pack.chg_on.copy()
        dsg = pack.dsg_on.copy()
        sub = chg[:, tr]
        sub = np.where(cmd.chg_on == NO_OPINION, sub, cmd.chg_on == 1)
        chg[:, tr] = sub
        sub = dsg[:, tr]
        sub = np.where(cmd.dsg_on == NO_OPINION, sub, cmd.dsg_on == 1)
        dsg[:, tr] = sub
        aux = pack.aux_index
        if aux is not None:
            said = cmd.aux_relay != NO_OPINION
            chg[said, aux] = cmd.aux_relay[said] == 1
            dsg[said, aux] = cmd.aux_relay[said] == 1
        pack.set_gates(chg, dsg)
        if cmd.balancer_set.any():
            bal = pack.balancer_a.copy()
            for p in np.nonzero(cmd.balancer_set)[0]:
                row = np.zeros(pack.n_groups)
                for k, i in enumerate(tr):
                    g0 = int(pack.string_group_starts[i])
                    ng = pack.groups_per_string[i]
                    row[g0 : g0 + ng] = cmd.balancer_a[p, k, :ng]
                bal[p] = row
            pack.set_balancer(bal)
        if cmd.aux_charge_set.any():
            aux_a = pack.aux_charge_a.copy()
            aux_a[cmd.aux_charge_set] = cmd.aux_charge_a[cmd.aux_charge_set]
            pack.set_aux_charge(aux_a)

    # ------------------------------------------------------------------ physics
    def step(self, dt_s: float, demand: Array) -> Interval:
        """One period of every pack under the load ``demand`` (P,)."""
        return self.pack.step(dt_s, self.cfg.load.kind, demand)


class _Strings:
    """Per-string sensor readings of the selected packs (internal)."""

    __slots__ = (
        "chg",
        "current_a",
        "dsg",
        "full",
        "group_v",
        "max_cell_v",
        "min_cell_v",
        "min_temp_c",
        "present",
        "remaining",
        "temp_c",
        "voltage_v",
    )

    def __init__(self, **kw: Any) -> None:
        for k, v in kw.items():
            setattr(self, k, v)


def _put(a: BatteryArrays, rows: slice | list[int], s: _Strings, strings: Any, pack: Pack) -> None:
    """Readings of ``strings`` (string indices) into battery columns 0.. of ``a``."""
    idx = np.asarray(strings, np.intp)
    full = s.full[:, idx]
    rem = s.remaining[:, idx]
    with np.errstate(invalid="ignore", divide="ignore"):
        soc = np.where(full > 0, rem / np.where(full > 0, full, 1.0), np.nan)
    n = idx.size
    a.voltage_v[rows, :n] = s.voltage_v[:, idx]
    a.current_a[rows, :n] = s.current_a[:, idx]
    a.temp_c[rows, :n] = s.temp_c[:, idx]
    a.min_temp_c[rows, :n] = s.min_temp_c[:, idx]
    a.min_cell_v[rows, :n] = s.min_cell_v[:, idx]
    a.max_cell_v[rows, :n] = s.max_cell_v[:, idx]
    a.soc[rows, :n] = soc
    a.full_capacity_ah[rows, :n] = full
    a.remaining_capacity_ah[rows, :n] = rem
    a.sample_age_s[rows, :n] = np.nan
    for k, i in enumerate(idx):
        g0 = int(pack.string_group_starts[i])
        ng = pack.groups_per_string[i]
        a.group_v[rows, k, :ng] = s.group_v[:, g0 : g0 + ng]
        a.group_v[rows, k, ng:] = np.nan
        a.n_groups[rows, k] = ng
    a.sw_chg[rows, :n] = s.chg[:, idx]
    a.sw_dsg[rows, :n] = s.dsg[:, idx]
    a.present[rows, :n] = s.present[:, idx]
    a.reported[rows, :n] = True


__all__ = ["SimulatedPlant", "topology"]
