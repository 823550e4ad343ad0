"""The simulated plant behind the loop's port: what the BMS's sensors read, what its commands
do, and one period of physics. The only code that touches the plant's internals.

A smart battery reports its terminal voltage, current, hottest and coldest cell, min/max cell
voltage, relative SOC and full/remaining capacity (the weakest cell limits a series string).
The port fills those into the batch measurements of all P packs with a few array reductions
(the same reductions a one-pack run uses, so P = 1 and P = N read identical numbers).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.arena import Arenas, unpack
from packpilot.config import ScenarioConfig
from packpilot.contract.arrays import NO_OPINION, BatteryArrays, CmdArrays, MeasArrays
from packpilot.contract.bms import SwitchKind
from packpilot.contract.topology import PackInfo, Topology
from packpilot.jit import kernel, kernel_inline
from packpilot.model.numerics import segment_sum, short_sum
from packpilot.model.pack import Interval, Pack
from packpilot.model.switches import KIND_RELAY
from packpilot.sim.sensors import sensors_of

Array = NDArray[np.float64]


def topology(cfg: ScenarioConfig) -> Topology:
    bats = cfg.pack.batteries
    return Topology(names=tuple(b.name for b in bats), roles=tuple(b.role for b in bats))


class SimulatedPlant:
    """``n_packs`` simulated packs of one scenario (campaign draws in ``overrides``: the
    ``Pack`` hooks, and ``sensor_stream``, each pack's key for its own sensor noise)."""

    def __init__(
        self, cfg: ScenarioConfig, n_packs: int = 1, overrides: Mapping[str, Any] | None = None
    ) -> None:
        self.cfg = cfg
        hooks = dict(overrides or {})
        streams = hooks.pop("sensor_stream", None)
        self.pack = Pack(cfg, n_packs=n_packs, **hooks)
        self.n_packs = n_packs
        self.topology = topology(cfg)
        self.traction = np.array(self.topology.traction, np.intp)
        self.aux = self.topology.aux
        self.infos = [self.pack_info(p) for p in range(n_packs)]
        pack = self.pack
        self._group_starts = np.asarray(pack.group_starts, np.int64)
        self._string_group_starts = np.asarray(pack.string_group_starts, np.int64)
        self._groups = np.array(pack.groups_per_string, np.int64)
        self._scratch = np.zeros(pack.n_strings)
        self._aux = -1 if self.aux is None else self.aux
        self.sensors = sensors_of(
            cfg.sensors, None if streams is None else np.asarray(streams, np.int64)
        )
        """The ``[sensors]`` errors (None: the sensors read the truth)."""

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
            balancer_max_a=float(cfg.balancer.max_current_a) if cfg.balancer.present else 0.0,
            balancer_bidirectional=bool(cfg.balancer.bidirectional),
            balancer_efficiency=float(cfg.balancer.efficiency),
            capacity_ah=tuple(float(pack.capacity_ah[p, pack.cell_string == i].min()) for i in tr),
            ocv_soc=tuple(float(x) for x in params.ocv_soc),
            ocv_v=tuple(float(x) for x in params.ocv_table_v),
            names=tuple(bats[i].name for i in tr),
            **_ecm(params),
            **_entropic(params),
            cell_v_min_v=float(params.v_min_v),
            cell_v_max_v=float(params.v_max_v),
            r_scale=tuple(float(pack.nominal_r_scale[pack.cell_string == i].mean()) for i in tr),
            charge_path_ohm=self._charge_path_ohm(),
        )

    def _charge_path_ohm(self) -> tuple[float, ...]:
        """Per traction battery, the resistance from the charger's regulation point to its
        cells (:attr:`PackInfo.charge_path_ohm`): the closed switch's (a relay's contact, a
        MOSFET pair's two channels in series) plus the charger's output slope times the
        number of traction batteries (its drop is the slope times the *total* current; with
        the current shared equally each battery sees that many times its own share), plus the
        battery's own leads, connectors and shunt (``series_ohm``, 0 unless stated)."""
        pack, cfg = self.pack, self.cfg
        tr = self.topology.traction
        share = float(cfg.charger.r_out_ohm) * len(tr) if cfg.charger.present else 0.0
        return tuple(
            float(pack.sw_on_ohm[i]) * (1.0 if pack.sw_kind[i] == KIND_RELAY else 2.0) + share
            + float(pack.series_ohm[i])
            for i in tr
        )

    def _traction_cell_params(self) -> Any:
        """Cell parameters of the first traction cell (the BMS's OCV table)."""
        pack = self.pack
        first = int(np.nonzero(~pack.is_aux[pack.cell_string])[0][0])
        return next(b.params for b in pack.banks if np.any(b.idx % pack.n_cells == first))

    # ------------------------------------------------------------------ sensing
    def measure(self, arenas: Arenas, m_row: int) -> None:
        """Fill the measurements at ``m_row`` of a core's arenas with what the sensors of every
        pack read now (the charger status is the link's business)."""
        pack = self.pack
        soc, temp = pack.cell_states()
        t = pack.t_s
        cell_v, string_a, bus_v = pack.cell_voltage_now(), pack.string_a, pack.bus_v
        if self.sensors is not None:
            cell_v, string_a, temp, bus_v = self.sensors.read(t, cell_v, string_a, temp, bus_v)
        sense(
            *arenas, m_row, t, cell_v, soc, temp, pack.capacity_ah,
            pack.string_cell_starts,
            self._group_starts, self._string_group_starts, self._groups, string_a,
            pack.chg_on, pack.dsg_on, pack.welded, pack.fet_shorted, pack.present_from_s,
            self.traction, self._aux, pack.is_aux, bus_v, bool(pack.charger_connected(t)[0]),
            self._scratch,
        )  # fmt: skip

    # ------------------------------------------------------------------ actuation
    def apply(self, arenas: Arenas, cmd_row: int) -> None:
        """Gates, balancer currents and the aux DC/DC as the commands at ``cmd_row`` of a
        core's arenas say (no opinion: unchanged). The charger setpoint is not a plant input:
        it travels over the charger link."""
        pack, cfg = self.pack, self.cfg
        bal = cfg.balancer
        actuate(
            *arenas, cmd_row, self.traction, -1 if self.aux is None else self.aux,
            self._string_group_starts, self._groups, pack.chg_on, pack.dsg_on,
            pack.balancer_a, pack.aux_charge_a, bal.present,
            -bal.max_current_a if bal.bidirectional else 0.0, bal.max_current_a,
            cfg.aux.dcdc_max_a,
        )  # fmt: skip
        pack.hold_unpowered()  # a browned-out BMU drives nothing

    # ------------------------------------------------------------------ physics
    def step(self, dt_s: float, demand: Array, kind: str | None = None) -> Interval:
        """One period of every pack under the load ``demand`` (P,) of ``kind`` (``current``,
        ``power``, ``resistance``, ``none``; the scenario's by default)."""
        return self.pack.step(dt_s, kind or self.cfg.load.kind, demand, reuse=True)


def _ecm(params: Any) -> dict[str, Any]:
    """The cell set's R0, R1 and tau = R1 C1 at zero current over (temperature, SOC), as the
    BMS's observer has them (the column of the current axis nearest 0 A)."""
    j = int(np.argmin(np.abs(params.rc_current_a)))
    r0 = params.r0_ohm[:, j, :]
    r1 = params.r1_ohm[:, j, :]
    tau = r1 * params.c1_f[:, j, :]
    return {
        "ecm_temp_c": tuple(float(x) for x in params.rc_temp_c),
        "ecm_soc": tuple(float(x) for x in params.rc_soc),
        "ecm_r0_ohm": tuple(float(x) for x in r0.ravel()),
        "ecm_r1_ohm": tuple(float(x) for x in r1.ravel()),
        "ecm_tau_s": tuple(float(x) for x in tau.ravel()),
    }


def _entropic(params: Any) -> dict[str, Any]:
    """The cell set's entropic term as the observer has it: dOCV/dT at every point of the OCV
    table and every temperature of the set's dU/dT axis (looked up as the plant does: on the
    OCV axis or the SOC axis, clamped or extended like the set), with its reference
    temperature; none (NaN, empty) when the set has no reference temperature."""
    if params.ocv_ref_temp_c is None:
        return {}
    clamp = params.extrapolation == "clamp"
    x = params.ocv_table_v if params.dudt_axis == "ocv_v" else params.ocv_soc
    ax = params.dudt_x
    k = np.clip(np.searchsorted(ax, x, side="right") - 1, 0, ax.size - 2)
    f = (x - ax[k]) / (ax[k + 1] - ax[k])
    if clamp:
        f = np.clip(f, 0.0, 1.0)
    du = params.dudt_v_per_k  # (len(dudt_x), len(dudt_temp_c))
    rows = [du[k, j] * (1 - f) + du[k + 1, j] * f for j in range(du.shape[1])]
    return {
        "ocv_ref_temp_c": float(params.ocv_ref_temp_c),
        "ocv_dudt_temp_c": tuple(float(t) for t in params.dudt_temp_c),
        "ocv_dudt_v_per_k": tuple(float(v) for row in rows for v in row),
    }


@kernel_inline
def _npmin(a: float, b: float) -> float:
    """``np.minimum`` on scalars: NaN propagates."""
    return a if a <= b or a != a else b


@kernel_inline
def _npmax(a: float, b: float) -> float:
    """``np.maximum`` on scalars: NaN propagates."""
    return a if a >= b or a != a else b


@kernel_inline
def _read_string(
    bat: BatteryArrays, p: int, k: int, s: int, t_s: float, cell_v: Array, soc: Array,
    temp: Array, cap: Array, starts: Any, group_starts: Any, string_group_starts: Any,
    groups: Any, string_a: Array, chg_on: Any, dsg_on: Any, welded: Any, fet_shorted: Any,
    present_from_s: Array,
) -> None:  # fmt: skip
    """String ``s`` of pack ``p`` into battery column ``k`` of ``bat``: the reductions NumPy's
    ``reduceat`` does, in its order (sums first item + pairwise rest; NaN propagates). Switch
    feedback is the gate as the hardware really is (``Pack.effective_gates``: welded relays
    closed, shorted FETs on); presence is ``Pack.present`` at ``t_s``."""
    C = cell_v.shape[1]
    lo = starts[s]
    hi = starts[s + 1] if s + 1 < starts.shape[0] else C
    row = cell_v[p]
    vmin = vmax = row[lo]
    tmax = tmin = temp[p, lo]
    rem = soc[p, lo] * cap[p, lo]
    full = cap[p, lo]
    for c in range(lo + 1, hi):
        vmin = _npmin(vmin, row[c])
        vmax = _npmax(vmax, row[c])
        tmax = _npmax(tmax, temp[p, c])
        tmin = _npmin(tmin, temp[p, c])
        rem = _npmin(rem, soc[p, c] * cap[p, c])
        full = _npmin(full, cap[p, c])
    bat.voltage_v[p, k] = segment_sum(row, starts, s)
    bat.current_a[p, k] = string_a[p, s]
    bat.temp_c[p, k] = tmax
    bat.min_temp_c[p, k] = tmin
    bat.min_cell_v[p, k] = vmin
    bat.max_cell_v[p, k] = vmax
    bat.soc[p, k] = rem / full if full > 0 else np.nan
    bat.full_capacity_ah[p, k] = full
    bat.remaining_capacity_ah[p, k] = rem
    bat.sample_age_s[p, k] = np.nan
    g0 = string_group_starts[s]
    ng = groups[s]
    for g in range(bat.group_v.shape[2]):
        bat.group_v[p, k, g] = segment_sum(row, group_starts, g0 + g) if g < ng else np.nan
    bat.n_groups[p, k] = ng
    bat.sw_chg[p, k] = chg_on[p, s] | welded[s] | fet_shorted[p, s, 0]
    bat.sw_dsg[p, k] = dsg_on[p, s] | welded[s] | fet_shorted[p, s, 1]
    bat.present[p, k] = present_from_s[s] <= t_s + 1e-12
    bat.reported[p, k] = True


@kernel
def sense(
    f: Any, i: Any, h: Any, c: Any, b: Any, lay: Any, m_row: int,
    t_s: float, cell_v: Array, soc: Array, temp: Array, cap: Array,
    starts: Any, group_starts: Any, string_group_starts: Any, groups: Any, string_a: Array,
    chg_on: Any, dsg_on: Any, welded: Any, fet_shorted: Any, present_from_s: Array,
    traction: Any, aux: int, is_aux: Any, bus_v: Array, docked: bool, scratch: Array,
) -> None:  # fmt: skip
    """What the sensors of every pack read now (all but the charger status), into the
    measurements at layout row ``m_row`` of the core's arena."""
    m = unpack(MeasArrays, f, i, h, c, b, lay, m_row)
    for p in range(cell_v.shape[0]):
        m.t_s[p] = t_s
        for k in range(traction.shape[0]):
            _read_string(m.bat, p, k, traction[k], t_s, cell_v, soc, temp, cap, starts,
                         group_starts, string_group_starts, groups, string_a, chg_on, dsg_on,
                         welded, fet_shorted, present_from_s)  # fmt: skip
        if aux >= 0:
            _read_string(m.aux, p, 0, aux, t_s, cell_v, soc, temp, cap, starts, group_starts,
                         string_group_starts, groups, string_a, chg_on, dsg_on, welded,
                         fet_shorted, present_from_s)  # fmt: skip
        m.has_aux[p] = aux >= 0
        m.bus_v[p] = bus_v[p]
        n = 0
        for s in range(string_a.shape[1]):  # np.sum over the traction strings: NumPy's order
            if not is_aux[s]:
                scratch[n] = string_a[p, s]
                n += 1
        m.load_current_a[p] = scratch[0] + short_sum(scratch, 1, n - 1)
        m.docked[p] = docked


@kernel_inline
def _clip(x: float, lo: float, hi: float) -> float:
    """``np.clip(np.nan_to_num(x), lo, hi)``."""
    if x != x:
        x = 0.0
    return min(max(x, lo), hi)


@kernel
def actuate(
    f: Any, i: Any, h: Any, c: Any, b: Any, lay: Any, cmd_row: int, traction: Any, aux: int,
    string_group_starts: Any, groups: Any, chg_on: Any, dsg_on: Any, balancer_a: Array,
    aux_charge_a: Array, balancer_present: bool, bal_lo: float, bal_hi: float, aux_max: float,
) -> None:  # fmt: skip
    """The merged commands into the plant's gates, balancers and aux DC/DC (in place)."""
    cmd = unpack(CmdArrays, f, i, h, c, b, lay, cmd_row)
    for p in range(chg_on.shape[0]):
        for k in range(traction.shape[0]):
            s = traction[k]
            if cmd.chg_on[p, k] != NO_OPINION:
                chg_on[p, s] = cmd.chg_on[p, k] == 1
            if cmd.dsg_on[p, k] != NO_OPINION:
                dsg_on[p, s] = cmd.dsg_on[p, k] == 1
        if aux >= 0 and cmd.aux_relay[p] != NO_OPINION:
            chg_on[p, aux] = cmd.aux_relay[p] == 1
            dsg_on[p, aux] = cmd.aux_relay[p] == 1
        if cmd.balancer_set[p]:
            balancer_a[p].fill(0.0)
            for k in range(traction.shape[0]):
                s = traction[k]
                g0 = string_group_starts[s]
                for g in range(groups[s]):
                    balancer_a[p, g0 + g] = cmd.balancer_a[p, k, g]
            for g in range(balancer_a.shape[1]):
                if balancer_present:
                    balancer_a[p, g] = _clip(balancer_a[p, g], bal_lo, bal_hi)
                else:
                    balancer_a[p, g] = 0.0
        if cmd.aux_charge_set[p]:
            aux_charge_a[p] = _clip(cmd.aux_charge_a[p], 0.0, aux_max)


__all__ = ["SimulatedPlant", "actuate", "sense", "topology"]
