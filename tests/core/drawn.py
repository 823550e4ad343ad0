"""Drawn measurement sequences and exact output comparison, for tests that drive two cores
(fused vs part by part) with the same hostile input: NaN, inf, absent batteries, time going
backwards, odd dt; commands, events (kind, battery, message, data) and status must match
exactly at every step."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from hypothesis import strategies as st

from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Measurements,
    SwitchState,
)
from packpilot.contract.charger import ChargerStatus

WEIRD = [math.nan, math.inf, -math.inf]


def num(lo: float, hi: float, weird: float = 0.05) -> st.SearchStrategy[float]:
    """Mostly finite values in [lo, hi], sometimes NaN / inf."""
    return (
        st.one_of(
            st.floats(lo, hi, allow_nan=False),
            st.sampled_from(WEIRD),
        )
        if weird
        else st.floats(lo, hi, allow_nan=False)
    )


@st.composite
def battery(
    draw: Any,
    groups: int,
    v_cell: tuple[float, float] = (2.5, 4.3),
    current: tuple[float, float] = (-30.0, 60.0),
    cap_ah: float = 5.0,
    bad_groups: int = 0,
) -> BatteryMeasurement:
    """One battery's reading; ``bad_groups`` = N > 0: one time in N a group voltage is
    NaN / inf / zero / negative (0: never, and no extra draw)."""
    cell = draw(st.floats(*v_cell))
    spread = draw(st.floats(0.0, 0.1))
    gv = tuple(draw(st.floats(cell - spread, cell + spread)) for _ in range(groups))
    if draw(st.integers(0, 20)) == 0:
        gv = gv[: draw(st.integers(0, groups))]
    if bad_groups and gv and draw(st.integers(0, bad_groups - 1)) == 0:
        k = draw(st.integers(0, len(gv) - 1))
        bad = draw(st.sampled_from([*WEIRD, 0.0, -0.0, -1.0]))
        gv = (*gv[:k], bad, *gv[k + 1 :])
    cur = draw(st.one_of(st.floats(*current), st.sampled_from([0.0, *WEIRD])))
    return BatteryMeasurement(
        # float(): a float 0.0 (not the int 0) when there are no group voltages
        voltage_v=draw(st.one_of(st.just(float(sum(gv))), num(0.0, 5.0 * groups))),
        current_a=cur,
        temp_c=draw(num(-30.0, 80.0)),
        min_cell_v=draw(st.one_of(st.just(min(gv, default=cell)), num(2.0, 4.5))),
        max_cell_v=draw(st.one_of(st.just(max(gv, default=cell)), num(2.0, 4.5))),
        soc=draw(num(0.0, 1.0)),
        full_capacity_ah=draw(st.one_of(st.just(cap_ah), num(0.0, 2 * cap_ah))),
        remaining_capacity_ah=draw(num(0.0, cap_ah)),
        group_voltages_v=gv,
        switch=SwitchState(draw(st.booleans()), draw(st.booleans())),
        min_temp_c=draw(num(-30.0, 80.0)),
        present=draw(st.sampled_from([True] * 9 + [False])),
        sample_age_s=draw(st.sampled_from([math.nan] * 8 + [0.0, 3.0])),
    )


@st.composite
def charger(draw: Any) -> ChargerStatus | None:
    if draw(st.integers(0, 3)) == 0:
        return None
    return ChargerStatus(
        output_v=draw(num(0.0, 60.0)),
        output_a=draw(num(-1.0, 30.0)),
        hardware_failure=draw(st.sampled_from([False] * 9 + [True])),
        over_temperature=draw(st.sampled_from([False] * 19 + [True])),
        communication_timeout=draw(st.sampled_from([False] * 19 + [True])),
        online=draw(st.sampled_from([True] * 9 + [False])),
    )


DTS = (0.1, 0.2, 0.5, 1.0, 5.0, 0.0, -0.1, math.nan, 0.3)
"""The tick lengths :func:`sequence` draws from by default."""


@st.composite
def sequence(
    draw: Any,
    n: int,
    groups: int | Sequence[int],
    steps: int = 60,
    dts: Sequence[float] = DTS,
    **kw: Any,
) -> list[tuple[Measurements, float]]:
    """A run of samples: mostly advancing time with sticky values, with jumps (``dts``: the
    tick lengths to draw from). ``groups``: the series groups of every battery, or of each."""
    out: list[tuple[Measurements, float]] = []
    t = 0.0
    per = [groups] * n if isinstance(groups, int) else list(groups)
    bats = [draw(battery(per[i], **kw)) for i in range(n)]
    for _ in range(draw(st.integers(1, steps))):
        dt = draw(st.sampled_from(list(dts)))
        k = draw(st.integers(0, n))  # change one battery (k == n: none)
        if k < n:
            bats[k] = draw(battery(per[k], **kw))
        nb = n if draw(st.integers(0, 30)) else draw(st.integers(0, n))
        meas = Measurements(
            t_s=t,
            batteries=tuple(bats[:nb]),
            bus_v=draw(num(0.0, 30.0)),
            load_current_a=draw(num(-5.0, 60.0)),
            charger=draw(charger()),
            aux=draw(st.one_of(st.none(), battery(1))),
            docked=draw(st.booleans()),
        )
        out.append((meas, dt))
        if math.isfinite(dt):
            t += dt
        if draw(st.integers(0, 40)) == 0:
            t -= 1.0
    return out


def _pad(flags: Sequence[bool | None], n: int) -> tuple[bool | None, ...]:
    return tuple(flags) + (None,) * (n - len(flags))


def norm_commands(c: Commands, n: int) -> tuple[Any, ...]:
    """Commands with the "no opinion" encodings made equal (``()`` == ``(None, None)``)."""
    return (
        _pad(c.chg_on, n),
        _pad(c.dsg_on, n),
        c.charger,
        c.balancer_a,
        c.aux_relay_closed,
        c.aux_charge_a,
    )


def same(a: Any, b: Any) -> bool:
    """Equal, with NaN equal to NaN (floats compared exactly otherwise)."""
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, dict) and isinstance(b, dict):
        return list(a) == list(b) and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple) and isinstance(b, list | tuple):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    return bool(a == b) and type(a) is type(b)


def assert_same_output(new: ControlOutput, old: ControlOutput, n: int, where: str) -> None:
    assert same(norm_commands(new.commands, n), norm_commands(old.commands, n)), (
        where,
        new.commands,
        old.commands,
    )
    ev_new = [(e.t_s, e.kind, e.battery, e.message, dict(e.data)) for e in new.events]
    ev_old = [(e.t_s, e.kind, e.battery, e.message, dict(e.data)) for e in old.events]
    assert same(ev_new, ev_old), (where, ev_new, ev_old)
    st_old = {k: list(v) for k, v in old.status.items()}
    st_new = {k: list(v) for k, v in new.status.items()}
    assert same(st_new, st_old), (where, st_new, st_old)
