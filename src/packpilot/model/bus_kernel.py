"""The bus solve as compiled scalar loops (its readable NumPy reference,
:func:`packpilot.model.bus.solve_bus`, checks it in the tests).

The NumPy solver is the readable reference; this numba kernel is what the closed loop calls,
because a pack has only a handful of strings and NumPy's per-call overhead would dominate.
Both are tested against each other (``tests/test_bus_solve.py``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from packpilot.jit import kernel
from packpilot.model.bus import BusSolution, ChargerSource, LoadSink
from packpilot.model.switches import BranchArrays

_F = TypeVar("_F", bound=Callable[..., Any])
_V_FLOOR = 1e-6


_jit = kernel


@_jit
def _sources(
    v: Any,
    e: Any,
    dok: Any,
    ddrop: Any,
    dohm: Any,
    cok: Any,
    cdrop: Any,
    cohm: Any,
    ch_en: Any,
    vset: Any,
    ilim: Any,
    rout: Any,
) -> Any:
    tot = 0.0
    for s in range(e.size):
        if dok[s]:
            x = (e[s] - ddrop[s] - v) / dohm[s]
            if x > 0.0:
                tot += x
        if cok[s]:
            x = (e[s] + cdrop[s] - v) / cohm[s]
            if x < 0.0:
                tot += x
    if ch_en:
        x = (vset - v) / rout
        if x > ilim:
            x = ilim
        if x > 0.0:
            tot += x
    return tot


@_jit
def _segment(
    lo: Any,
    up: Any,
    e: Any,
    dok: Any,
    ddrop: Any,
    dohm: Any,
    cok: Any,
    cdrop: Any,
    cohm: Any,
    ch_en: Any,
    vset: Any,
    ilim: Any,
    rout: Any,
) -> Any:
    """Sources are linear inside a segment between breakpoints: S(V) = s0 + s1 V there."""
    mid = 0.5 * (lo + up)
    st = max(1e-3 * (up - lo), 1e-9)
    ta = _sources(mid, e, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, rout)
    tb = _sources(mid + st, e, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, rout)
    s1 = (tb - ta) / st
    return ta - s1 * mid, s1


@_jit
def _solve_one(
    e: Any,
    dok: Any,
    ddrop: Any,
    dohm: Any,
    cok: Any,
    cdrop: Any,
    cohm: Any,
    ch_en: Any,
    vset: Any,
    ilim: Any,
    rout: Any,
    a: Any,
    g: Any,
    p: Any,
    vmin: Any,
) -> Any:
    n = e.size
    bp = np.empty(2 * n + 5)
    m = 0
    hi = 0.0
    for s in range(n):
        if dok[s]:
            bp[m] = e[s] - ddrop[s]
            m += 1
            hi = max(hi, abs(e[s] - ddrop[s]))
        if cok[s]:
            bp[m] = e[s] + cdrop[s]
            m += 1
            hi = max(hi, abs(e[s] + cdrop[s]))
    if ch_en:
        bp[m] = vset
        bp[m + 1] = vset - ilim * rout
        m += 2
        hi = max(hi, abs(vset), abs(vset - ilim * rout))
    bp[m] = _V_FLOOR
    bp[m + 1] = 2.0 * hi + 10.0
    bp[m + 2] = vmin
    m += 3
    for k in range(m):
        if not (bp[k] >= _V_FLOOR):
            bp[k] = _V_FLOOR
    pts = np.sort(bp[:m])
    if p > 0.0:
        extra = np.empty(m - 1)
        for k in range(m - 1):
            lo = pts[k]
            up = pts[k + 1]
            s0, s1 = _segment(
                lo, up, e, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, rout
            )
            den = 2.0 * (s1 - g)
            vs = lo
            if den < 0.0:
                vs = (a - s0) / den
            extra[k] = min(max(vs, lo), up)
        pts = np.sort(np.concatenate((pts, extra)))
    K = pts.size
    f = np.empty(K)
    kk = -1
    for k in range(K):
        v = pts[k]
        f[k] = _sources(v, e, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, rout) - (
            a + g * v + p / v
        )
        if f[k] > 0.0:
            kk = k
    if kk < 0:
        return 0.0, False
    if kk > K - 2:
        kk = K - 2
    lo = pts[kk]
    up = pts[kk + 1]
    if p == 0.0:
        fl = f[kk]
        fu = f[kk + 1]
        v = lo + fl * (up - lo) / (fl - fu) if fl != fu else up
        return min(max(v, lo), up), True
    s0, s1 = _segment(lo, up, e, dok, ddrop, dohm, cok, cdrop, cohm, ch_en, vset, ilim, rout)
    qa = s1 - g
    qb = s0 - a
    qc = -p
    if qa != 0.0:
        disc = max(qb * qb - 4.0 * qa * qc, 0.0)
        v = (-qb - np.sqrt(disc)) / (2.0 * qa)
    elif qb != 0.0:
        v = -qc / qb
    else:
        v = up
    return min(max(v, lo), up), True


@_jit
def _solve_all(
    e: Any,
    dok: Any,
    ddrop: Any,
    dohm: Any,
    cok: Any,
    cdrop: Any,
    cohm: Any,
    ch_en: Any,
    vset: Any,
    ilim: Any,
    rout: Any,
    a: Any,
    g: Any,
    p: Any,
    vmin: Any,
) -> Any:
    P, S = e.shape
    bus = np.zeros(P)
    sa = np.zeros((P, S))
    ca = np.zeros(P)
    la = np.zeros(P)
    ok = np.ones(P, dtype=np.bool_)
    for i in range(P):
        ai, gi, pi, vm = a[i], g[i], p[i], vmin[i]
        demand = ai > 0.0 or gi > 0.0 or pi > 0.0
        v, root = _solve_one(
            e[i],
            dok[i],
            ddrop[i],
            dohm[i],
            cok[i],
            cdrop[i],
            cohm[i],
            ch_en[i],
            vset[i],
            ilim[i],
            rout[i],
            ai,
            gi,
            pi,
            vm,
        )
        if demand and not (root and v >= vm):
            ok[i] = False
            ai = 0.0
            gi = 0.0
            pi = 0.0
            v, root = _solve_one(
                e[i],
                dok[i],
                ddrop[i],
                dohm[i],
                cok[i],
                cdrop[i],
                cohm[i],
                ch_en[i],
                vset[i],
                ilim[i],
                rout[i],
                0.0,
                0.0,
                0.0,
                0.0,
            )
        if not root:
            v = 0.0
        bus[i] = v
        for s in range(S):
            x = 0.0
            if dok[i, s]:
                d = (e[i, s] - ddrop[i, s] - v) / dohm[i, s]
                if d > 0.0:
                    x += d
            if cok[i, s]:
                c = (e[i, s] + cdrop[i, s] - v) / cohm[i, s]
                if c < 0.0:
                    x += c
            sa[i, s] = x
        if ch_en[i]:
            c = (vset[i] - v) / rout[i]
            ca[i] = min(max(c, 0.0), ilim[i])
        if v > 0.0:
            la[i] = ai + gi * v + pi / max(v, _V_FLOOR)
    return bus, sa, ca, la, ok


def solve_bus_fast(
    e: NDArray[np.float64], br: BranchArrays, ch: ChargerSource, ld: LoadSink
) -> BusSolution:
    """Same contract as :func:`packpilot.model.bus.solve_bus`, compiled."""
    P, S = e.shape

    def f(x: Any) -> NDArray[np.float64]:
        return np.ascontiguousarray(np.broadcast_to(x, (P, S)), dtype=np.float64)

    def b(x: Any) -> NDArray[np.bool_]:
        return np.ascontiguousarray(np.broadcast_to(x, (P, S)), dtype=np.bool_)

    bus, sa, ca, la, ok = _solve_all(
        np.ascontiguousarray(e, dtype=np.float64),
        b(br.dsg_ok),
        f(br.dsg_drop_v),
        f(br.dsg_ohm),
        b(br.chg_ok),
        f(br.chg_drop_v),
        f(br.chg_ohm),
        np.ascontiguousarray(ch.enabled, dtype=np.bool_),
        np.asarray(ch.v_set, np.float64),
        np.asarray(ch.i_lim, np.float64),
        np.asarray(ch.r_out, np.float64),
        np.asarray(ld.a, np.float64),
        np.asarray(ld.g, np.float64),
        np.asarray(ld.p, np.float64),
        np.asarray(ld.v_min, np.float64),
    )
    return BusSolution(bus_v=bus, string_a=sa, charger_a=ca, load_a=la, supplied=ok)
