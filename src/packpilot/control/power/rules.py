"""State of power and join planning, compiled: what the pack can hold for a horizon, and what
closing a switch onto the bus will cause.

Both questions are answered by one prediction: the batteries' equivalent circuits (EMF from
the SOC through the cell OCV table, ohmic resistance R0, one or two RC branches with their
present polarisation voltages) stepped over the horizon with the **same bus solve the plant
uses** (``model/bus.py``: every string behind its switch is a monotone piecewise-linear
source of the bus voltage, a relay or a MOSFET pair whose off FET still passes one direction
through its body diode). Each sub-step solves the bus exactly for the demanded pack current,
gives every battery its share, checks each battery against its own limits (cut-off and
maximum cell voltage, current limit, temperature limit) and advances its RC voltages exactly
for that constant current, its SOC and (adiabatically) its temperature. A pack current is
*holdable* for a horizon when no check fails; the state of power is the largest holdable
current, found by bisection (holdability is monotone in the current). Because the split is
predicted battery by battery, an aged battery limits the pack exactly as much as its share
of the current says, not ``N ×`` its own limit.

``control/`` cannot import the plant (``model/``), so the bus solve is written here again
for a constant-current load, without allocation (core kernels run without numba's runtime);
``tests/test_power.py`` checks it against ``model.bus_kernel.solve_bus_fast`` on random
packs (same breakpoints, same interpolation expression, same numbers).

Every input that describes the batteries' present state arrives in **one structure**,
:class:`PowerInputs` (per battery: SOC, capacity, temperature, R0, the RC branches and their
voltages, switch states, current limits). Today ``sim/power.py:inputs_from_core`` fills it
from the SOC method and the cell set; a model-based observer fills the same fields.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.jit import kernel

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

V_FLOOR = 1e-6
"""Lowest bus voltage the plant's solve considers (``model/bus.py``)."""

# Why a current cannot be held (``why_*`` outputs).
WHY_NONE = 0
WHY_CUTOFF = 1
"""A discharging battery's lowest cell fell below its cut-off (or a charging battery's
highest cell rose above its maximum)."""
WHY_CURRENT = 2
WHY_TEMP = 3
WHY_SUPPLY = 4
"""The connected batteries cannot carry the current at all (no bus voltage solves it)."""
WHY_NAMES = ("none", "cell voltage", "current limit", "temperature", "no path")


class PowerParams(NamedTuple):
    """Static facts: the cell OCV curve, each battery's series count, switch and limits."""

    ocv_soc: F64
    """(K,) strictly increasing SOC ..."""
    ocv_v: F64
    """(K,) ... and the cell OCV at each point."""
    series: F64
    """(B,) cells in series (the battery's EMF is ``series × cell OCV``)."""
    relay: B1
    """(B,) switched by a relay (else a MOSFET pair with body diodes)."""
    on_ohm: F64
    """(B,) relay contact, or one FET's channel resistance."""
    diode_drop_v: F64
    diode_ohm: F64
    series_ohm: F64
    """(B,) the battery's leads, connectors and current shunt (``series_ohm``, issue #27): in
    its branch with the switch, outside its cells, as the plant has it. It lowers the bus and
    shifts the split, but the cells' voltage (the cut-off), their heat and the RC branches do
    not see it, and it does not follow the cells' temperature, SOC or current laws."""
    cell_v_min: F64
    """(B,) cut-off cell voltage (the lowest cell of a discharging battery must stay above)."""
    cell_v_max: F64
    """(B,) highest cell voltage while charging."""
    temp_max_dsg_c: F64
    """(B,) temperature limit while discharging ..."""
    temp_max_chg_c: F64
    """(B,) ... and while charging."""
    temp_min_dsg_c: F64
    """(B,) lowest temperature for discharging ..."""
    temp_min_chg_c: F64
    """(B,) ... and for charging (a cold cell takes no charge)."""
    heat_j_per_k: F64
    """(B,) the battery's heat capacity ..."""
    cool_w_per_k: F64
    """(B,) ... and its conductance to its surroundings, held at the starting temperature
    (the jig warms far more slowly than a cell over 30 s)."""
    horizons_s: F64
    """(H,) the horizons, e.g. 2, 10, 30 s."""
    n_sub: int
    """Sub-steps per horizon."""
    iters: int
    """Bisection steps: the result is within ``2**-iters`` of the upper bound (the sum of the
    conducting batteries' limits, or their short-circuit currents) below the holdable
    current, never above it. 16 (the default; 30 before): evtol_charging's 10 s limit reads
    791.14 A against 791.32 A, 0.02 % low against the 2 % margin taken off anyway, for half
    the CPU (8.0 against 16.7 ms per publication, measured in one process)."""
    margin: float
    """Share taken off the largest holdable current before it is published (the
    prediction's error against the plant, ``docs/power.md``)."""


class PowerInputs(NamedTuple):
    """THE input structure of state of power and join planning: each battery's present state,
    shape (P, B). Whatever estimates the state (the SOC method and the cell set today, a
    model-based observer tomorrow) writes these fields and nothing else changes."""

    present: B1
    chg_on: B1
    """Switch feedback: charge path (relay: closed iff both)."""
    dsg_on: B1
    soc: F64
    capacity_ah: F64
    temp_c: F64
    r0_ohm: F64
    """The battery's ohmic resistance (cells only: the switch and the leads, connectors and
    shunt, ``PowerParams.series_ohm``, come from the params). An observer's R0 belongs here
    only if its voltage is read at the cells (the plant's is: the cell taps' sum)."""
    r1_ohm: F64
    tau1_s: F64
    v1_v: F64
    """Polarisation voltage of RC branch 1 (positive after discharging)."""
    r2_ohm: F64
    """0 for a one-RC model."""
    tau2_s: F64
    v2_v: F64
    emf_offset_v: F64
    """Added to ``series × cell OCV(SOC)`` (the table's reference temperature): the entropic
    shift at the battery's temperature, or an observer's EMF correction."""
    surround_c: F64
    """Temperature of what the cells lose heat to (their jig, the air; NaN: the cells' own
    starting temperature, i.e. no cooling until they warm)."""
    dudt_v_per_k: F64
    """The battery's EMF change per kelvin (entropic coefficient × cells): its EMF follows
    the predicted temperature, and ``-I·T·dU/dT`` of reversible heat enters the heating."""
    r_per_k: F64
    """d ln R / dT of R0, R1 and R2 at the present state (1/K; negative: a warming battery's
    resistance falls) ..."""
    r_per_soc: F64
    """... d ln R / d SOC (a discharging battery's resistance rises towards empty) ..."""
    r_per_a: F64
    """... and d ln R / d|I| (1/A); R0/R1/R2 are the values at zero current. All three 0
    hold the resistances constant over the horizon."""
    low_cell_v: F64
    """How far the lowest cell sits below the battery's average cell (V, >= 0)."""
    high_cell_v: F64
    """How far the highest cell sits above the average cell (V, >= 0)."""
    limit_dsg_a: F64
    """Discharge current limit (A, inf = none)."""
    limit_chg_a: F64
    """Charge current limit (A, positive, inf = none)."""


class PowerWork(NamedTuple):
    """Scratch of the prediction, (P, B) unless noted (allocated once, never by a kernel)."""

    soc: F64
    v1: F64
    v2: F64
    temp: F64
    r0: F64
    """R0 at the predicted temperature (the RC resistances scale with it)."""
    e: F64
    eoff: F64
    """Offset added to a battery's EMF: ``emf_offset_v``, plus the joining battery's dV."""
    cur: F64
    peak_pos: F64
    peak_neg: F64
    dok: B1
    ddrop: F64
    dohm: F64
    cok: B1
    cdrop: F64
    cohm: F64
    bus_lo: F64
    """(P,) lowest bus voltage over the last prediction."""
    bus_hi: F64
    why: I64
    """(P,) why the last failing prediction failed (``WHY_*``) ..."""
    who: I64
    """(P,) ... and which battery (-1: the pack)."""
    only: I64
    """(P,) the battery predicted alone (-1: all)."""


class PowerOut(NamedTuple):
    """State of power of P packs for each horizon (H)."""

    pack_dsg_a: F64
    """(P, H) largest pack discharge current holdable for the horizon."""
    pack_chg_a: F64
    """(P, H) largest pack charge current (positive)."""
    pack_dsg_w: F64
    """(P, H) that current times the lowest bus voltage on the way."""
    pack_chg_w: F64
    """(P, H) the charge current times the highest bus voltage on the way."""
    share_dsg_a: F64
    """(P, B, H) each battery's largest current while the pack draws its limit."""
    share_chg_a: F64
    alone_dsg_a: F64
    """(P, B, H) the largest current each battery could hold alone on the bus."""
    alone_chg_a: F64
    why_dsg: I64
    """(P, H) what stops the pack from drawing more (``WHY_*``) ..."""
    who_dsg: I64
    """(P, H) ... in which battery."""
    why_chg: I64
    who_chg: I64


# ------------------------------------------------------------------------------ battery


@kernel
def cell_ocv(prm: PowerParams, soc: float) -> float:
    """The cell OCV table at ``soc``, held at its end points."""
    xs, ys = prm.ocv_soc, prm.ocv_v
    n = xs.shape[0]
    if not soc > xs[0]:
        return float(ys[0])
    if soc >= xs[n - 1]:
        return float(ys[n - 1])
    k = 1
    while xs[k] <= soc:
        k += 1
    return float(ys[k - 1] + (ys[k] - ys[k - 1]) * (soc - xs[k - 1]) / (xs[k] - xs[k - 1]))


@kernel
def branches(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, only: int) -> None:
    """Each battery's two conduction branches, as ``model/switches.py:switch_branches``
    builds them for the plant (``only`` >= 0: that battery alone on the bus): its cells' R0
    plus its leads, connectors and shunt (``pack_kernel``'s ``r_s``), then the switch."""
    for s in range(inp.present.shape[1]):
        on = bool(inp.present[p, s]) and (only < 0 or only == s)
        chg = bool(inp.chg_on[p, s])
        dsg = bool(inp.dsg_on[p, s])
        r = wk.r0[p, s] + prm.series_ohm[s]
        if prm.relay[s]:
            closed = chg and dsg
            wk.dok[p, s] = on and closed
            wk.cok[p, s] = on and closed
            wk.ddrop[p, s] = 0.0
            wk.cdrop[p, s] = 0.0
            wk.dohm[p, s] = r + prm.on_ohm[s]
            wk.cohm[p, s] = r + prm.on_ohm[s]
        else:
            wk.dok[p, s] = on and dsg
            wk.cok[p, s] = on and chg
            wk.ddrop[p, s] = 0.0 if chg else prm.diode_drop_v[s]
            wk.cdrop[p, s] = 0.0 if dsg else prm.diode_drop_v[s]
            wk.dohm[p, s] = r + (prm.on_ohm[s] + (prm.on_ohm[s] if chg else prm.diode_ohm[s]))
            wk.cohm[p, s] = r + (prm.on_ohm[s] + (prm.on_ohm[s] if dsg else prm.diode_ohm[s]))


@kernel
def string_current(wk: PowerWork, p: int, s: int, v: float) -> float:
    """Battery ``s``'s current at bus voltage ``v`` (positive = discharging)."""
    x = 0.0
    if wk.dok[p, s]:
        d = (wk.e[p, s] - wk.ddrop[p, s] - v) / wk.dohm[p, s]
        if d > 0.0:
            x += d
    if wk.cok[p, s]:
        c = (wk.e[p, s] + wk.cdrop[p, s] - v) / wk.cohm[p, s]
        if c < 0.0:
            x += c
    return x


@kernel
def _sources(wk: PowerWork, p: int, v: float) -> float:
    """Total current the batteries deliver at bus voltage ``v`` (the plant's ``_sources``)."""
    tot = 0.0
    for s in range(wk.e.shape[1]):
        if wk.dok[p, s]:
            x = (wk.e[p, s] - wk.ddrop[p, s] - v) / wk.dohm[p, s]
            if x > 0.0:
                tot += x
        if wk.cok[p, s]:
            x = (wk.e[p, s] + wk.cdrop[p, s] - v) / wk.cohm[p, s]
            if x < 0.0:
                tot += x
    return tot


@kernel
def _breakpoint(wk: PowerWork, p: int, k: int, top: float) -> float:
    """Breakpoint ``k`` of the bus solve (2 per battery, then the floor and the top), floored
    at :data:`V_FLOOR` like the plant's; NaN where a branch does not conduct."""
    n = wk.e.shape[1]
    if k == 2 * n:
        return V_FLOOR
    if k == 2 * n + 1:
        return top
    s = k // 2
    if k % 2 == 0:
        if not wk.dok[p, s]:
            return math.nan
        x = wk.e[p, s] - wk.ddrop[p, s]
    else:
        if not wk.cok[p, s]:
            return math.nan
        x = wk.e[p, s] + wk.cdrop[p, s]
    return x if x >= V_FLOOR else V_FLOOR


@kernel
def bus_voltage(wk: PowerWork, p: int, load_a: float) -> float:
    """The bus voltage at which the batteries deliver ``load_a`` (negative: current pushed
    into them), NaN where none exists above :data:`V_FLOOR`.

    The plant's solve for a constant-current load: the residual ``S(V) - load`` is monotone
    non-increasing and linear between breakpoints; the root lies between the highest
    breakpoint with a positive residual and the next one above it, where it is interpolated
    with the plant's expression. Above the highest breakpoint only charge branches conduct,
    still linearly, so a charge current that needs more is extrapolated there."""
    n = wk.e.shape[1]
    hi = 0.0
    for s in range(n):
        if wk.dok[p, s]:
            hi = max(hi, abs(wk.e[p, s] - wk.ddrop[p, s]))
        if wk.cok[p, s]:
            hi = max(hi, abs(wk.e[p, s] + wk.cdrop[p, s]))
    top = 2.0 * hi + 10.0
    lo = -math.inf
    f_lo = 0.0
    for k in range(2 * n + 2):
        c = _breakpoint(wk, p, k, top)
        if c > lo:
            f = _sources(wk, p, c) - load_a
            if f > 0.0:
                lo = c
                f_lo = f
    if lo == -math.inf:
        return math.nan
    up = math.inf
    for k in range(2 * n + 2):
        c = _breakpoint(wk, p, k, top)
        if c > lo and c < up:
            up = c
    if up == math.inf:
        f1 = _sources(wk, p, lo + 1.0) - load_a
        if not f_lo > f1:
            return math.nan
        return lo + f_lo / (f_lo - f1)
    f_up = _sources(wk, p, up) - load_a
    v = lo + f_lo * (up - lo) / (f_lo - f_up) if f_lo != f_up else up
    return min(max(v, lo), up)


# ------------------------------------------------------------------------------ prediction


@kernel
def _decay(tau_s: float, h: float) -> float:
    return math.exp(-h / tau_s) if tau_s > 0.0 else 0.0


@kernel
def start(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, only: int) -> None:
    """Load the present state into the scratch and build the branches."""
    for s in range(inp.soc.shape[1]):
        wk.soc[p, s] = inp.soc[p, s]
        wk.v1[p, s] = inp.v1_v[p, s] if math.isfinite(inp.v1_v[p, s]) else 0.0
        wk.v2[p, s] = inp.v2_v[p, s] if math.isfinite(inp.v2_v[p, s]) else 0.0
        wk.temp[p, s] = inp.temp_c[p, s]
        wk.r0[p, s] = inp.r0_ohm[p, s]
        off = inp.emf_offset_v[p, s]
        wk.eoff[p, s] = off if math.isfinite(off) else 0.0
        wk.cur[p, s] = 0.0
        wk.peak_pos[p, s] = 0.0
        wk.peak_neg[p, s] = 0.0
    wk.bus_lo[p] = math.inf
    wk.bus_hi[p] = -math.inf
    wk.only[p] = only
    branches(prm, inp, wk, p, only)


@kernel
def _x(k: float, dx: float) -> float:
    return k * dx if math.isfinite(k) and k != 0.0 else 0.0


@kernel
def rescale(inp: PowerInputs, wk: PowerWork, p: int) -> None:
    """Resistances at the predicted temperature, SOC and the current just carried
    (log-linear in each: what the cell set's tables say about this state), as the plant
    looks its R0 up at the last period's current."""
    for s in range(inp.soc.shape[1]):
        e = _x(inp.r_per_k[p, s], wk.temp[p, s] - inp.temp_c[p, s])
        e += _x(inp.r_per_soc[p, s], wk.soc[p, s] - inp.soc[p, s])
        e += _x(inp.r_per_a[p, s], abs(wk.cur[p, s]))
        wk.r0[p, s] = inp.r0_ohm[p, s] * math.exp(e)


@kernel
def _entropic(inp: PowerInputs, wk: PowerWork, p: int, s: int) -> float:
    """EMF moved by the predicted warming."""
    return _x(inp.dudt_v_per_k[p, s], wk.temp[p, s] - inp.temp_c[p, s])


@kernel
def emf(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int) -> None:
    """Each battery's source voltage now: EMF from the SOC minus its polarisation."""
    for s in range(inp.soc.shape[1]):
        ocv = prm.series[s] * cell_ocv(prm, wk.soc[p, s]) + _entropic(inp, wk, p, s)
        wk.e[p, s] = ocv - wk.v1[p, s] - wk.v2[p, s] + wk.eoff[p, s]


@kernel
def _fail(wk: PowerWork, p: int, why: int, who: int) -> int:
    wk.why[p] = why
    wk.who[p] = who
    return why


@kernel
def advance(
    prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, s: int, cur: float, h: float
) -> int:
    """Battery ``s`` carries ``cur`` for ``h`` seconds: RC branches exactly, SOC, adiabatic
    heat; then its checks at the end of the step (where a constant current is worst)."""
    a1 = _decay(inp.tau1_s[p, s], h)
    a2 = _decay(inp.tau2_s[p, s], h)
    scale = wk.r0[p, s] / inp.r0_ohm[p, s]
    v1 = wk.v1[p, s]
    v2 = wk.v2[p, s]
    wk.v1[p, s] = wk.v1[p, s] * a1 + inp.r1_ohm[p, s] * scale * cur * (1.0 - a1)
    wk.v2[p, s] = wk.v2[p, s] * a2 + inp.r2_ohm[p, s] * scale * cur * (1.0 - a2)
    wk.soc[p, s] -= cur * h / (3600.0 * inp.capacity_ah[p, s])
    heat_w = cur * (cur * wk.r0[p, s] + 0.5 * (v1 + wk.v1[p, s]) + 0.5 * (v2 + wk.v2[p, s]))
    dudt = inp.dudt_v_per_k[p, s]
    if math.isfinite(dudt):
        heat_w -= cur * (wk.temp[p, s] + 273.15) * dudt
    around = inp.surround_c[p, s]
    if not math.isfinite(around):
        around = inp.temp_c[p, s]
    heat_w -= prm.cool_w_per_k[s] * (wk.temp[p, s] - around)
    if heat_w > 0.0 and prm.heat_j_per_k[s] > 0.0:
        wk.temp[p, s] += heat_w * h / prm.heat_j_per_k[s]
    ocv = prm.series[s] * cell_ocv(prm, wk.soc[p, s]) + _entropic(inp, wk, p, s)
    term = ocv - wk.v1[p, s] - wk.v2[p, s] + wk.eoff[p, s] - cur * wk.r0[p, s]
    cell = term / prm.series[s]
    if cur > 0.0 and cell - inp.low_cell_v[p, s] < prm.cell_v_min[s]:
        return _fail(wk, p, WHY_CUTOFF, s)
    if cur < 0.0 and cell + inp.high_cell_v[p, s] > prm.cell_v_max[s]:
        return _fail(wk, p, WHY_CUTOFF, s)
    if cur > 0.0 and wk.temp[p, s] > prm.temp_max_dsg_c[s]:
        return _fail(wk, p, WHY_TEMP, s)
    if cur < 0.0 and wk.temp[p, s] > prm.temp_max_chg_c[s]:
        return _fail(wk, p, WHY_TEMP, s)
    if cur > 0.0 and wk.temp[p, s] < prm.temp_min_dsg_c[s]:
        return _fail(wk, p, WHY_TEMP, s)
    if cur < 0.0 and wk.temp[p, s] < prm.temp_min_chg_c[s]:
        return _fail(wk, p, WHY_TEMP, s)
    return WHY_NONE


@kernel
def substep(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, load_a: float,
            h: float) -> int:  # fmt: skip
    """One sub-step: solve the bus, split the current, check and advance every battery."""
    emf(prm, inp, wk, p)
    v = bus_voltage(wk, p, load_a)
    if not math.isfinite(v):
        return _fail(wk, p, WHY_SUPPLY, -1)
    wk.bus_lo[p] = min(wk.bus_lo[p], v)
    wk.bus_hi[p] = max(wk.bus_hi[p], v)
    for s in range(inp.soc.shape[1]):
        cur = string_current(wk, p, s, v)
        wk.cur[p, s] = cur
        wk.peak_pos[p, s] = max(wk.peak_pos[p, s], cur)
        wk.peak_neg[p, s] = min(wk.peak_neg[p, s], cur)
        if cur > inp.limit_dsg_a[p, s] or -cur > inp.limit_chg_a[p, s]:
            return _fail(wk, p, WHY_CURRENT, s)
    for s in range(inp.soc.shape[1]):
        if wk.cur[p, s] != 0.0:
            why = advance(prm, inp, wk, p, s, wk.cur[p, s], h)
            if why != WHY_NONE:
                return why
    rescale(inp, wk, p)
    branches(prm, inp, wk, p, wk.only[p])
    return WHY_NONE


@kernel
def final_check(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int,
                load_a: float) -> int:  # fmt: skip
    """The split at the end of the horizon (it drifts as the RC branches charge), against
    the current limits."""
    emf(prm, inp, wk, p)
    v = bus_voltage(wk, p, load_a)
    if not math.isfinite(v):
        return _fail(wk, p, WHY_SUPPLY, -1)
    for s in range(inp.soc.shape[1]):
        cur = string_current(wk, p, s, v)
        wk.peak_pos[p, s] = max(wk.peak_pos[p, s], cur)
        wk.peak_neg[p, s] = min(wk.peak_neg[p, s], cur)
        if cur > inp.limit_dsg_a[p, s] or -cur > inp.limit_chg_a[p, s]:
            return _fail(wk, p, WHY_CURRENT, s)
    return WHY_NONE


@kernel
def hold(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, only: int, load_a: float,
         horizon_s: float) -> int:  # fmt: skip
    """Can pack ``p`` (or battery ``only`` alone) hold ``load_a`` for ``horizon_s``?
    ``WHY_NONE`` if so, else why not (and who, in ``wk.who``)."""
    start(prm, inp, wk, p, only)
    h = horizon_s / prm.n_sub
    for _ in range(prm.n_sub):
        why = substep(prm, inp, wk, p, load_a, h)
        if why != WHY_NONE:
            return why
    return final_check(prm, inp, wk, p, load_a)


@kernel
def _upper(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, only: int,
           sign: float) -> float:  # fmt: skip
    """A current no larger than which the answer lies: the sum of the conducting batteries'
    current limits, or of their short-circuit currents where a battery has none."""
    start(prm, inp, wk, p, only)
    hi = 0.0
    for s in range(inp.soc.shape[1]):
        ok = wk.dok[p, s] if sign > 0.0 else wk.cok[p, s]
        if not ok:
            continue
        lim = inp.limit_dsg_a[p, s] if sign > 0.0 else inp.limit_chg_a[p, s]
        if not math.isfinite(lim):
            ohm = wk.dohm[p, s] if sign > 0.0 else wk.cohm[p, s]
            lim = prm.series[s] * prm.ocv_v[prm.ocv_v.shape[0] - 1] / ohm
        hi += max(lim, 0.0)
    return hi


@kernel
def largest(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, only: int,
            horizon_s: float, sign: float) -> float:  # fmt: skip
    """The largest current (discharge for ``sign`` = 1, charge for -1) holdable for the
    horizon; ``wk.why``/``wk.who`` say what stops more. Bisection: holdability is monotone
    in the current (every battery's share grows with the pack current)."""
    hi = _upper(prm, inp, wk, p, only, sign)
    if not hi > 0.0:
        _fail(wk, p, WHY_SUPPLY, -1)
        return 0.0
    if hold(prm, inp, wk, p, only, sign * hi, horizon_s) == WHY_NONE:
        _fail(wk, p, WHY_CURRENT, -1)
        return hi
    why = wk.why[p]
    who = wk.who[p]
    lo = 0.0
    for _ in range(prm.iters):
        mid = 0.5 * (lo + hi)
        w = hold(prm, inp, wk, p, only, sign * mid, horizon_s)
        if w == WHY_NONE:
            lo = mid
        else:
            hi = mid
            why = w
            who = wk.who[p]
    wk.why[p] = why
    wk.who[p] = who
    return lo


ALONE_ALL = -1
"""``alone_k`` for each battery's own limits at every horizon ..."""
ALONE_NONE = -2
"""... and at none."""


@kernel
def sop_pack(prm: PowerParams, inp: PowerInputs, wk: PowerWork, out: PowerOut, p: int,
             alone_k: int) -> None:  # fmt: skip
    """State of power of pack ``p`` for every horizon, both directions; and what each battery
    could give or take on its own at horizon ``alone_k`` (every horizon: :data:`ALONE_ALL`;
    none: :data:`ALONE_NONE`; NaN where not computed: they are 2B of the 2B + 2 searches per
    horizon, which only the report and the dashboard show)."""
    n = inp.soc.shape[1]
    for k in range(prm.horizons_s.shape[0]):
        t = prm.horizons_s[k]
        for d in range(2):
            sign = 1.0 if d == 0 else -1.0
            i = largest(prm, inp, wk, p, -1, t, sign) * (1.0 - prm.margin)
            why = wk.why[p]
            who = wk.who[p]
            hold(prm, inp, wk, p, -1, sign * i, t)
            if d == 0:
                out.pack_dsg_a[p, k] = i
                out.pack_dsg_w[p, k] = i * wk.bus_lo[p] if i > 0.0 else 0.0
                out.why_dsg[p, k] = why
                out.who_dsg[p, k] = who
                for s in range(n):
                    out.share_dsg_a[p, s, k] = wk.peak_pos[p, s]
            else:
                out.pack_chg_a[p, k] = i
                out.pack_chg_w[p, k] = i * wk.bus_hi[p] if i > 0.0 else 0.0
                out.why_chg[p, k] = why
                out.who_chg[p, k] = who
                for s in range(n):
                    out.share_chg_a[p, s, k] = -wk.peak_neg[p, s]
        for s in range(n):
            if alone_k != ALONE_ALL and alone_k != k:
                out.alone_dsg_a[p, s, k] = math.nan
                out.alone_chg_a[p, s, k] = math.nan
                continue
            out.alone_dsg_a[p, s, k] = largest(prm, inp, wk, p, s, t, 1.0) * (1.0 - prm.margin)
            out.alone_chg_a[p, s, k] = largest(prm, inp, wk, p, s, t, -1.0) * (1.0 - prm.margin)


@kernel
def sop_packs(prm: PowerParams, inp: PowerInputs, wk: PowerWork, out: PowerOut,
              alone_k: int) -> None:  # fmt: skip
    """State of power of every pack (one implementation for P packs)."""
    for p in range(inp.soc.shape[0]):
        sop_pack(prm, inp, wk, out, p, alone_k)


# ------------------------------------------------------------------------------ joining


@kernel
def join_bus_v(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, j: int,
               load_a: float) -> float:  # fmt: skip
    """The bus voltage just before battery ``j`` joins (the others carry ``load_a``)."""
    start(prm, inp, wk, p, -1)
    wk.dok[p, j] = False
    wk.cok[p, j] = False
    emf(prm, inp, wk, p)
    return bus_voltage(wk, p, load_a)


@kernel
def join(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, j: int, load_a: float,
         dv: float, horizon_s: float, n_steps: int, limit_a: float) -> tuple[
             float, float, float, float]:  # fmt: skip
    """Battery ``j`` (its switch as ``inp`` gives it once closed) joins a bus held by the
    others at ``load_a``, its source voltage ``dv`` above the bus voltage before it closes
    (NaN: as its own state in ``inp`` says).

    Returns (peak current through its switch, signed, inf if the bus collapses, NaN if
    there is no bus to join; seconds above ``limit_a``; seconds
    until the current falls to half its peak; the current at the horizon). The peak is the
    first step's: the RC branches act as shorts at the instant of closing and then charge,
    so the current through the switch decays from there (towards the SOC balance, hours
    away)."""
    v0 = join_bus_v(prm, inp, wk, p, j, load_a)
    if not math.isfinite(v0):
        return math.nan, math.nan, math.nan, math.nan
    if not math.isnan(dv):
        wk.eoff[p, j] += v0 + dv - wk.e[p, j]
    branches(prm, inp, wk, p, -1)
    h = horizon_s / n_steps
    peak = 0.0
    over = 0.0
    half = math.nan
    cur = 0.0
    for k in range(n_steps):
        emf(prm, inp, wk, p)
        v = bus_voltage(wk, p, load_a)
        if not math.isfinite(v):
            peak = math.inf  # the bus collapses: nothing in the model bounds the current
            break
        for s in range(inp.soc.shape[1]):
            x = string_current(wk, p, s, v)
            wk.cur[p, s] = x
            wk.peak_pos[p, s] = max(wk.peak_pos[p, s], x)
            wk.peak_neg[p, s] = min(wk.peak_neg[p, s], x)
        cur = wk.cur[p, j]
        if abs(cur) > abs(peak):
            peak = cur
        if abs(cur) > limit_a:
            over += h
        if math.isnan(half) and k > 0 and abs(cur) <= 0.5 * abs(peak):
            half = k * h
        for s in range(inp.soc.shape[1]):
            if wk.cur[p, s] != 0.0:
                advance(prm, inp, wk, p, s, wk.cur[p, s], h)
        rescale(inp, wk, p)
        branches(prm, inp, wk, p, -1)
    return peak, over, half, cur


@kernel
def _join_ok(inp: PowerInputs, wk: PowerWork, p: int, j: int, peak: float,
             limit_a: float) -> bool:  # fmt: skip
    """The join's peak is within ``limit_a`` and every other battery's within its own
    current limits."""
    if not abs(peak) <= limit_a:
        return False
    for s in range(inp.soc.shape[1]):
        if s != j and (wk.peak_pos[p, s] > inp.limit_dsg_a[p, s]
                       or -wk.peak_neg[p, s] > inp.limit_chg_a[p, s]):  # fmt: skip
            return False
    return True


@kernel
def admissible_dv(prm: PowerParams, inp: PowerInputs, wk: PowerWork, p: int, j: int,
                  load_a: float, sign: float, limit_a: float, dv_max: float, n_steps: int,
                  iters: int) -> float:  # fmt: skip
    """The largest ``|dV|`` (joining battery above the bus for ``sign`` = 1, below for -1) whose
    peak current through the switch stays within ``limit_a`` and leaves every other battery
    within its own current limits; ``dv_max`` if any will do, 0 if none.
    Only the first steps matter for the peak, so each trial predicts 1 s."""
    pk, _o, _h, _c = join(prm, inp, wk, p, j, load_a, sign * dv_max, 1.0, n_steps, limit_a)
    if math.isnan(pk):
        return math.nan  # no bus to join
    if _join_ok(inp, wk, p, j, pk, limit_a):
        return dv_max
    lo = 0.0
    hi = dv_max
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        pk, _o, _h, _c = join(prm, inp, wk, p, j, load_a, sign * mid, 1.0, n_steps, limit_a)
        if _join_ok(inp, wk, p, j, pk, limit_a):
            lo = mid
        else:
            hi = mid
    return lo
