"""A toy multi-battery charging plant for driving ChargingController without the real model.

Each battery is a linear OCV source (``E = v0 + slope * charge_ah``) behind a resistance; the
charger is an ideal CC/CV source that cannot sink current. Batteries whose relays are closed
share one busbar, so connected batteries also exchange current with each other. The tests in
this file check the toy itself, so the controller tests do not rest on a broken yardstick.
"""

from __future__ import annotations

import math
import random
from collections.abc import Sequence
from dataclasses import dataclass, field

from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.charger import ChargerCommand, ChargerStatus
from packpilot.contract.topology import PackInfo


def pack_info(n: int, series: int = 30, has_aux: bool = False) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(series,) * n,
        cells_per_group=(1,) * n,
        switch_kind=(SwitchKind.RELAY,) * n,
        has_aux=has_aux,
        has_charger=True,
        capacity_ah=(5.0,) * n,
    )


def solve_bus(
    ocv: Sequence[float], r_ohm: Sequence[float], closed: Sequence[bool], cmd: ChargerCommand
) -> tuple[float, list[float], float]:
    """Bus voltage, battery currents (positive = discharge) and charger current."""
    idx = [i for i, c in enumerate(closed) if c]
    cur = [0.0] * len(ocv)
    if not idx:
        return math.nan, cur, 0.0
    g = sum(1.0 / r_ohm[i] for i in idx)
    ge = sum(ocv[i] / r_ohm[i] for i in idx)
    v_float = ge / g
    i_chg = 0.0
    v = v_float
    if cmd.enable and cmd.current_a > 0.0:
        i_cv = cmd.voltage_v * g - ge  # charger current needed to hold the bus at Vc
        if i_cv <= 0.0:
            v, i_chg = v_float, 0.0
        elif i_cv <= cmd.current_a:
            v, i_chg = cmd.voltage_v, i_cv
        else:
            v, i_chg = (cmd.current_a + ge) / g, cmd.current_a
    for i in idx:
        cur[i] = (ocv[i] - v) / r_ohm[i]
    return v, cur, i_chg


@dataclass
class ToyPack:
    """Batteries + relays + CC/CV charger; ``step`` integrates one period."""

    v0: list[float]
    r_ohm: float = 0.1
    capacity_ah: float = 5.0
    slope_v_per_ah: float = 8.0
    series: int = 30
    noise_v: float = 0.0
    seed: int = 0
    docked: bool = True
    closed: list[bool] = field(default_factory=list)
    charger_cmd: ChargerCommand = field(
        default_factory=lambda: ChargerCommand(0.0, 0.0, enable=False)
    )
    charger_online: bool = True
    charger_flags: dict[str, bool] = field(default_factory=dict)
    aux_soc: float | None = None
    cell_offset_v: list[float] = field(default_factory=list)
    """Per battery: how far the highest cell sits above the average cell."""
    t_s: float = 0.0

    def __post_init__(self) -> None:
        n = len(self.v0)
        self.ocv = list(self.v0)
        self.closed = self.closed or [False] * n
        self.current = [0.0] * n
        self.bus_v = math.nan
        self.charger_a = 0.0
        self.heat_j = [0.0] * n
        self.peak_a = [0.0] * n
        self.rng = random.Random(self.seed)
        self.aux_relay = False
        self.aux_a = 0.0

    @property
    def n(self) -> int:
        return len(self.v0)

    def apply(self, out: ControlOutput) -> None:
        c: Commands = out.commands
        for i in range(self.n):
            chg = c.chg_on[i] if i < len(c.chg_on) else None
            dsg = c.dsg_on[i] if i < len(c.dsg_on) else None
            if chg is not None or dsg is not None:
                self.closed[i] = bool(chg) and bool(dsg)
        if c.charger is not None:
            self.charger_cmd = c.charger
        if c.aux_relay_closed is not None:
            self.aux_relay = c.aux_relay_closed
        if c.aux_charge_a is not None:
            self.aux_a = c.aux_charge_a

    def step(self, dt_s: float) -> None:
        cmd = self.charger_cmd
        if not self.docked or not self.charger_online or any(self.charger_flags.values()):
            cmd = ChargerCommand(0.0, 0.0, enable=False)
        self.bus_v, self.current, self.charger_a = solve_bus(
            self.ocv, [self.r_ohm] * self.n, self.closed, cmd
        )
        for i, cur in enumerate(self.current):
            self.ocv[i] -= cur * dt_s / 3600.0 * self.slope_v_per_ah
            self.heat_j[i] += cur * cur * self.r_ohm * dt_s
            self.peak_a[i] = max(self.peak_a[i], abs(cur))
        if self.aux_soc is not None and self.aux_relay:
            self.aux_soc = min(1.0, self.aux_soc + self.aux_a * dt_s / 3600.0 / 2.0)
        self.t_s += dt_s

    def terminal_v(self, i: int) -> float:
        return self.ocv[i] - self.current[i] * self.r_ohm

    def measure(self) -> Measurements:
        bats = []
        for i in range(self.n):
            v = self.terminal_v(i) + (self.rng.gauss(0.0, self.noise_v) if self.noise_v else 0.0)
            sw = SwitchState(self.closed[i], self.closed[i])
            bats.append(
                BatteryMeasurement(
                    voltage_v=v,
                    current_a=self.current[i],
                    temp_c=25.0,
                    min_cell_v=v / self.series,
                    max_cell_v=v / self.series
                    + (self.cell_offset_v[i] if self.cell_offset_v else 0.0),
                    soc=(self.ocv[i] - 80.0) / 40.0,
                    full_capacity_ah=self.capacity_ah,
                    remaining_capacity_ah=self.capacity_ah * (self.ocv[i] - 80.0) / 40.0,
                    switch=sw,
                )
            )
        charger = None
        if self.docked:
            charger = ChargerStatus(
                output_v=0.0 if math.isnan(self.bus_v) else self.bus_v,
                output_a=self.charger_a,
                online=self.charger_online,
                **self.charger_flags,
            )
        aux = None
        if self.aux_soc is not None:
            aux = BatteryMeasurement(
                voltage_v=12.0 + 2.0 * self.aux_soc,
                current_a=-self.aux_a if self.aux_relay else 0.0,
                temp_c=25.0,
                min_cell_v=3.0,
                max_cell_v=3.5,
                soc=self.aux_soc,
                full_capacity_ah=2.0,
                remaining_capacity_ah=2.0 * self.aux_soc,
            )
        return Measurements(
            t_s=self.t_s,
            batteries=tuple(bats),
            bus_v=self.bus_v,
            charger=charger,
            aux=aux,
            docked=self.docked,
        )


def test_solve_bus_cc_cv_and_no_sink() -> None:
    cmd = ChargerCommand(92.0, 20.0)
    v, cur, ich = solve_bus([80.0, 90.0], [0.1, 0.1], [True, False], cmd)
    assert ich == 20.0 and cur[0] == -20.0 and cur[1] == 0.0
    assert math.isclose(v, 82.0)
    v, cur, ich = solve_bus([91.5, 90.0], [0.1, 0.1], [True, False], cmd)
    assert v == 92.0 and math.isclose(ich, 5.0)
    # charger below both batteries: it cannot sink, the batteries equalize between themselves
    v, cur, ich = solve_bus([95.0, 97.0], [0.1, 0.1], [True, True], cmd)
    assert ich == 0.0 and math.isclose(v, 96.0) and math.isclose(sum(cur), 0.0, abs_tol=1e-9)


def test_toy_charge_conservation() -> None:
    toy = ToyPack([80.0, 90.0], closed=[True, True])
    toy.charger_cmd = ChargerCommand(100.0, 10.0)
    q0 = sum(toy.ocv)
    for _ in range(100):
        toy.step(1.0)
    gained_ah = (sum(toy.ocv) - q0) / toy.slope_v_per_ah
    assert math.isclose(gained_ah, 10.0 * 100 / 3600.0, rel_tol=1e-9)
