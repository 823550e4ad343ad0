"""Shared builders for the safety-layer tests (limits, plausibility, SOC): no tests here."""

from __future__ import annotations

import math
from typing import Any

from hypothesis import strategies as st

from packpilot.contract.bms import (
    BatteryMeasurement,
    ControlOutput,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.topology import PackInfo
from packpilot.control.limits import LimitRow, LimitsConfig, LimitsController

CAP = 5.0
DT = 0.1
DELTA = 1e-3


def pack(n: int = 1, kind: SwitchKind = SwitchKind.MOSFET_PAIR) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(6,) * n,
        cells_per_group=(1,) * n,
        switch_kind=(kind,) * n,
        capacity_ah=(CAP,) * n,
    )


def healthy(**kw: Any) -> BatteryMeasurement:
    base: dict[str, Any] = dict(
        voltage_v=22.2,
        current_a=0.0,
        temp_c=25.0,
        min_temp_c=25.0,
        min_cell_v=3.7,
        max_cell_v=3.7,
        soc=0.5,
        full_capacity_ah=CAP,
        remaining_capacity_ah=2.5,
    )
    base.update(kw)
    return BatteryMeasurement(**base)


def with_value(row: LimitRow, value: float) -> BatteryMeasurement:
    """A healthy battery whose row quantity is ``value`` (and whose context is active)."""
    q = row.quantity
    kw: dict[str, Any] = {}
    if q == "cell_v_max":
        kw = {"max_cell_v": value, "min_cell_v": min(3.7, value)}
    elif q == "cell_v_min":
        kw = {"min_cell_v": value, "max_cell_v": max(3.7, value)}
    elif q == "chg_c_rate":
        kw = {"current_a": -value * CAP}
    elif q == "dsg_c_rate":
        kw = {"current_a": value * CAP}
    elif q == "temp_max_c":
        kw = {"temp_c": value, "min_temp_c": min(25.0, value)}
    elif q == "temp_min_c":
        kw = {"min_temp_c": value, "temp_c": max(25.0, value)}
    if row.when == "discharging" and "current_a" not in kw:
        kw["current_a"] = 1.0 * CAP
    return healthy(**kw)


class Driver:
    def __init__(self, cfg: LimitsConfig | None = None, n: int = 1, **pk: Any) -> None:
        self.ctl = LimitsController(cfg or LimitsConfig(), pack(n, **pk))
        self.t = 0.0

    def step(self, *bms: BatteryMeasurement, docked: bool = False, dt: float = DT) -> ControlOutput:
        out = self.ctl.step(Measurements(t_s=self.t, batteries=bms, bus_v=22.2, docked=docked), dt)
        self.t += dt
        return out


# -- hypothesis strategies: arbitrary (hostile) measurements -----------------------------

SPECIAL = st.sampled_from([math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e-308])
ANY_FLOAT = st.one_of(
    SPECIAL,
    st.floats(min_value=-100.0, max_value=100.0),
    st.floats(allow_nan=True, allow_infinity=True),
)


@st.composite
def battery_measurements(draw: st.DrawFn) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=draw(ANY_FLOAT),
        current_a=draw(ANY_FLOAT),
        temp_c=draw(ANY_FLOAT),
        min_cell_v=draw(ANY_FLOAT),
        max_cell_v=draw(ANY_FLOAT),
        soc=draw(ANY_FLOAT),
        full_capacity_ah=draw(ANY_FLOAT),
        remaining_capacity_ah=draw(ANY_FLOAT),
        group_voltages_v=tuple(draw(st.lists(ANY_FLOAT, max_size=8))),
        switch=SwitchState(chg_on=draw(st.booleans()), dsg_on=draw(st.booleans())),
        min_temp_c=draw(ANY_FLOAT),
        present=draw(st.booleans()),
    )


@st.composite
def measurements(draw: st.DrawFn) -> Measurements:
    return Measurements(
        t_s=draw(ANY_FLOAT),
        batteries=tuple(draw(st.lists(battery_measurements(), max_size=5))),
        bus_v=draw(ANY_FLOAT),
        load_current_a=draw(ANY_FLOAT),
        docked=draw(st.booleans()),
    )


@st.composite
def pack_infos(draw: st.DrawFn) -> PackInfo:
    n = draw(st.integers(min_value=1, max_value=4))
    kinds = tuple(draw(st.sampled_from(list(SwitchKind))) for _ in range(n))
    caps = draw(
        st.one_of(
            st.just(()),
            st.lists(st.floats(min_value=0.1, max_value=200.0), min_size=n, max_size=n),
        )
    )
    return PackInfo(
        n_batteries=n,
        groups_per_battery=tuple(draw(st.integers(1, 8)) for _ in range(n)),
        cells_per_group=tuple(draw(st.integers(1, 4)) for _ in range(n)),
        switch_kind=kinds,
        capacity_ah=tuple(caps),
    )
