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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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

    def __post_init__(self) -> None:
        n = len(self.t_s)
        for name in ("current_a", "voltage_v", "charge_ah", "temp_c"):
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
    def period_s(self) -> float:
        """The logging period (median interval)."""
        return float(np.median(np.diff(self.t_s)))

    def window(self, lo: int, hi: int) -> Profile:
        """Samples ``lo:hi`` (the counter kept absolute: the state carries over)."""
        sl = slice(lo, hi)
        return Profile(
            self.name, self.t_s[sl], self.current_a[sl], self.voltage_v[sl],
            None if self.charge_ah is None else self.charge_ah[sl],
            None if self.temp_c is None else self.temp_c[sl],
        )  # fmt: skip


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
    scale = temp_scale(profile, values.b_k, values.t_ref_c)
    v = np.interp(soc, ocv_soc, ocv_v) - values.r0_ohm * scale * profile.current_a
    for r, tau in values.rc:
        v = v - rc_drop(profile, r, tau, scale)
    return v, soc


__all__ = ["EcmValues", "Profile", "predict", "rc_drop", "temp_scale"]
