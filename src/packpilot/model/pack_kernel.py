"""The plant step as compiled scalar loops (its readable NumPy reference,
:meth:`packpilot.model.pack.Pack.step_reference`, checks it in the tests).

A pack has a handful of strings and a few dozen cells, so the NumPy step is dominated by
per-call overhead (~50 array operations of ~1 µs each). These kernels do the same arithmetic in
plain loops, in the same order, so the results match the NumPy reference bit for bit where it
matters (tests/test_pack_kernel.py steps both side by side):

* sums over segments reproduce NumPy's own order (``np.add.reduceat`` and ``ndarray.sum`` use
  pairwise summation in blocks of 8), see :mod:`packpilot.model.numerics`;
* the bus is solved by the very compiled function the NumPy step calls
  (:func:`packpilot.model.bus_kernel._solve_one`);
* cells advance through the cell model's own kernels (``_advance_kernel``,
  ``_thevenin_kernel``), called from compiled code, so their fused multiply-adds (written
  ``fma(a, b, c)``, :mod:`packpilot.model.fma`) and results are unchanged.

No fastmath here: every operation is the IEEE operation NumPy performs. The on-disk cache of
these kernels is keyed by everything they import (:mod:`packpilot.jit`), so editing the cell
model or the bus solve recompiles them.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from packpilot.jit import kernel
from packpilot.model.bus_kernel import _V_FLOOR, _solve_one
from packpilot.model.cell.kernels import _advance_kernel, _thevenin_kernel
from packpilot.model.charger import FLAG_NAMES
from packpilot.model.numerics import segment_sum, short_sum
from packpilot.model.switches import KIND_MOSFET, KIND_RELAY

LOAD_KINDS: dict[str, int] = {"current": 0, "power": 1, "resistance": 2}
"""Load kind codes of the kernel; any other kind (``"none"``) is code 3: no load."""
LOAD_NONE = 3

# Indices into the ``prm`` vector of scalar parameters passed to :func:`pack_electrical`.
P_BAL_EFF, P_AUX_MIN_V, P_AUX_EFF, P_AUX_BMS_W, P_LOAD_VMIN, P_CH_ROUT, P_CH_TIMEOUT = range(7)
N_PRM = 7
# P_AUX_BMS_W stays in the vector (the config's value) but the kernel reads the BMU's power per
# pack from ``bmu_w`` (0 while that pack's BMU is browned out, Pack.bmu_w).
_TIMEOUT_FLAG = FLAG_NAMES.index("communication_timeout")


@kernel
def _npmax(a: float, b: float) -> float:
    """``np.maximum`` on scalars: NaN propagates (Python's ``max`` would drop it)."""
    if a >= b or a != a:
        return a
    return b


@kernel
def segment_sums(x: Any, starts: Any, out: Any) -> None:
    """``out[:] = np.add.reduceat(x, starts, axis=1)`` for a 2-D ``x``."""
    for p in range(x.shape[0]):
        row = x[p]
        for k in range(starts.size):
            out[p, k] = segment_sum(row, starts, k)


@kernel
def pack_electrical(
    cell_string: Any,
    cell_group: Any,
    cell_starts: Any,
    group_starts: Any,
    string_group_starts: Any,
    sw_kind: Any,
    sw_on_ohm: Any,
    series_ohm: Any,
    sw_drop_v: Any,
    sw_diode_ohm: Any,
    sw_rev_trip_a: Any,
    is_aux: Any,
    present_from_s: Any,
    aux_index: int,
    prm: Any,
    t: float,
    dt: float,
    load_kind: int,
    chg_on: Any,
    dsg_on: Any,
    welded: Any,
    fet_shorted: Any,
    ib: Any,
    aux_charge_a: Any,
    bmu_w: Any,
    bus_prev: Any,
    gv: Any,
    e_cell: Any,
    r_cell: Any,
    ch_connected: bool,
    on_req: Any,
    last_request_s: Any,
    flags: Any,
    v_req: Any,
    i_req: Any,
    demand: Any,
    connected: Any,
    bus_v: Any,
    load_demand_a: Any,
    load_a: Any,
    supplied: Any,
    charger_a: Any,
    out_v: Any,
    charger_v: Any,
    string_a: Any,
    battery_v: Any,
    cell_v: Any,
    cell_a: Any,
    group_v: Any,
    chg_d: Any,
    dsg_d: Any,
    p_in_string: Any,
    chg_diode_s: Any,
    dsg_diode_s: Any,
    chg_diode_j: Any,
    dsg_diode_j: Any,
    charge_in_ah: Any,
    joule_j: Any,
) -> None:
    """Everything of a plant step except the cell model, for every pack.

    Inputs are the plant's attributes at the start of the period; the outputs (fresh arrays)
    receive the period's flows; the diode, charge and joule ledgers and the charger's timeout
    flag are updated in place. Mirrors ``Pack.step_reference`` (and
    ``ChargerModel.output_enabled``) line by line.
    """
    P, S = chg_on.shape
    C = cell_string.size
    G = group_starts.size
    bal_eff = prm[P_BAL_EFF]
    ch_rout = prm[P_CH_ROUT]
    # Per-pack scratch for the branch description handed to the bus solve.
    e_s = np.empty(S)
    r_s = np.empty(S)
    dok = np.empty(S, dtype=np.bool_)
    cok = np.empty(S, dtype=np.bool_)
    ddrop = np.empty(S)
    cdrop = np.empty(S)
    dohm = np.empty(S)
    cohm = np.empty(S)
    chg = np.empty(S, dtype=np.bool_)
    dsg = np.empty(S, dtype=np.bool_)
    p_in = np.empty(G)
    i_draw = np.empty(S)
    x_cell = np.empty(C)
    src = np.empty(C)
    jl = np.empty(C)
    for p in range(P):
        gvp = gv[p]
        # Balancer internal currents, explicit in the previous group voltages.
        for g in range(G):
            x = ib[p, g]
            p_in[g] = x * gvp[g] / bal_eff if x > 0.0 else x * gvp[g] * bal_eff
        for s in range(S):
            p_in_string[p, s] = segment_sum(p_in, string_group_starts, s)
            i_draw[s] = p_in_string[p, s] / _npmax(segment_sum(gvp, string_group_starts, s), 1e-3)
        for c in range(C):
            x_cell[c] = i_draw[cell_string[c]] - ib[p, cell_group[c]]
        # Aux battery: fed by its DC/DC from the bus (``aux_charge_a``: 0 unless its relay is
        # closed, Pack.aux_input); powers the BMU (``bmu_w``: 0 while browned out).
        aux_p_bus = 0.0
        if aux_index >= 0:
            g0 = string_group_starts[aux_index]
            g1 = string_group_starts[aux_index + 1] if aux_index + 1 < S else G
            v_aux = _npmax(short_sum(gvp, g0, g1 - g0), 1e-3)
            i_aux = aux_charge_a[p] if bus_prev[p] >= prm[P_AUX_MIN_V] else 0.0
            aux_p_bus = i_aux * v_aux / prm[P_AUX_EFF]
            extra = bmu_w[p] / v_aux - i_aux
            for c in range(C):
                if cell_string[c] == aux_index:
                    x_cell[c] += extra
        # String sources and switch branches.
        for c in range(C):
            src[c] = e_cell[p, c] - r_cell[p, c] * x_cell[c]
        er = e_cell[p]
        rr = r_cell[p]
        for s in range(S):
            e_s[s] = segment_sum(src, cell_starts, s)
            # the battery's leads, connectors and shunt: in its branch, heating no cell
            r_s[s] = segment_sum(rr, cell_starts, s) + series_ohm[s]
            present = present_from_s[s] <= t + 1e-12 and not is_aux[s]
            cg = chg_on[p, s] or welded[s] or fet_shorted[p, s, 0]
            dg = dsg_on[p, s] or welded[s] or fet_shorted[p, s, 1]
            chg[s] = cg
            dsg[s] = dg
            on = sw_on_ohm[s]
            if sw_kind[s] == KIND_RELAY:
                closed = cg and dg and present
                dok[s] = closed
                cok[s] = closed
                ddrop[s] = 0.0
                cdrop[s] = 0.0
                dohm[s] = r_s[s] + on
                cohm[s] = r_s[s] + on
            else:
                dok[s] = dg and present
                cok[s] = cg and present
                ddrop[s] = 0.0 if cg else sw_drop_v[s]
                cdrop[s] = 0.0 if dg else sw_drop_v[s]
                dohm[s] = r_s[s] + (on + (on if cg else sw_diode_ohm[s]))
                cohm[s] = r_s[s] + (on + (on if dg else sw_diode_ohm[s]))
        # Load seen by the bus (the aux DC/DC is a constant-power draw on it).
        dem = demand[p]
        la, lg, lp, vm = 0.0, 0.0, aux_p_bus, prm[P_LOAD_VMIN]
        if load_kind == 0:
            la = dem
        elif load_kind == 1:
            lp = dem + aux_p_bus
        elif load_kind == 2:
            lg = 1.0 / _npmax(dem, 1e-12) if dem > 0 else 0.0
        else:
            vm = 0.0
        # Charger output: ChargerModel.output_enabled (heartbeat timeout, fault flags).
        connected[p] = ch_connected
        timeout = (t - last_request_s[p]) > prm[P_CH_TIMEOUT]
        flags[p, _TIMEOUT_FLAG] = timeout and ch_connected
        faulted = False
        for f in range(flags.shape[1]):
            if f != _TIMEOUT_FLAG and flags[p, f]:
                faulted = True
        ch_en = ch_connected and on_req[p] and not timeout and not faulted and i_req[p] > 0.0
        # Bus solve: as bus_kernel._solve_all, one pack. A fitted reverse-current comparator
        # (ideal-diode controller on the charge FET, armed while no charger output is on) that
        # sees more than its trip current flowing into its battery opens that charge FET within
        # the step: the string is solved again with the charge path blocked (the body diode
        # still lets the battery discharge). Each pass trips at least one more string.
        vset = v_req[p]
        ilim = i_req[p]
        want = la > 0.0 or lg > 0.0 or lp > 0.0
        la0, lg0, lp0 = la, lg, lp
        v = 0.0
        ok = True
        for _ in range(S + 1):
            la, lg, lp = la0, lg0, lp0
            v, root = _solve_one(
                e_s, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, ch_rout, la, lg, lp,
                vm,
            )  # fmt: skip
            ok = True
            if want and not (root and v >= vm):
                ok = False
                la = 0.0
                lg = 0.0
                lp = 0.0
                v, root = _solve_one(
                    e_s, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, ch_rout,
                    0.0, 0.0, 0.0, 0.0,
                )  # fmt: skip
            if not root:
                v = 0.0
            tripped = False
            if not ch_en:
                for s in range(S):
                    if not (cok[s] and chg[s] and sw_kind[s] == KIND_MOSFET):
                        continue
                    if welded[s] or fet_shorted[p, s, 0] or not chg_on[p, s]:
                        continue
                    q = (e_s[s] + cdrop[s] - v) / cohm[s]
                    if q < -sw_rev_trip_a[s]:
                        tripped = True
                        chg[s] = False
                        cok[s] = False
                        ddrop[s] = sw_drop_v[s]
                        dohm[s] = r_s[s] + (sw_on_ohm[s] + sw_diode_ohm[s])
            if not tripped:
                break
        bus_v[p] = v
        supplied[p] = ok
        for s in range(S):
            x = 0.0
            if dok[s]:
                d = (e_s[s] - ddrop[s] - v) / dohm[s]
                if d > 0.0:
                    x += d
            if cok[s]:
                q = (e_s[s] + cdrop[s] - v) / cohm[s]
                if q < 0.0:
                    x += q
            string_a[p, s] = x
        ca = 0.0
        if ch_en:
            q = (vset - v) / ch_rout
            ca = min(max(q, 0.0), ilim)
        charger_a[p] = ca
        lv = 0.0
        if v > 0.0:
            lv = la + lg * v + lp / max(v, _V_FLOOR)
        load_a[p] = lv - aux_p_bus / _npmax(v, 1e-6) * (1.0 if v > 0 else 0.0)
        ov = v if ch_en else 0.0
        out_v[p] = ov
        charger_v[p] = ov
        if load_kind == 0:
            load_demand_a[p] = dem
        elif load_kind == 1:
            if v > 0:
                load_demand_a[p] = dem / _npmax(v, 1e-6)
            else:
                load_demand_a[p] = np.inf if dem > 0 else 0.0
        elif load_kind == 2:
            load_demand_a[p] = v / _npmax(dem, 1e-12) if dem > 0 else 0.0
        else:
            load_demand_a[p] = 0.0
        # Cell currents and voltages; the aux string's terminal current is its own cells'.
        cap = cell_a[p]
        cvp = cell_v[p]
        for c in range(C):
            cap[c] = string_a[p, cell_string[c]] + x_cell[c]
            cvp[c] = er[c] - rr[c] * cap[c]
            jl[c] = rr[c] * (cap[c] * cap[c])
        if aux_index >= 0:
            string_a[p, aux_index] = cap[cell_starts[aux_index]]
        for g in range(G):
            group_v[p, g] = segment_sum(cvp, group_starts, g)
        # Diodes and ledgers.
        for s in range(S):
            battery_v[p, s] = segment_sum(cvp, cell_starts, s)
            cur = string_a[p, s]
            mos = sw_kind[s] == KIND_MOSFET
            cd = cur if (mos and not chg[s] and cur > 0.0) else 0.0
            dd = -cur if (mos and not dsg[s] and cur < 0.0) else 0.0
            chg_d[p, s] = cd
            dsg_d[p, s] = dd
            drop = sw_drop_v[s]
            dohm_s = sw_diode_ohm[s]
            chg_diode_s[p, s] += dt * (1.0 if cd > 0 else 0.0)
            dsg_diode_s[p, s] += dt * (1.0 if dd > 0 else 0.0)
            chg_diode_j[p, s] += dt * cd * (drop + cd * dohm_s)
            dsg_diode_j[p, s] += dt * dd * (drop + dd * dohm_s)
            charge_in_ah[p, s] += _npmax(-cur, 0.0) * dt / 3600.0
            joule_j[p, s] += dt * segment_sum(jl, cell_starts, s)


@kernel
def bank_cells(
    idx: Any,
    cell_a: Any,
    ambient: Any,
    capacity: Any,
    r_scale: Any,
    soc: Any,
    eta: Any,
    tc: Any,
    tj: Any,
    h: float,
    th: Any,
    flat: Any,
    ax_t: Any,
    ax_i: Any,
    ax_s: Any,
    ocv_x: Any,
    ocv_y: Any,
    du_x: Any,
    du_t: Any,
    du_y: Any,
    fmeta: Any,
    imeta: Any,
    soc_o: Any,
    eta_o: Any,
    tc_o: Any,
    tj_o: Any,
    heat: Any,
    e_cell: Any,
    r_cell: Any,
) -> None:
    """Advance one bank's cells and refresh their Thevenin source, scattering into the pack.

    ``idx`` are flat (pack * cells + cell) indices into the (packs, cells) arrays; the new
    state goes to ``*_o``; ``heat``, ``e_cell``, ``r_cell`` receive the bank's cells.
    The same two cell-model kernels as ``cell.advance`` and ``cell.thevenin`` do the work.
    """
    n = idx.size
    C = cell_a.shape[1]
    cur = np.empty(n)
    ta = np.empty(n)
    cap = np.empty(n)
    rs = np.empty(n)
    for k in range(n):
        p = idx[k] // C
        c = idx[k] - p * C
        cur[k] = cell_a[p, c]
        ta[k] = ambient[p, c]
        cap[k] = capacity[p, c]
        rs[k] = r_scale[p, c]
    q = np.empty(n)
    _advance_kernel(
        soc, eta, tc, tj, cur, ta, cap, rs, h, th,
        flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        soc_o, eta_o, tc_o, tj_o, q,
    )  # fmt: skip
    e = np.empty(n)
    r = np.empty(n)
    _thevenin_kernel(
        soc_o, eta_o, tc_o, cur, rs,
        flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        e, r,
    )  # fmt: skip
    for k in range(n):
        p = idx[k] // C
        c = idx[k] - p * C
        heat[p, c] = q[k]
        e_cell[p, c] = e[k]
        r_cell[p, c] = r[k]
