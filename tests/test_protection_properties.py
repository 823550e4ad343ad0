"""Property tests of the discharge protection (hypothesis)."""

from __future__ import annotations

import math
from fractions import Fraction

from hypothesis import given
from hypothesis import strategies as st

from packpilot.contract.bms import BatteryMeasurement, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.protection import CompiledTable, ProtectionConfig, ProtectionController
from tests.budget import budget

PACK = PackInfo(
    n_batteries=1,
    groups_per_battery=(6,),
    cells_per_group=(1,),
    switch_kind=(SwitchKind.RELAY,),
)
CFG = ProtectionConfig()
TABLE = CompiledTable.from_config(CFG)

currents = st.one_of(
    st.sampled_from([15.0, 25.0, 0.6, 100.0]),
    st.floats(min_value=0.6, max_value=80.0, allow_nan=False),
)
temps = st.one_of(
    st.sampled_from([5.0, 15.0, -30.0, 60.0]),
    st.floats(min_value=-30.0, max_value=60.0, allow_nan=False),
)
Row = tuple[float, float, float, float]  # (I, T, V, dt)


def _bm(i: float, t: float, v: float) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=6 * v,
        current_a=i,
        temp_c=t,
        min_cell_v=v,
        max_cell_v=v,
        soc=0.5,
        full_capacity_ah=5.0,
        remaining_capacity_ah=2.5,
    )


def _trip_time(rows: list[Row], cfg: ProtectionConfig = CFG) -> float | None:
    """End time of the tick in which the protection trips (None = never)."""
    ctl = ProtectionController(cfg, PACK)
    t = 0.0
    for i, temp, v, dt in rows:
        out = ctl.step(Measurements(t_s=t, batteries=(_bm(i, temp, v),), bus_v=6 * v), dt)
        t += dt
        if any(e.kind == "ProtectionTripped" for e in out.events):
            return t
    return None


def _reference_param(i: float, t: float) -> str:
    """Spec §4 grid with the §10.1 edge convention, written out independently."""
    if t < 5.0 or i > 25.0:
        return "P1"
    if i > 15.0 or t < 15.0:
        return "P2"
    return "P3"


@budget(300)
@given(i=currents, t=temps)
def test_lookup_matches_edge_convention(i: float, t: float) -> None:
    row = TABLE.lookup([i, t])
    assert TABLE.params[TABLE.rows[row][0]].name == _reference_param(i, t)


@budget(200)
@given(
    i=currents,
    t=temps,
    dt_ms=st.integers(min_value=1, max_value=3000),
    depth=st.floats(min_value=0.0, max_value=0.5),
)
def test_constant_parameter_trips_at_tmax_within_one_step(
    i: float, t: float, dt_ms: int, depth: float
) -> None:
    params = {p.name: p for p in TABLE.params}
    p = params[_reference_param(i, t)]
    dt = dt_ms / 1000.0
    n = math.ceil(p.t_max_s / dt) + 2
    trip = _trip_time([(i, t, p.cutoff_v - depth, dt)] * n)
    assert trip is not None
    assert p.t_max_s - 1e-9 <= trip < p.t_max_s + dt + 1e-9
    # and exactly on the tick where k*dt first reaches t_max (exact arithmetic)
    assert round(trip / dt) == math.ceil(Fraction(p.t_max_ms, dt_ms))


trace_rows = st.tuples(
    currents | st.floats(min_value=-10.0, max_value=0.6),
    temps,
    st.floats(min_value=2.5, max_value=4.2),
    st.sampled_from([0.1, 0.5, 1.0, 2.0]),
)


@budget(200)
@given(
    rows=st.lists(
        st.tuples(currents, temps, st.floats(min_value=3.2001, max_value=4.3), st.just(1.0)),
        min_size=1,
        max_size=200,
    )
)
def test_voltage_above_every_cutoff_never_trips(rows: list[Row]) -> None:
    assert max(p.cutoff_v for p in TABLE.params) == 3.2
    assert _trip_time(rows) is None


@budget(200)
@given(
    rows=st.lists(trace_rows, min_size=1, max_size=120),
    drops=st.lists(st.floats(min_value=0.0, max_value=1.0), min_size=120, max_size=120),
)
def test_lowering_voltage_never_delays_the_trip(rows: list[Row], drops: list[float]) -> None:
    lowered = [(i, t, v - d, dt) for (i, t, v, dt), d in zip(rows, drops, strict=False)]
    before = _trip_time(rows)
    after = _trip_time(lowered)
    if before is not None:
        assert after is not None and after <= before + 1e-9


@budget(200)
@given(rows=st.lists(trace_rows, min_size=1, max_size=120))
def test_fraction_is_sum_of_t_over_tmax(rows: list[Row]) -> None:
    """The weighted sum / m equals sum(t_k / t_max_k) over discharging ticks below cut-off."""
    ctl = ProtectionController(CFG, PACK)
    params = {p.name: p for p in TABLE.params}
    expected = Fraction(0)
    for k, (i, t, v, dt) in enumerate(rows):
        ctl.step(Measurements(t_s=float(k), batteries=(_bm(i, t, v),), bus_v=6 * v), dt)
        if ctl.battery(0).tripped:
            break
        p = params[_reference_param(i, t)]
        if i > CFG.discharge_threshold_a and v <= p.cutoff_v:
            expected += Fraction(round(dt * 1000), p.t_max_ms)
        assert ctl.battery(0).acc_wms / TABLE.m_ms == expected


def test_dt_ms_is_pythons_limit_denominator() -> None:
    """The tick length in exact ms (rules.dt_ms) equals CPython's
    ``Fraction(dt * 1000).limit_denominator(1000)`` for tick lengths that are no whole number
    of ms (k / 7919 s), where the continued fraction must choose between its last convergent
    and the semiconvergent (generated mutant 68f193f081: that choice broken), and for ticks
    below a microsecond, where only 0/1 and 1/1000 are candidates (6e8f3f340e)."""
    from packpilot.control.protection.rules import dt_ms

    tiny = [1e-9, 1e-7, 4.9e-7, 5e-7, 5.1e-7, 9.9e-7]  # below 1/1000 ms: 0/1 or 1/1000
    for dt in [*(k / 7919.0 for k in range(1, 4000, 7)), *tiny]:
        want = Fraction(dt * 1000.0).limit_denominator(1000)
        assert dt_ms(dt) == (want.numerator, want.denominator), dt


def test_ticks_of_coprime_lengths_round_the_sum_up_and_go_on() -> None:
    """Tick lengths of 100 + 1/q ms for distinct primes q near 1000 make the exact sum's
    denominator (their product) outgrow the integer range after a few ticks: the sum is then
    rounded up to whole weighted microseconds and goes on, within a few microseconds of the
    exact sum, and never jumps to a trip (acc_add's fallback; generated mutant cefe11f424: the
    guard inverted, every rounded sum saturated and tripped at once). P3: 5 s allowance."""
    ctl = ProtectionController(CFG, PACK)
    params = {p.name: p for p in TABLE.params}
    p3 = params[_reference_param(10.0, 25.0)]
    assert p3.cutoff_v > 3.1
    exact, t = Fraction(0), 0.0
    for q in (997, 991, 983, 977, 971, 967, 953, 947, 941, 937):
        dt = (100 * q + 1) / q / 1000.0
        out = ctl.step(Measurements(t_s=t, batteries=(_bm(10.0, 25.0, 3.1),), bus_v=18.6), dt)
        t += dt
        exact += Fraction(100 * q + 1, q) / p3.t_max_ms
        assert not ctl.battery(0).tripped
        assert not any(e.kind == "ProtectionTripped" for e in out.events)
    got = ctl.battery(0).acc_wms / TABLE.m_ms
    assert float(exact) <= got <= float(exact) + 1e-4  # rounded up, by microseconds


def test_dt_ms_rounds_sub_microsecond_ticks_like_python() -> None:
    """Ticks of 0.5 to 1 microsecond (below 1/1000 ms: the only candidates are 0/1 and
    1/1000 ms) with full 53-bit mantissas: dt_ms picks 1/1000 above the midpoint and 0/1 at or
    below it, as ``Fraction.limit_denominator(1000)`` does (generated mutant 50c4a9cc5c: every
    such tick read as 0 ms)."""
    from packpilot.control.protection.rules import dt_ms

    for j in range(1, 500):
        dt = math.nextafter((0.5 + j / 1000.0) * 1e-6, 1.0)
        want = Fraction(dt * 1000.0).limit_denominator(1000)
        assert dt_ms(dt) == (want.numerator, want.denominator), dt


def test_dt_ms_of_half_millisecond_ticks() -> None:
    """Ticks of a whole number of milliseconds and a half (0.5, 1.5, ... 199.5 ms): dt_ms gives
    the exact (2k + 1) / 2 ms, as ``Fraction.limit_denominator(1000)`` does (generated mutant
    6839332153: ``e <= 0`` -> ``<= 1`` shifted such ticks by a negative count)."""
    from packpilot.control.protection.rules import dt_ms

    for k in range(200):
        dt = (k + 0.5) / 1000.0
        want = Fraction(dt * 1000.0).limit_denominator(1000)
        assert dt_ms(dt) == (want.numerator, want.denominator), dt
    assert dt_ms(0.0015) == (3, 2)
