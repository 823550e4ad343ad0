"""CC/CV charging dock: commanded voltage and current limit, heartbeat timeout, fault flags.

The dock behaves like a real CAN-commanded charger (TC/Elcon style): it regulates its output
to the last *requested* voltage/current, and switches its output off when no request has
arrived for ``heartbeat_timeout_s`` (so a hung BMS loop cannot leave it charging). Output
restarts when requests resume. Arrays are over packs so a fleet steps together.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

FLAG_NAMES: tuple[str, ...] = (
    "hardware_failure",
    "over_temperature",
    "input_voltage_fault",
    "battery_not_detected",
    "communication_timeout",
)


@dataclass(frozen=True)
class ChargerParams:
    rated_v: float = 500.0
    rated_a: float = 100.0
    r_out_ohm: float = 0.01
    """Output regulation slope: turns the CV corner into a monotone piecewise-linear source."""
    heartbeat_timeout_s: float = 5.0


@dataclass
class ChargerModel:
    """State of the chargers of ``n`` packs."""

    params: ChargerParams
    n: int
    connected: BoolArray = field(init=False)
    v_req: Array = field(init=False)
    i_req: Array = field(init=False)
    on_req: BoolArray = field(init=False)
    last_request_s: Array = field(init=False)
    flags: NDArray[np.bool_] = field(init=False)
    """Shape (n, 5), columns as FLAG_NAMES."""
    out_v: Array = field(init=False)
    out_a: Array = field(init=False)

    def __post_init__(self) -> None:
        self.connected = np.zeros(self.n, dtype=bool)
        self.v_req = np.zeros(self.n)
        self.i_req = np.zeros(self.n)
        self.on_req = np.zeros(self.n, dtype=bool)
        self.last_request_s = np.full(self.n, -np.inf)
        self.flags = np.zeros((self.n, len(FLAG_NAMES)), dtype=bool)
        self.out_v = np.zeros(self.n)
        self.out_a = np.zeros(self.n)

    def request(
        self, idx: int, voltage_v: float, current_a: float, enable: bool, t_s: float
    ) -> None:
        """A request (heartbeat) arrived for charger ``idx``; clamped to the rating."""
        self.v_req[idx] = min(max(voltage_v, 0.0), self.params.rated_v)
        self.i_req[idx] = min(max(current_a, 0.0), self.params.rated_a)
        self.on_req[idx] = bool(enable)
        self.last_request_s[idx] = t_s

    def timed_out(self, t_s: float) -> BoolArray:
        return (t_s - self.last_request_s) > self.params.heartbeat_timeout_s

    def output_enabled(self, t_s: float) -> BoolArray:
        """Output is live iff connected, requested on, heartbeat fresh and no fault flag."""
        timeout = self.timed_out(t_s)
        self.flags[:, 4] = timeout & self.connected
        faulted = self.flags[:, :4].any(axis=1)
        return self.connected & self.on_req & ~timeout & ~faulted & (self.i_req > 0.0)

    def view(self, idx: int) -> ChargerView:
        return ChargerView(self, idx)


@dataclass
class ChargerView:
    """One pack's charger, in the shape the CAN emulator expects (``ChargerPlant``)."""

    model: ChargerModel
    idx: int

    def request(self, voltage_v: float, current_a: float, enable: bool, t_s: float) -> None:
        self.model.request(self.idx, voltage_v, current_a, enable, t_s)

    def output(self) -> tuple[float, float]:
        return float(self.model.out_v[self.idx]), float(self.model.out_a[self.idx])

    @property
    def fault_flags(self) -> dict[str, bool]:
        return {name: bool(self.model.flags[self.idx, k]) for k, name in enumerate(FLAG_NAMES)}

    def set_fault(self, name: str, value: bool = True) -> None:
        """Fault injection: raise or clear one status flag."""
        self.model.flags[self.idx, FLAG_NAMES.index(name)] = value
