"""A battery stepped over a logged profile: variable time steps, the sampled current for the
resistive drop and the RC branches, the charge counter for the state of charge.

A flight log is not a simulation input: its samples come at the logger's times (1 Hz, 10 Hz,
with gaps), its current is a sample, not the average over the interval, and the autopilot's
own charge counter (PX4 ``discharged_mah``, ArduPilot ``CurrTot``) integrates the current at
its sensor rate, far better than the samples can. So the state of charge is read from that
counter when the log has one (else from the sampled current, rectangle rule), and each RC
branch takes the sample's current as held over the interval before it — the convention of
:func:`packpilot.model.cell.simulate_current`, where ``current_a[k]`` is the current behind
``voltage_v[k]``, so on a plant-made log the stepper is exact.

Per cell, with ``I`` the cell current (battery current / parallel count, + = discharge)::

    soc_k  = soc0 - Ah_k / Q
    eta_jk = a_jk eta_j(k-1) + R_j I_k (1 - a_jk),      a_jk = exp(-dt_k / tau_j)
    V_k    = OCV(soc_k) - sum_j eta_jk - R0 f(T_k) I_k

``f(T) = exp(B (1/(T+273.15) - 1/(T_ref+273.15)))`` scales every resistance when the logs
span temperatures (``B`` fitted); otherwise ``f = 1`` at the stated reference temperature.

**Self-heating** (logs without temperature): a pack warms in flight by its own losses and its
resistance falls, which constant resistances cannot follow (a real ArduCopter flight: R from
36 to 19 mOhm per cell over the first 1.0 Ah, the voltage at 18 A *rising* as charge was
drawn). With ``heat_c_j_per_k > 0`` the stepper carries one lumped temperature rise ``y``
above the start (= the reference temperature), driven by the cell's irreversible heat::

    P_k = I_k (R0 f_k I_k + sum_j eta_jk)                 (W: current x overpotential)
    y_k = b_k y_(k-1) + P_k / G (1 - b_k),   b_k = exp(-G dt_k / C)
    f_k = exp(B (1/(T_ref + y_(k-1)) - 1/T_ref))        (the rise before the interval)

with ``C`` the heat capacity and ``G`` the conductance to ambient per cell, ``B`` the
template's Arrhenius constant (not fitted: with the temperature unlogged, only ``B / C``
would be seen). The pack starts at ambient (logs start at rest).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from packpilot.jit import kernel

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Profile:
    """One battery of one log, per cell: what the fit reads."""

    name: str
    t_s: F64
    current_a: F64
    """Cell current, A (+ = discharge)."""
    voltage_v: F64
    """Cell voltage: the battery's voltage / series cells (the average cell)."""
    charge_ah: F64 | None = None
    """Charge drawn since the log's start from the autopilot's counter, per cell (Ah)."""
    temp_c: F64 | None = None
    series_cells: int = 1
    """Series cells of the battery the voltage was divided by (the pack the log came from)."""
    fit_mask: NDArray[np.bool_] | None = None
    """Samples whose voltage the fit sees (None: all). A held-out flight stays in the profile,
    so the state of charge and the RC branches run through it, but its voltages are left out
    of the residuals (leave one flight out, :mod:`packpilot.model.fit.validate`)."""

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name in ("current_a", "voltage_v", "charge_ah", "temp_c", "fit_mask"):
            x = getattr(self, name)
            if x is not None and len(x) != n:
                raise ValueError(f"profile {self.name}: {name} has {len(x)} samples, t_s {n}")
        if n < 2 or not np.all(np.diff(self.t_s) > 0):
            raise ValueError(f"profile {self.name}: t_s must increase, at least 2 samples")

    @property
    def drawn_ah(self) -> F64:
        """Charge drawn since the first sample: the counter, else the sampled current."""
        if self.charge_ah is not None:
            out: F64 = self.charge_ah - self.charge_ah[0]
            return out
        dt = np.diff(self.t_s, prepend=self.t_s[0])
        ah: F64 = np.cumsum(self.current_a * dt) / 3600.0
        return ah

    @property
    def fitted(self) -> NDArray[np.bool_]:
        """The samples the fit sees (all of them without a mask)."""
        return np.ones(len(self.t_s), bool) if self.fit_mask is None else self.fit_mask

    @property
    def period_s(self) -> float:
        """The logging period (median interval)."""
        return float(np.median(np.diff(self.t_s)))

    def window(self, lo: int, hi: int) -> Profile:
        """Samples ``lo:hi`` (the counter kept absolute: the state carries over)."""
        sl = slice(lo, hi)
        return Profile(
            self.name, self.t_s[sl], self.current_a[sl], self.voltage_v[sl],
            None if self.charge_ah is None else self.charge_ah[sl],
            None if self.temp_c is None else self.temp_c[sl], self.series_cells,
            None if self.fit_mask is None else self.fit_mask[sl],
        )  # fmt: skip

    def holding_out(self, lo: int, hi: int) -> Profile:
        """The same profile with samples ``lo:hi`` left out of the fit (kept for the state)."""
        mask = self.fitted.copy()
        mask[lo:hi] = False
        return replace(self, fit_mask=mask)


def noise_floor(p: Profile) -> float:
    """The voltage's scatter between consecutive samples where the current barely changes
    (1.4826 x the median absolute first difference / sqrt 2): no model can beat it."""
    dv = np.diff(p.voltage_v)
    di = np.abs(np.diff(p.current_a))
    calm = di <= max(0.02 * float(np.max(np.abs(p.current_a))), 1e-3)
    d = dv[calm] if calm.sum() >= 10 else dv
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


REST_SHARE = 0.10
"""A rest between flights: the current below this share of the log's high current (the largest
median of five consecutive |I| samples: spikes left out, and a log resting most of the time
keeps its load) ... On the dronekit tlog the aircraft draws 0.43 A on the ground (its
electronics; 37 mA sample-to-sample scatter), 1.2 A with the motors armed and idling and
15-25 A in the air (high current 33.8 A): 10 % (3.4 A) puts the ground, armed or not, below and
the flights above. A multirotor cannot fly on a tenth of its highest current."""
REST_NOISE = 5.0
"""... and at least this many times the current's own scatter (the robust sample-to-sample
scatter between consecutive quiet samples, as the voltage's noise floor), so a noisy sensor's
zero is not taken for load."""
REST_GAP_S = 30.0
"""... held for at least this long. The tlog's landings between its three flights rest 36 s and
65 s; its two touch-downs inside a flight (motors stopped, 18 s and 14 s) do not split it."""
MIN_FLIGHT_S = 30.0
"""A burst of load shorter than this (a motor test, a hop) starts no flight of its own."""


def _high_current_a(i: F64) -> float:
    """The log's high current: the largest median of five consecutive samples (a one- or
    two-sample spike does not count; a log resting most of the time still has its load)."""
    if i.size < 5:
        return float(np.max(i))
    return float(np.max(np.median(np.lib.stride_tricks.sliding_window_view(i, 5), axis=1)))


def rest_threshold_a(p: Profile) -> float:
    """The current below which a sample is at rest (REST_SHARE, REST_NOISE)."""
    i = np.abs(p.current_a)
    share = REST_SHARE * _high_current_a(i)
    quiet = i <= share
    d = np.diff(p.current_a)[quiet[1:] & quiet[:-1]]
    scatter = float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0)) if d.size >= 10 \
        else 0.0  # fmt: skip
    return max(share, REST_NOISE * scatter, 1e-6)


def flights(p: Profile) -> list[tuple[int, int]]:
    """``(lo, hi)`` sample ranges of the log's flights: load separated by rests of at least
    REST_GAP_S below :func:`rest_threshold_a`. A flight runs from its first loaded sample to
    the next flight's first (the rest after it, the voltage relaxing at its final state of
    charge, is part of it); the samples before the first flight (the rest at the start, where
    the voltage tells the initial state of charge) belong to none."""
    load = np.flatnonzero(np.abs(p.current_a) > rest_threshold_a(p))
    if load.size == 0:
        return []
    t = p.t_s
    # a rest: at least one sample at rest between two loaded ones, REST_GAP_S apart (a cycler
    # logging a constant current every 48 s has long intervals but no rest)
    gaps = np.flatnonzero((t[load[1:]] - t[load[:-1]] >= REST_GAP_S) & (np.diff(load) > 1))
    firsts = np.concatenate([[load[0]], load[gaps + 1]])
    lasts = np.concatenate([load[gaps], [load[-1]]])
    starts = [int(a) for a, b in zip(firsts, lasts, strict=True) if t[b] - t[a] >= MIN_FLIGHT_S]
    if not starts:
        return []
    ends = [*starts[1:], len(t)]
    return list(zip(starts, ends, strict=True))


@kernel
def _rc_kernel(t: F64, i: F64, r: float, tau: float, scale: F64, out: F64) -> None:
    """One RC branch over variable steps; starts in steady state with the first current."""
    eta = r * scale[0] * i[0]
    out[0] = eta
    for k in range(1, t.size):
        a = math.exp(-(t[k] - t[k - 1]) / tau)
        eta = a * eta + r * scale[k] * i[k] * (1.0 - a)
        out[k] = eta


def rc_drop(profile: Profile, r_ohm: float, tau_s: float, scale: F64) -> F64:
    """The drop across one RC branch at each sample."""
    out = np.empty(len(profile.t_s))
    _rc_kernel(profile.t_s, profile.current_a, float(r_ohm), float(tau_s), scale, out)
    return out


@kernel
def _heated_kernel(t: F64, i: F64, r0: float, rc_r: F64, rc_tau: F64, c_j: float, g_w: float,
                   b_k: float, t_ref_k: float, eta: F64, drop: F64, rise: F64) -> None:  # fmt: skip
    """R0 and the RC branches over variable steps with one lumped self-heating node: the
    resistance factor of each interval from the rise before it (explicit in the temperature,
    exact in the RC branches and the cooling); RC branches start in steady state."""
    y = 0.0
    for k in range(t.size):
        f = math.exp(b_k * (1.0 / (t_ref_k + y) - 1.0 / t_ref_k))
        dt = t[k] - t[k - 1] if k > 0 else 0.0
        total = r0 * f * i[k]
        for j in range(rc_r.size):
            if k == 0:
                eta[j] = rc_r[j] * f * i[0]
            else:
                a = math.exp(-dt / rc_tau[j])
                eta[j] = a * eta[j] + rc_r[j] * f * i[k] * (1.0 - a)
            total += eta[j]
        drop[k] = total
        if k > 0:
            b = math.exp(-g_w * dt / c_j)
            y = b * y + i[k] * total / g_w * (1.0 - b)
        rise[k] = y


def heated_drop(profile: Profile, values: EcmValues) -> tuple[F64, F64]:
    """(R0 + RC drop, temperature rise above the start) at each sample, self-heating."""
    n = len(profile.t_s)
    drop, rise = np.empty(n), np.empty(n)
    rc_r = np.array([r for r, _ in values.rc], dtype=np.float64)
    rc_tau = np.array([tau for _, tau in values.rc], dtype=np.float64)
    _heated_kernel(profile.t_s, profile.current_a, float(values.r0_ohm), rc_r, rc_tau,
                   float(values.heat_c_j_per_k), float(values.heat_g_w_per_k),
                   float(values.b_k), float(values.t_ref_c) + 273.15, np.empty(len(rc_r)),
                   drop, rise)  # fmt: skip
    return drop, rise


@dataclass(frozen=True)
class EcmValues:
    """The parameters the stepper needs (per cell)."""

    capacity_ah: float
    r0_ohm: float
    rc: tuple[tuple[float, float], ...]
    """(R_j, tau_j) per RC branch."""
    b_k: float = 0.0
    """Arrhenius constant of the resistances (K); 0 = no temperature dependence."""
    t_ref_c: float = 25.0
    heat_c_j_per_k: float = 0.0
    """Self-heating: heat capacity per cell (J/K); 0 = no self-heating (see the module)."""
    heat_g_w_per_k: float = 0.0
    """Self-heating: conductance to ambient per cell (W/K)."""


def temp_scale(profile: Profile, b_k: float, t_ref_c: float) -> F64:
    """Resistance factor f(T) at each sample (1 without temperature or law)."""
    if profile.temp_c is None or b_k == 0.0:
        return np.ones(len(profile.t_s))
    inv = 1.0 / (profile.temp_c + 273.15) - 1.0 / (t_ref_c + 273.15)
    out: F64 = np.exp(b_k * inv)
    return out


def predict(
    profile: Profile, values: EcmValues, soc0: float, ocv_soc: F64, ocv_v: F64
) -> tuple[F64, F64]:
    """(cell voltage, state of charge) at every sample of the profile."""
    soc = soc0 - profile.drawn_ah / values.capacity_ah
    if values.heat_c_j_per_k > 0.0:
        drop, _ = heated_drop(profile, values)
        return np.interp(soc, ocv_soc, ocv_v) - drop, soc
    scale = temp_scale(profile, values.b_k, values.t_ref_c)
    v = np.interp(soc, ocv_soc, ocv_v) - values.r0_ohm * scale * profile.current_a
    for r, tau in values.rc:
        v = v - rc_drop(profile, r, tau, scale)
    return v, soc


__all__ = [
    "EcmValues", "Profile", "flights", "heated_drop", "noise_floor", "predict", "rc_drop",
    "rest_threshold_a", "temp_scale",
]
