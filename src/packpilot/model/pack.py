"""The pack plant: strings in parallel on one bus, each string = series groups of cells.

Every cell is simulated (equivalent circuit + thermal, :mod:`packpilot.model.cell`), so the
min/max cell voltage of a group is the real spread, not a guess. A pack object steps ``n_packs``
packs of identical topology in one NumPy call (a fleet for Monte-Carlo campaigns).

Step structure, per control period ``dt_s``:

1. the cached Thevenin source (``e``, ``r``) of every cell at the start of the period, plus the
   balancers' internal currents, give each string's source voltage and resistance;
2. the bus is solved exactly (:mod:`packpilot.model.bus`) with the gates as commanded;
3. every cell advances with its constant current over the period;
4. the source is re-evaluated at the new state and cached (measurements read it).

The plant knows nothing of controllers: gates, charger requests, balancer and aux currents are
inputs set by whoever runs it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import BatteryConfig, ScenarioConfig
from packpilot.model import cell as cellmod
from packpilot.model import pack_kernel
from packpilot.model.bus import ChargerSource, LoadSink
from packpilot.model.bus_kernel import solve_bus_fast
from packpilot.model.cell.kernels import _tables, _thermal_coeffs
from packpilot.model.charger import ChargerModel, ChargerParams
from packpilot.model.switches import KIND_MOSFET, KIND_RELAY, diode_currents, switch_branches

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]


AUX_EMPTY_AH = 1e-6
"""An aux battery with at most this left in its weakest cell is empty: the BMU browns out."""


def _load_cell_set(name: str) -> cellmod.CellParams:
    if name.endswith((".json", ".toml", ".npz")) or "/" in name:
        return cellmod.load_parameter_file(Path(name))
    return cellmod.load_parameter_set(name)


def battery_series_ohm(b: BatteryConfig, params: cellmod.CellParams) -> float:
    """A battery's leads, connectors and shunt (issue #27): its stated ``series_ohm``, else its
    cell set's per series cell x series groups / cells per group. The one definition: the
    plant's branch and the state of power / join planner (``sim/power.py:params_of``) read it
    here, so a prediction cannot leave out what the plant puts in."""
    if b.series_ohm is not None:
        return float(b.series_ohm)
    return float(params.series_ohm) * b.series_groups / b.cells_per_group


def soc_from_ocv(params: cellmod.CellParams, ocv_v: Array, temp_c: Array) -> Array:
    """Invert the (monotone) OCV curve by bisection, clamped to SOC 0..1."""
    lo = np.zeros_like(ocv_v)
    hi = np.ones_like(ocv_v)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        above = cellmod.ocv_v(params, mid, temp_c) > ocv_v
        hi = np.where(above, mid, hi)
        lo = np.where(above, lo, mid)
    return 0.5 * (lo + hi)


def battery_base_soc(b: BatteryConfig, params: cellmod.CellParams, ambient_c: float) -> float:
    """A battery's initial SOC as configured, before any per-group or per-cell spread: its
    ``ocv0_v`` read through the OCV at the ambient, else its ``soc0``, else 0.5. The one
    definition: the plant starts its cells there, and the state of power's stated-resistance
    scale (``sim/power.py:resistance_scale``) reads R0 there."""
    if b.ocv0_v is not None:
        return float(soc_from_ocv(params, np.array([b.ocv0_v / b.n_cells]),
                                  np.array([ambient_c]))[0])  # fmt: skip
    return 0.5 if b.soc0 is None else float(b.soc0)


@dataclass
class CellBank:
    """Cells sharing one parameter set; ``idx`` maps them into the pack's flat cell axis."""

    params: cellmod.CellParams
    idx: IntArray
    state: cellmod.CellState
    base: cellmod.CellParams | None = None
    """The unmodified set, when ``params`` carries a fault (e.g. a cooling failure)."""


def _take(state: cellmod.CellState, m: BoolArray) -> cellmod.CellState:
    return cellmod.CellState(state.soc[m], state.eta_v[m], state.temp_c[m], state.jig_temp_c[m])


@dataclass
class Interval:
    """What flowed during the last period ``[t_s, t_s + dt_s]`` (arrays over packs)."""

    t_s: float
    dt_s: float
    bus_v: Array
    load_demand_a: Array
    load_a: Array
    supplied: BoolArray
    charger_v: Array
    charger_a: Array
    string_a: Array
    """(packs, strings), positive = discharge; the aux string's own current included."""
    battery_v: Array
    """(packs, strings) battery-side terminal voltage during the period."""
    cell_v: Array
    """(packs, cells) cell terminal voltage during the period."""
    group_v: Array
    """(packs, groups)."""
    chg_diode_a: Array
    dsg_diode_a: Array
    balancer_in_w: Array
    """(packs, strings) power drawn by the string's equalizers from the string."""
    heat_w: Array
    """(packs, strings) heat generated in the cells."""


@dataclass
class Pack:
    """Plant of ``n_packs`` identical-topology packs, built from a scenario config."""

    cfg: ScenarioConfig
    n_packs: int = 1
    capacity_scale: Array | None = None
    """Optional (packs,) or (packs, cells) factor on cell capacity (campaign spreads)."""
    r_scale: Array | None = None
    """Optional (packs,) or (packs, cells) factor on cell resistance."""
    soc_offset: Array | None = None
    """Optional (packs,) additive offset on initial SOC."""
    ambient_c: Array | None = None
    """Optional (packs,) ambient temperature override."""

    t_s: float = field(init=False, default=0.0)
    names: list[str] = field(init=False)
    banks: list[CellBank] = field(init=False)
    charger: ChargerModel = field(init=False)

    def __post_init__(self) -> None:
        pc = self.cfg.pack
        bats = pc.batteries
        self.names = [b.name for b in bats]
        n_s = len(bats)
        self.n_strings = n_s
        self.is_aux = np.array([b.role == "aux" for b in bats])
        self.aux_index: int | None = int(np.argmax(self.is_aux)) if self.is_aux.any() else None
        self._build_layout(bats)
        self._build_switches(bats)
        P = self.n_packs
        self.ambient = (
            np.full(P, pc.ambient_c)
            if self.ambient_c is None
            else np.asarray(self.ambient_c, float)
        )
        offsets = np.array([b.ambient_offset_c for b in bats])
        self.cell_ambient = self.ambient[:, None] + offsets[self.cell_string][None, :]

        rng = np.random.default_rng(pc.seed)
        self._build_cells(bats, rng)
        self.charger = ChargerModel(
            ChargerParams(
                rated_v=self.cfg.charger.rated_v,
                rated_a=self.cfg.charger.rated_a,
                r_out_ohm=self.cfg.charger.r_out_ohm,
                heartbeat_timeout_s=self.cfg.charger.heartbeat_timeout_s,
            ),
            P,
        )
        self.balancer_a = np.zeros((P, self.n_groups))
        self.aux_charge_a = np.zeros(P)
        self.bmu_on = np.ones(P, dtype=bool)
        """The BMU is powered (the aux battery above its cut-off); False: browned out."""
        self.bmu_changed = np.zeros(P, dtype=bool)
        """The BMU browned out or restarted at the last step."""
        self.bmu_min_v = np.full(P, np.inf)
        """Lowest aux terminal voltage seen (V)."""
        self.cell_a = np.zeros((P, self.n_cells))
        self.string_a = np.zeros((P, n_s))
        self.bus_v = np.zeros(P)
        self.group_v_prev = np.zeros((P, self.n_groups))
        # Diode stress ledgers, (packs, strings): conduction time and energy.
        self.chg_diode_s = np.zeros((P, n_s))
        self.dsg_diode_s = np.zeros((P, n_s))
        self.chg_diode_j = np.zeros((P, n_s))
        self.dsg_diode_j = np.zeros((P, n_s))
        self.charge_in_ah = np.zeros((P, n_s))
        self.joule_j = np.zeros((P, n_s))
        """Ohmic heat in cells and switches, (packs, strings)."""
        self._refresh_source()
        self.group_v_prev = self._group_sum(self.e_cell)

    # ------------------------------------------------------------------ construction
    def _build_layout(self, bats: list[BatteryConfig]) -> None:
        """Index arrays of the flat cell axis: battery-major, then group, then cell."""
        n_s = len(bats)
        n_cells = [b.n_cells for b in bats]
        self.cell_string = np.repeat(np.arange(n_s), n_cells)
        groups = [b.series_groups for b in bats]
        self.groups_per_string = tuple(groups)
        cell_group: list[int] = []
        g0 = 0
        for b in bats:
            for g in range(b.series_groups):
                cell_group += [g0 + g] * b.cells_per_group
            g0 += b.series_groups
        self.cell_group = np.array(cell_group, dtype=np.int64)
        self.n_cells = int(sum(n_cells))
        self.n_groups = int(sum(groups))
        self.group_starts = np.concatenate(
            [[0], np.cumsum([b.cells_per_group for b in bats for _ in range(b.series_groups)])[:-1]]
        )
        self.string_group_starts = np.concatenate([[0], np.cumsum(groups)[:-1]])
        self.max_groups = max(groups)
        self.string_cell_starts = np.concatenate([[0], np.cumsum(n_cells)[:-1]]).astype(np.int64)
        # (strings, max_groups) -> flat group index, -1 where a string has fewer groups.
        self.group_table = np.full((n_s, self.max_groups), -1, dtype=np.int64)
        for i, ng in enumerate(groups):
            self.group_table[i, :ng] = self.string_group_starts[i] + np.arange(ng)

    def _build_switches(self, bats: list[BatteryConfig]) -> None:
        """Each string's switch (its own, else the pack's) and its initial gates."""
        n_s = len(bats)
        sw = [b.switch or self.cfg.pack.switch for b in bats]
        self.sw_kind = np.array(
            [KIND_RELAY if s.kind == "relay" else KIND_MOSFET for s in sw], dtype=np.int64
        )
        self.sw_on_ohm = np.array([s.on_ohm for s in sw])
        self.sw_drop_v = np.array([s.diode_drop_v for s in sw])
        self.sw_diode_ohm = np.array([s.diode_ohm for s in sw])
        self.sw_rev_trip_a = np.array(
            [s.reverse_trip_a if s.reverse_comparator and s.kind != "relay" else np.inf for s in sw]
        )
        self.welded = np.array([s.welded and s.kind == "relay" for s in sw])
        P = self.n_packs
        self.chg_on = np.tile(np.array([s.chg_on for s in sw]), (P, 1))
        self.dsg_on = np.tile(np.array([s.dsg_on for s in sw]), (P, 1))
        self.fet_shorted = np.zeros((P, n_s, 2), dtype=bool)
        self.present_from_s = np.array([b.present_from_s for b in bats])

    def _build_cells(self, bats: list[BatteryConfig], rng: np.random.Generator) -> None:
        P, C = self.n_packs, self.n_cells
        pc = self.cfg.pack
        set_names = [b.cell or pc.cell for b in bats]
        cap = np.empty(C)
        rs = np.ones(C)
        soc = np.empty(C)
        params_of_string = {}
        for name in set(set_names):
            params_of_string[name] = _load_cell_set(name)
        start = 0
        for b, name in zip(bats, set_names, strict=True):
            prm = params_of_string[name]
            sl = slice(start, start + b.n_cells)
            nominal = b.capacity_ah if b.capacity_ah is not None else prm.capacity_ah
            gscale = np.repeat(
                np.array(b.group_capacity_scale or [1.0] * b.series_groups), b.cells_per_group
            )
            spread = rng.uniform(-b.cell_capacity_spread, b.cell_capacity_spread, b.n_cells)
            cap[sl] = nominal * gscale * (1.0 + spread)
            gsoc = np.repeat(
                np.array(b.group_soc0 if b.group_soc0 is not None else [np.nan] * b.series_groups),
                b.cells_per_group,
            )
            base = battery_base_soc(b, prm, pc.ambient_c)
            soc_spread = rng.uniform(-b.cell_soc_spread, b.cell_soc_spread, b.n_cells)
            soc[sl] = np.where(np.isnan(gsoc), base, gsoc) + soc_spread
            if b.resistance_ohm is not None:
                # The stated DC resistance holds at its reference temperature (a datasheet's or
                # an ohmmeter's, 25 degC by default) and the initial mean SOC, no current; at
                # another ambient the cells follow their set's temperature law from there (it
                # used to hold at the ambient: the same pack was no worse at -10 degC, #27).
                ref = cellmod.initial_state(
                    prm, 1, float(np.clip(soc[sl].mean(), 0, 1)), b.resistance_temp_c
                )
                _, r0 = cellmod.thevenin(prm, ref, np.zeros(1), np.array([nominal]), np.ones(1))
                rs[sl] = b.resistance_ohm / (b.n_cells * float(r0[0]))
            start += b.n_cells
        self.nominal_r_scale = rs.copy()
        """(cells,) each cell's resistance factor as the config states it (no campaign draw):
        what the BMS is told."""
        soc2 = self._per_pack(cap, rs, soc)
        self.banks = []
        string_of_cell = self.cell_string
        for name, prm in params_of_string.items():
            strings = [i for i, n in enumerate(set_names) if n == name]
            mask = np.isin(string_of_cell, strings)
            flat = (np.arange(P)[:, None] * C + np.nonzero(mask)[0][None, :]).ravel()
            state = cellmod.initial_state(
                prm, flat.size, soc2.ravel()[flat], self.cell_ambient.ravel()[flat]
            )
            self.banks.append(CellBank(params=prm, idx=flat, state=state))
        # Leads, connectors and shunt of each battery: in its branch, outside its cells (#27).
        self.series_ohm = np.array([
            battery_series_ohm(b, params_of_string[n]) for b, n in zip(bats, set_names, strict=True)
        ])  # fmt: skip
        self.cooling_scale = np.array([b.cooling_scale for b in bats])
        for i in np.flatnonzero(self.cooling_scale != 1.0):
            self.set_cooling(int(i), 1.0)
        self.v_min_cell = np.empty(C)
        self.v_max_cell = np.empty(C)
        for bank in self.banks:
            cells = bank.idx[: bank.idx.size // P] if P else bank.idx
            self.v_min_cell[cells] = bank.params.v_min_v
            self.v_max_cell[cells] = bank.params.v_max_v

    def _per_pack(self, cap: Array, rs: Array, soc: Array) -> Array:
        """Capacity and resistance scale of every pack's cells (the campaign's draws applied);
        returns the packs' initial cell SOC."""
        P = self.n_packs
        cap2 = np.tile(cap, (P, 1))
        if self.capacity_scale is not None:
            cap2 = cap2 * np.asarray(self.capacity_scale, float).reshape(P, -1)
        rs2 = np.tile(rs, (P, 1))
        if self.r_scale is not None:
            rs2 = rs2 * np.asarray(self.r_scale, float).reshape(P, -1)
        soc2 = np.tile(soc, (P, 1))
        if self.soc_offset is not None:
            soc2 = soc2 + np.asarray(self.soc_offset, float).reshape(P, 1)
        self.capacity_ah = cap2
        self.cell_r_scale = rs2
        return np.clip(soc2, 0.0, 1.0)

    # ------------------------------------------------------------------ helpers
    def _group_sum(self, x: Array) -> Array:
        return np.add.reduceat(x, self.group_starts, axis=1)

    def _string_sum_groups(self, g: Array) -> Array:
        return np.add.reduceat(g, self.string_group_starts, axis=1)

    def _refresh_source(self) -> None:
        """Thevenin source of every cell at the present state (looked up at the last current)."""
        P, C = self.n_packs, self.n_cells
        e = np.empty(P * C)
        r = np.empty(P * C)
        cap = self.capacity_ah.ravel()
        rs = self.cell_r_scale.ravel()
        ia = self.cell_a.ravel()
        for bank in self.banks:
            eb, rb = cellmod.thevenin(
                bank.params, bank.state, ia[bank.idx], cap[bank.idx], rs[bank.idx]
            )
            e[bank.idx] = eb
            r[bank.idx] = rb
        self.e_cell = e.reshape(P, C)
        self.r_cell = r.reshape(P, C)

    def present(self, t_s: float | None = None) -> BoolArray:
        t = self.t_s if t_s is None else t_s
        return np.broadcast_to(self.present_from_s <= t + 1e-12, (self.n_packs, self.n_strings))

    def charger_connected(self, t_s: float) -> BoolArray:
        return np.full(self.n_packs, self._charger_on(t_s))

    def _charger_on(self, t_s: float) -> bool:
        c = self.cfg.charger
        return c.present and t_s >= c.connect_s and (c.disconnect_s is None or t_s < c.disconnect_s)

    # ------------------------------------------------------------------ inputs
    def set_gates(self, chg_on: BoolArray, dsg_on: BoolArray) -> None:
        """Command the switches, shape (packs, strings)."""
        self.chg_on = np.array(chg_on, dtype=bool).reshape(self.n_packs, self.n_strings)
        self.dsg_on = np.array(dsg_on, dtype=bool).reshape(self.n_packs, self.n_strings)

    def effective_gates(self) -> tuple[BoolArray, BoolArray]:
        """Gates as the hardware really is: welded relays closed, shorted FETs on."""
        chg = self.chg_on | self.welded[None, :] | self.fet_shorted[:, :, 0]
        dsg = self.dsg_on | self.welded[None, :] | self.fet_shorted[:, :, 1]
        return chg, dsg

    def set_balancer(self, current_a: Array) -> None:
        """Equalizer current into each group, shape (packs, groups); clamped to the rating."""
        bc = self.cfg.balancer
        if not bc.present:
            self.balancer_a = np.zeros((self.n_packs, self.n_groups))
            return
        lo = -bc.max_current_a if bc.bidirectional else 0.0
        a = np.nan_to_num(np.asarray(current_a, float).reshape(self.n_packs, self.n_groups))
        self.balancer_a = np.clip(a, lo, bc.max_current_a)

    def set_aux_charge(self, current_a: Array) -> None:
        a = np.nan_to_num(np.asarray(current_a, float).reshape(self.n_packs))
        self.aux_charge_a = np.clip(a, 0.0, self.cfg.aux.dcdc_max_a)

    def set_cooling(self, string: int, factor: float) -> None:
        """Scale one battery's heat transfer to ambient (1 = healthy; a cooling failure < 1).

        The battery's cells move to a bank of their own whose thermal parameters carry the
        factor, so the fault touches no other battery that shares the cell set. The factor
        multiplies the battery's configured ``cooling_scale`` (airflow), so a fault and its end
        keep it.
        """
        factor = factor * float(self.cooling_scale[string])
        C = self.n_cells
        banks: list[CellBank] = []
        for bank in self.banks:
            m = self.cell_string[bank.idx % C] == string
            if not m.any():
                banks.append(bank)
                continue
            if (~m).any():
                banks.append(CellBank(bank.params, bank.idx[~m], _take(bank.state, ~m), bank.base))
            base = bank.base or bank.params
            th = base.thermal
            params = (
                base
                if factor == 1.0
                else dataclasses.replace(
                    base,
                    thermal=dataclasses.replace(th, jig_air_w_per_k=th.jig_air_w_per_k * factor),
                )
            )
            banks.append(
                CellBank(params, bank.idx[m], _take(bank.state, m), None if factor == 1.0 else base)
            )
        self.banks = banks

    # ------------------------------------------------------------------ step
    def _out(self, reuse: bool) -> dict[str, Any]:
        """Output arrays of one step: fresh, or one of two sets used in turn (``reuse``: the
        loop's fast path, where an :class:`Interval` is dead after the next step)."""
        if reuse:
            self._flip = 1 - getattr(self, "_flip", 0)
            sets = self.__dict__.setdefault("_sets", [None, None])
            if sets[self._flip] is None:
                sets[self._flip] = self._new_out()
            out: dict[str, Any] = sets[self._flip]
            return out
        return self._new_out()

    def _new_out(self) -> dict[str, Any]:
        P, S, C, G = self.n_packs, self.n_strings, self.n_cells, self.n_groups
        out: dict[str, Any] = {k: np.empty(P) for k in ("bus", "dem", "load", "cha", "ov", "chv")}
        out.update(sup=np.empty(P, dtype=bool), con=np.empty(P, dtype=bool))
        for k in ("sa", "bv", "cd", "dd", "pin", "hs"):
            out[k] = np.empty((P, S))
        for k in ("cv", "ca", "heat", "e", "r"):
            out[k] = np.empty((P, C))
        out["gv"] = np.empty((P, G))
        out["banks"] = [
            cellmod.CellState(
                np.empty(b.state.soc.shape[0]),
                np.empty((b.state.soc.shape[0], b.params.n_rc)),
                np.empty(b.state.soc.shape[0]),
                np.empty(b.state.soc.shape[0]),
            )
            for b in self.banks
        ]
        return out

    def step(self, dt_s: float, load_kind: str, load_value: Array, reuse: bool = False) -> Interval:
        """Solve the bus for the coming period, advance every cell, return the flows.

        Compiled (:mod:`packpilot.model.pack_kernel`): one kernel for the electrical part and
        the ledgers, one per cell bank for the cell model. Same results as
        :meth:`step_reference`, the readable NumPy version (``tests/test_pack_kernel.py``).
        ``reuse``: write into two alternating sets of arrays instead of fresh ones (the
        returned :class:`Interval` is then valid until the step after next).
        """
        h = float(dt_s)
        if not h > 0.0:
            raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
        P = self.n_packs
        t = self.t_s
        prm = self._kernel_params()
        ch = self.charger
        demand = np.asarray(load_value, np.float64).reshape(P)
        kind = pack_kernel.LOAD_KINDS.get(load_kind, pack_kernel.LOAD_NONE)
        ids = [id(b) for b in self.banks]
        if ids != getattr(self, "_bank_ids", None):  # banks re-made (a cooling fault): new sets
            self._bank_ids = ids
            self.__dict__.pop("_sets", None)
        o = self._out(reuse)
        bus_v, demand_a, load_a = o["bus"], o["dem"], o["load"]
        charger_a, out_v, charger_v = o["cha"], o["ov"], o["chv"]
        supplied, connected = o["sup"], o["con"]
        string_a, battery_v = o["sa"], o["bv"]
        chg_d, dsg_d, p_in = o["cd"], o["dd"], o["pin"]
        cell_v, cell_a = o["cv"], o["ca"]
        group_v = o["gv"]
        pack_kernel.pack_electrical(
            self.cell_string, self.cell_group, self.string_cell_starts, self.group_starts,
            self.string_group_starts, self.sw_kind, self.sw_on_ohm, self.series_ohm,
            self.sw_drop_v,
            self.sw_diode_ohm, self.sw_rev_trip_a, self.is_aux, self.present_from_s,
            -1 if self.aux_index is None else self.aux_index, prm, t, h, kind,
            self.chg_on, self.dsg_on, self.welded, self.fet_shorted, self.balancer_a,
            self.aux_input(), self.aux_draw_w(h), self.bus_v, self.group_v_prev, self.e_cell,
            self.r_cell,
            self._charger_on(t), ch.on_req, ch.last_request_s, ch.flags, ch.v_req, ch.i_req,
            demand, connected,
            bus_v, demand_a, load_a, supplied, charger_a, out_v, charger_v, string_a, battery_v,
            cell_v, cell_a, group_v, chg_d, dsg_d, p_in,
            self.chg_diode_s, self.dsg_diode_s, self.chg_diode_j, self.dsg_diode_j,
            self.charge_in_ah, self.joule_j,
        )  # fmt: skip
        heat, e_cell, r_cell = o["heat"], o["e"], o["r"]
        for bank, new in zip(self.banks, o["banks"], strict=True):
            st = bank.state
            pack_kernel.bank_cells(
                bank.idx, cell_a, self.cell_ambient, self.capacity_ah, self.cell_r_scale,
                st.soc, st.eta_v, st.temp_c, st.jig_temp_c,
                h, _thermal_coeffs(bank.params, h), *_tables(bank.params),
                new.soc, new.eta_v, new.temp_c, new.jig_temp_c, heat, e_cell, r_cell,
            )  # fmt: skip
            bank.state = new
        heat_string = o["hs"]
        pack_kernel.segment_sums(heat, self.string_cell_starts, heat_string)

        self.cell_a = cell_a
        self.string_a = string_a
        self.bus_v = bus_v
        self.group_v_prev = group_v
        ch.connected = connected
        ch.out_v = out_v
        ch.out_a = charger_a
        self.t_s = t + h
        self.e_cell = e_cell
        self.r_cell = r_cell
        self._bmu_supply(battery_v)
        return Interval(
            t_s=t,
            dt_s=dt_s,
            bus_v=bus_v,
            load_demand_a=demand_a,
            load_a=load_a,
            supplied=supplied,
            charger_v=charger_v,
            charger_a=charger_a,
            string_a=string_a,
            battery_v=battery_v,
            cell_v=cell_v,
            group_v=group_v,
            chg_diode_a=chg_d,
            dsg_diode_a=dsg_d,
            balancer_in_w=p_in,
            heat_w=heat_string,
        )

    def _kernel_params(self) -> Array:
        """Scalar parameters of the step kernel, cached while the config object is the same."""
        key = (self.cfg, self.charger.params)
        cached: tuple[tuple[object, object], Array] | None = self.__dict__.get("_kprm")
        if cached is not None and cached[0][0] is key[0] and cached[0][1] is key[1]:
            return cached[1]
        prm = np.empty(pack_kernel.N_PRM)
        prm[pack_kernel.P_BAL_EFF] = self.cfg.balancer.efficiency
        prm[pack_kernel.P_AUX_MIN_V] = self.cfg.aux.dcdc_min_input_v
        prm[pack_kernel.P_AUX_EFF] = self.cfg.aux.dcdc_efficiency
        prm[pack_kernel.P_AUX_BMS_W] = self.cfg.aux.bms_load_w
        prm[pack_kernel.P_LOAD_VMIN] = self.cfg.load.v_min_v
        prm[pack_kernel.P_CH_ROUT] = self.charger.params.r_out_ohm
        prm[pack_kernel.P_CH_TIMEOUT] = self.charger.params.heartbeat_timeout_s
        self._kprm = (key, prm)
        return prm

    def step_reference(self, dt_s: float, load_kind: str, load_value: Array) -> Interval:
        """Readable NumPy version of :meth:`step` (same contract and results; ~7x slower per pack).

        Solve the bus for the coming period, advance every cell, return the flows. The
        reverse-current comparator (``[pack.switch] reverse_comparator``) is modelled only in
        the kernel (:func:`pack_kernel.pack_electrical`); this reference refuses it.
        """
        if np.isfinite(self.sw_rev_trip_a).any():
            raise NotImplementedError(
                "step_reference does not model the reverse-current comparator; use step()"
            )
        P = self.n_packs
        t = self.t_s
        present = self.present(t) & ~self.is_aux[None, :]
        chg, dsg = self.effective_gates()
        # Balancer internal currents (explicit in the previous group voltages).
        bc = self.cfg.balancer
        gv = self.group_v_prev
        ib = self.balancer_a
        p_in = np.where(ib > 0.0, ib * gv / bc.efficiency, ib * gv * bc.efficiency)
        p_in_string = self._string_sum_groups(p_in)
        v_string_prev = np.maximum(self._string_sum_groups(gv), 1e-3)
        i_draw = p_in_string / v_string_prev
        x_cell = i_draw[:, self.cell_string] - ib[:, self.cell_group]

        aux_p_bus = self._aux_reference(gv, x_cell)

        e_string = np.add.reduceat(
            self.e_cell - self.r_cell * x_cell, self._string_starts(), axis=1
        )
        r_string = np.add.reduceat(self.r_cell, self._string_starts(), axis=1) + self.series_ohm
        br = switch_branches(
            self.sw_kind,
            self.sw_on_ohm,
            self.sw_drop_v,
            self.sw_diode_ohm,
            chg,
            dsg,
            present,
            r_string,
        )
        connected = self.charger_connected(t)
        self.charger.connected = connected
        ch_on = self.charger.output_enabled(t)
        chs = ChargerSource(
            enabled=ch_on,
            v_set=self.charger.v_req.copy(),
            i_lim=self.charger.i_req.copy(),
            r_out=np.full(P, self.charger.params.r_out_ohm),
        )
        demand = np.asarray(load_value, float).reshape(P)
        sol = solve_bus_fast(e_string, br, chs, self._load_sink(load_kind, demand, aux_p_bus))
        string_a = sol.string_a.copy()
        # The aux string's terminal current is its BMS load minus its DC/DC charge.
        cell_a = string_a[:, self.cell_string] + x_cell
        if self.aux_index is not None:
            string_a[:, self.aux_index] = cell_a[:, self.cell_string == self.aux_index][:, 0]
        cell_v = self.e_cell - self.r_cell * cell_a
        group_v = self._group_sum(cell_v)
        battery_v = np.add.reduceat(cell_v, self._string_starts(), axis=1)
        chg_d, dsg_d = diode_currents(self.sw_kind, chg, dsg, string_a)
        drop = self.sw_drop_v[None, :]
        self.chg_diode_s += dt_s * (chg_d > 0)
        self.dsg_diode_s += dt_s * (dsg_d > 0)
        self.chg_diode_j += dt_s * chg_d * (drop + chg_d * self.sw_diode_ohm)
        self.dsg_diode_j += dt_s * dsg_d * (drop + dsg_d * self.sw_diode_ohm)
        self.charge_in_ah += np.maximum(-string_a, 0.0) * dt_s / 3600.0
        heat_string = self._advance_cells_reference(cell_a, dt_s)
        # Ohmic (I^2 R) heat of the period: cell R0 plus switch path, and the RC branches'
        # share through the cell model's irreversible heat is not separable here, so count R0.
        self.joule_j += dt_s * np.add.reduceat(
            self.r_cell * cell_a**2, self._string_starts(), axis=1
        )

        self.cell_a = cell_a
        self.string_a = string_a
        self.bus_v = sol.bus_v
        self.group_v_prev = group_v
        # Charger telemetry: what it delivered over the period.
        self.charger.out_v = np.where(ch_on, sol.bus_v, 0.0)
        self.charger.out_a = sol.charger_a
        self.t_s = t + dt_s
        self._refresh_source()
        self._bmu_supply(battery_v)
        return Interval(
            t_s=t,
            dt_s=dt_s,
            bus_v=sol.bus_v,
            load_demand_a=self._demand_current(load_kind, demand, sol.bus_v),
            load_a=sol.load_a - aux_p_bus / np.maximum(sol.bus_v, 1e-6) * (sol.bus_v > 0),
            supplied=sol.supplied,
            charger_v=self.charger.out_v.copy(),
            charger_a=sol.charger_a,
            string_a=string_a,
            battery_v=battery_v,
            cell_v=cell_v,
            group_v=group_v,
            chg_diode_a=chg_d,
            dsg_diode_a=dsg_d,
            balancer_in_w=p_in_string,
            heat_w=heat_string,
        )

    def _aux_reference(self, gv: Array, x_cell: Array) -> Array:
        """Aux battery (step_reference): fed by its DC/DC from the bus, it powers the BMS. Adds
        its internal draw to ``x_cell``; returns the DC/DC's power from the bus (P,)."""
        aux_p_bus = np.zeros(self.n_packs)
        aux_cfg = self.cfg.aux
        if self.aux_index is not None:
            a = self.aux_index
            v_aux = np.maximum(
                gv[
                    :,
                    self.string_group_starts[a] : self.string_group_starts[a]
                    + self.groups_per_string[a],
                ].sum(axis=1),
                1e-3,
            )
            bus_ok = self.bus_v >= aux_cfg.dcdc_min_input_v
            i_aux_chg = np.where(bus_ok, self.aux_input(), 0.0)
            aux_p_bus = i_aux_chg * v_aux / aux_cfg.dcdc_efficiency
            x_cell[:, self.cell_string == a] += (self.aux_draw_w() / v_aux - i_aux_chg)[:, None]
        return aux_p_bus

    # ------------------------------------------------------------------ the BMU's supply
    @property
    def bmu_cutoff_v(self) -> float:
        """Aux terminal voltage below which the BMU browns out ([aux] bmu_cutoff_v, default
        the aux battery's series groups × its cell's v_min_v); inf without an aux battery."""
        if self.aux_index is None:
            return math.inf
        cut = self.cfg.aux.bmu_cutoff_v
        if cut is not None:
            return float(cut)
        a = self.aux_index
        first = int(np.nonzero(self.cell_string == a)[0][0])
        params = next(b.params for b in self.banks if np.any(b.idx % self.n_cells == first))
        bat = self.cfg.pack.batteries[a]
        return float(bat.series_groups * bat.cells_per_group * params.v_min_v)

    def aux_input(self) -> Array:
        """DC/DC current into the aux battery (P,): as commanded, but only through its closed
        relay (the source's module 140 feeds battery 230 through its own relay)."""
        if self.aux_index is None:
            return self.aux_charge_a
        a = self.aux_index
        closed = (self.chg_on[:, a] & self.dsg_on[:, a]) | self.welded[a]
        return np.where(closed, self.aux_charge_a, 0.0)

    def bmu_w(self) -> Array:
        """Power the BMU draws from the aux battery (P,): 0 while browned out, and 0 while the
        dock supplies it (``[aux] dock_powers_bmu``, the dock connected)."""
        on = self.bmu_on & ~self.dock_supplies_bmu()
        return np.where(on, self.cfg.aux.bms_load_w, 0.0)

    def dock_supplies_bmu(self, t_s: float | None = None) -> BoolArray:
        """(P,) the dock is connected and supplies the BMU and the aux path itself
        (``[aux] dock_powers_bmu``); at the plant's time by default."""
        if not self.cfg.aux.dock_powers_bmu or self.aux_index is None:
            return np.zeros(self.n_packs, dtype=bool)
        return self.charger_connected(self.t_s if t_s is None else t_s)

    @property
    def dock_aux_cv_v(self) -> float:
        """Voltage limit of the dock's aux path ([aux] dock_aux_cv_v, default the aux
        battery's series groups x its cell's v_max_v); NaN without an aux battery."""
        if self.aux_index is None:
            return math.nan
        cv = self.cfg.aux.dock_aux_cv_v
        if cv is not None:
            return float(cv)
        a = self.aux_index
        first = int(np.nonzero(self.cell_string == a)[0][0])
        params = next(b.params for b in self.banks if np.any(b.idx % self.n_cells == first))
        bat = self.cfg.pack.batteries[a]
        return float(bat.series_groups * bat.cells_per_group * params.v_max_v)

    def _aux_left_ah(self) -> Array:
        """(P,) charge left in the aux battery's weakest cell (Ah; NaN without one)."""
        if self.aux_index is None:
            return np.full(self.n_packs, np.nan)
        soc, _ = self.cell_states()
        cells = self.cell_string == self.aux_index
        left: Array = np.min(soc[:, cells] * self.capacity_ah[:, cells], axis=1)
        return left

    def aux_draw_w(self, dt_s: float = math.inf) -> Array:
        """Net power drawn from the aux battery's cells besides its DC/DC (P,; negative: into
        it): the BMU's load, less the dock's own charging path while the dock is connected.

        The aux battery never goes below empty (issue #24): the BMU's draw over a period of
        ``dt_s`` is capped at the charge its weakest cell has left (its protection cuts the
        load at empty, which the terminal-voltage brown-out alone missed: an LFP aux battery
        at SOC 0 still shows more than its cut-off, and the 15 W BMU ran it to -5 %)."""
        draw = self.bmu_w()
        if self.aux_index is None:
            return draw
        a = self.aux_index
        v_aux = np.maximum(self._string_sum_groups(self.group_v_prev)[:, a], 1e-3)
        if math.isfinite(dt_s) and dt_s > 0.0:
            left_ah = np.maximum(self._aux_left_ah() - 0.5 * AUX_EMPTY_AH, 0.0)  # rounding
            draw = np.minimum(draw, left_ah * 3600.0 / dt_s * v_aux)
        dock = self.dock_supplies_bmu()
        if dock.any():
            aux = self.cfg.aux
            taper = np.clip((self.dock_aux_cv_v - v_aux) / 0.2, 0.0, 1.0)
            draw = draw - np.where(dock, aux.dock_aux_charge_a * taper * v_aux, 0.0)
        return draw

    def _bmu_supply(self, battery_v: Array) -> None:
        """Brown-out and restart of the BMU from the aux terminal voltage at the end of the
        period. Browned out, every relay and FET drops to its unpowered (open) state (a welded
        relay or shorted FET stays as it is) and the aux DC/DC stops; the BMU restarts only
        above cut-off + hysteresis, with every switch still open."""
        if self.aux_index is None:
            return
        v = battery_v[:, self.aux_index]
        self._aux_v = v.copy()
        self.bmu_min_v = np.minimum(self.bmu_min_v, v)
        cut = self.bmu_cutoff_v
        dock = self.dock_supplies_bmu()
        empty = self._aux_left_ah() <= AUX_EMPTY_AH
        out = self.bmu_on & ~dock & ((v < cut) | empty)
        back = ~self.bmu_on & (dock | ((v >= cut + self.cfg.aux.bmu_recover_hysteresis_v) & ~empty))
        self.bmu_changed = out | back
        if not self.bmu_changed.any():
            return
        self.bmu_on = (self.bmu_on & ~out) | back
        self.hold_unpowered()

    def battery_v_aux(self) -> Array:
        """Aux terminal voltage at the end of the last step (P,); NaN before the first."""
        v: Array | None = self.__dict__.get("_aux_v")
        return np.full(self.n_packs, np.nan) if v is None else v

    def hold_unpowered(self) -> None:
        """Switches of a browned-out BMU stay open whatever was commanded."""
        off = ~self.bmu_on
        if off.any():
            self.chg_on[off] = False
            self.dsg_on[off] = False
            self.aux_charge_a = np.where(off, 0.0, self.aux_charge_a)

    def _load_sink(self, load_kind: str, demand: Array, aux_p_bus: Array) -> LoadSink:
        """The bus load (step_reference): the demand of ``load_kind`` plus the aux DC/DC."""
        P = self.n_packs
        zero = np.zeros(P)
        if load_kind == "current":
            return LoadSink(a=demand, g=zero, p=aux_p_bus, v_min=np.full(P, self.cfg.load.v_min_v))
        if load_kind == "power":
            return LoadSink(
                a=zero, g=zero, p=demand + aux_p_bus, v_min=np.full(P, self.cfg.load.v_min_v)
            )
        if load_kind == "resistance":
            g = np.where(demand > 0, 1.0 / np.maximum(demand, 1e-12), 0.0)
            return LoadSink(a=zero, g=g, p=aux_p_bus, v_min=np.full(P, self.cfg.load.v_min_v))
        return LoadSink(a=zero, g=zero, p=aux_p_bus, v_min=zero)

    def _advance_cells_reference(self, cell_a: Array, dt_s: float) -> Array:
        """Advance every cell with its constant current (step_reference); returns the heat
        per string (P, S)."""
        P = self.n_packs
        cap = self.capacity_ah.ravel()
        rs = self.cell_r_scale.ravel()
        amb = self.cell_ambient.ravel()
        ia = cell_a.ravel()
        heat = np.empty(P * self.n_cells)
        for bank in self.banks:
            bank.state, hb = cellmod.advance(
                bank.params,
                bank.state,
                ia[bank.idx],
                dt_s,
                amb[bank.idx],
                cap[bank.idx],
                rs[bank.idx],
            )
            heat[bank.idx] = hb
        return np.add.reduceat(heat.reshape(P, -1), self._string_starts(), axis=1)

    def _demand_current(self, kind: str, demand: Array, v: Array) -> Array:
        if kind == "current":
            return demand
        if kind == "power":
            return np.where(v > 0, demand / np.maximum(v, 1e-6), np.where(demand > 0, np.inf, 0.0))
        if kind == "resistance":
            return np.where(demand > 0, v / np.maximum(demand, 1e-12), 0.0)
        return np.zeros_like(demand)

    def _string_starts(self) -> IntArray:
        return self.string_cell_starts

    # ------------------------------------------------------------------ truth for sensors
    def cell_states(self) -> tuple[Array, Array]:
        """(soc, temp_c) of every cell, shape (packs, cells)."""
        P, C = self.n_packs, self.n_cells
        soc = np.empty(P * C)
        temp = np.empty(P * C)
        for bank in self.banks:
            soc[bank.idx] = bank.state.soc
            temp[bank.idx] = bank.state.temp_c
        return soc.reshape(P, C), temp.reshape(P, C)

    def cell_voltage_now(self) -> Array:
        """Cell terminal voltage at the present instant, under the last period's currents."""
        return self.e_cell - self.r_cell * self.cell_a
