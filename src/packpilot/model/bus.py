"""Exact solve of the shared bus voltage, vectorized over packs.

Every source on the bus (each string behind its switch, the charger) delivers a current that is
a monotone non-increasing piecewise-linear function of the bus voltage V. The load draws
``a + g·V + p/V`` (constant current, resistance, constant power). Kirchhoff's current law,
``S(V) = L(V)``, is solved exactly: evaluate the residual at every breakpoint, pick the segment
that holds the highest root (the stable operating point of a constant-power load), and solve the
linear/quadratic equation inside it. No iteration, no tolerance.

If no root at or above the load's minimum operating voltage exists, the load is *unsupplied*
(an ESC or DC/DC drops out under-voltage): it is removed and the bus re-solved without it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from packpilot.model.switches import BranchArrays

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_V_FLOOR = 1e-6


@dataclass(frozen=True)
class ChargerSource:
    """CC/CV charger seen from the bus: I = clip((v_set - V)/r_out, 0, i_lim) when enabled."""

    enabled: BoolArray
    v_set: Array
    i_lim: Array
    r_out: Array


@dataclass(frozen=True)
class LoadSink:
    """Load current a + g·V + p/V, present only while V >= v_min."""

    a: Array
    g: Array
    p: Array
    v_min: Array


@dataclass(frozen=True)
class BusSolution:
    bus_v: Array
    string_a: Array
    charger_a: Array
    load_a: Array
    supplied: BoolArray
    """False where the load demanded power but could not be supplied."""


def _source_current(v: Array, e: Array, br: BranchArrays, ch: ChargerSource) -> tuple[Array, Array]:
    """String currents (P, K, S) and charger current (P, K) at bus voltages v (P, K)."""
    vv = v[..., None]
    ee = e[:, None, :]
    dsg = np.where(
        br.dsg_ok[:, None, :],
        np.maximum(0.0, (ee - br.dsg_drop_v[:, None, :] - vv) / br.dsg_ohm[:, None, :]),
        0.0,
    )
    chg = np.where(
        br.chg_ok[:, None, :],
        np.minimum(0.0, (ee + br.chg_drop_v[:, None, :] - vv) / br.chg_ohm[:, None, :]),
        0.0,
    )
    charger = np.where(
        ch.enabled[:, None],
        np.clip((ch.v_set[:, None] - v) / ch.r_out[:, None], 0.0, ch.i_lim[:, None]),
        0.0,
    )
    return dsg + chg, charger


def _breakpoints(e: Array, br: BranchArrays, ch: ChargerSource, ld: LoadSink) -> Array:
    """(P, K) sorted bus voltages between which every residual is one smooth piece."""
    n_packs = e.shape[0]
    # Breakpoints: string kinks, charger kinks, the load's minimum voltage, and the ends.
    kinks = [
        np.where(br.dsg_ok, e - br.dsg_drop_v, np.nan),
        np.where(br.chg_ok, e + br.chg_drop_v, np.nan),
        np.where(ch.enabled, ch.v_set, np.nan)[:, None],
        np.where(ch.enabled, ch.v_set - ch.i_lim * ch.r_out, np.nan)[:, None],
    ]
    hi = np.nanmax(
        np.concatenate([np.abs(k) for k in kinks] + [np.zeros((n_packs, 1))], axis=1), axis=1
    )
    ends = np.stack([np.full(n_packs, _V_FLOOR), 2.0 * hi + 10.0], axis=1)
    bp = np.concatenate([*kinks, ends, ld.v_min[:, None]], axis=1)
    bp = np.where(np.isfinite(bp) & (bp >= _V_FLOOR), bp, _V_FLOOR)
    bp.sort(axis=1)
    if np.any(ld.p > 0.0):
        # V·f(V) is a concave quadratic inside each segment; with a constant-power load the
        # residual can be positive only around its maximum, so add each segment's maximizer.
        lo_s, up_s = bp[:, :-1], bp[:, 1:]
        mid = 0.5 * (lo_s + up_s)
        step = np.maximum(1e-3 * (up_s - lo_s), 1e-9)
        s_a, c_a = _source_current(mid, e, br, ch)
        s_b, c_b = _source_current(mid + step, e, br, ch)
        tot_a = s_a.sum(axis=-1) + c_a
        s1 = (s_b.sum(axis=-1) + c_b - tot_a) / step
        s0 = tot_a - s1 * mid
        den = 2.0 * (s1 - ld.g[:, None])
        with np.errstate(divide="ignore", invalid="ignore"):
            vstar = np.where(den < 0.0, (ld.a[:, None] - s0) / den, lo_s)
        vstar = np.clip(np.nan_to_num(vstar, nan=_V_FLOOR), lo_s, up_s)
        bp = np.sort(np.concatenate([bp, vstar], axis=1), axis=1)
    return bp


def _solve(e: Array, br: BranchArrays, ch: ChargerSource, ld: LoadSink) -> tuple[Array, BoolArray]:
    n_packs = e.shape[0]
    bp = _breakpoints(e, br, ch, ld)

    def residual(v: Array) -> Array:
        s, c = _source_current(v, e, br, ch)
        out: Array = s.sum(axis=-1) + c - (ld.a[:, None] + ld.g[:, None] * v + ld.p[:, None] / v)
        return out

    f = residual(bp)
    pos = f > 0.0
    has_root = pos.any(axis=1)
    # Highest breakpoint with a positive residual: the root lies in the segment above it.
    k = bp.shape[1] - 1 - np.argmax(pos[:, ::-1], axis=1)
    k = np.minimum(k, bp.shape[1] - 2)
    rows = np.arange(n_packs)
    lo = bp[rows, k]
    up = bp[rows, k + 1]
    # Linear coefficients of the sources inside the segment: S(V) = s0 + s1 V.
    mid = 0.5 * (lo + up)
    probe = np.stack([mid, mid + np.maximum(1e-3 * (up - lo), 1e-9)], axis=1)
    s_probe, c_probe = _source_current(probe, e, br, ch)
    tot = s_probe.sum(axis=-1) + c_probe
    s1 = (tot[:, 1] - tot[:, 0]) / (probe[:, 1] - probe[:, 0])
    s0 = tot[:, 0] - s1 * probe[:, 0]
    # (s1 - g) V^2 + (s0 - a) V - p = 0; highest root in [lo, up].
    qa = s1 - ld.g
    qb = s0 - ld.a
    qc = -ld.p
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        disc = np.maximum(qb * qb - 4.0 * qa * qc, 0.0)
        sq = np.sqrt(disc)
        quad = np.where(qa != 0.0, (-qb - sq) / (2.0 * qa), np.nan)  # qa < 0: larger root
        lin = np.where(qb != 0.0, -qc / qb, up)
        v = np.where((qa != 0.0) & np.isfinite(quad), quad, lin)
        # Where the residual is linear and p == 0, interpolate exactly between breakpoints.
        f_lo = f[rows, k]
        f_up = f[rows, k + 1]
        interp = lo + f_lo * (up - lo) / (f_lo - f_up)
    v = np.where((ld.p == 0.0) & np.isfinite(interp), interp, v)
    v = np.clip(v, lo, up)
    return np.where(has_root, v, 0.0), np.asarray(has_root, dtype=bool)


def solve_bus(e: Array, br: BranchArrays, ch: ChargerSource, ld: LoadSink) -> BusSolution:
    """Bus voltage and every current, for ``e`` of shape (packs, strings)."""
    demand = (ld.a > 0.0) | (ld.g > 0.0) | (ld.p > 0.0)
    v, has_root = _solve(e, br, ch, ld)
    supplied = has_root & (v >= ld.v_min)
    drop = demand & ~supplied
    if drop.any():
        zero = np.zeros_like(ld.a)
        ld2 = LoadSink(
            a=np.where(drop, 0.0, ld.a),
            g=np.where(drop, 0.0, ld.g),
            p=np.where(drop, 0.0, ld.p),
            v_min=np.where(drop, zero, ld.v_min),
        )
        v2, _ = _solve(e, br, ch, ld2)
        v = np.where(drop, v2, v)
        ld = ld2
    s, c = _source_current(v[:, None], e, br, ch)
    string_a = s[:, 0, :]
    charger_a = c[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        load_a = np.where(v > 0.0, ld.a + ld.g * v + ld.p / np.maximum(v, _V_FLOOR), 0.0)
    # Nothing connected and no load: the bus floats; report the charger/strings' view of 0 V.
    return BusSolution(
        bus_v=v,
        string_a=string_a,
        charger_a=charger_a,
        load_a=load_a,
        supplied=supplied | ~demand,
    )
