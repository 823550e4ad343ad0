"""The exact bus solve against brute-force root finding."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from packpilot.model.bus import ChargerSource, LoadSink, solve_bus
from packpilot.model.switches import KIND_MOSFET, KIND_RELAY, switch_branches
from tests.budget import budget


def _setup(e, kinds, chg, dsg, r, load=(0.0, 0.0, 0.0, 0.0), charger=None):  # type: ignore[no-untyped-def]
    n = len(e)
    br = switch_branches(
        np.array(kinds),
        np.full(n, 0.001),
        np.full(n, 0.6),
        np.full(n, 0.002),
        np.array([chg]),
        np.array([dsg]),
        np.ones((1, n), bool),
        np.array([r]),
    )
    en, v, i = charger or (False, 0.0, 0.0)
    ch = ChargerSource(np.array([en]), np.array([v]), np.array([i]), np.array([0.01]))
    a, g, p, vmin = load
    ld = LoadSink(np.array([a]), np.array([g]), np.array([p]), np.array([vmin]))
    return np.array([e], float), br, ch, ld


@budget(200)
@given(
    st.lists(st.floats(10.0, 30.0), min_size=1, max_size=6),
    st.data(),
)
def test_kcl_holds_and_solution_is_unique_operating_point(e, data) -> None:  # type: ignore[no-untyped-def]
    n = len(e)
    kinds = data.draw(st.lists(st.sampled_from([KIND_RELAY, KIND_MOSFET]), min_size=n, max_size=n))
    chg = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    dsg = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    r = data.draw(st.lists(st.floats(0.005, 0.2), min_size=n, max_size=n))
    a = data.draw(st.floats(0.0, 50.0))
    p = data.draw(st.sampled_from([0.0, 100.0, 400.0]))
    charger = data.draw(st.sampled_from([None, (True, 25.0, 10.0)]))
    args = _setup(e, kinds, chg, dsg, r, (a, 0.0, p, 0.0), charger)
    sol = solve_bus(*args)
    v = sol.bus_v[0]
    if sol.supplied[0] and (a > 0 or p > 0):
        total = sol.string_a[0].sum() + sol.charger_a[0]
        assert abs(total - sol.load_a[0]) <= 1e-6 * max(1.0, abs(total))
        assert abs(sol.load_a[0] - (a + p / v)) <= 1e-6 * max(1.0, sol.load_a[0])
    # Strings never carry current in a direction their switch blocks.
    for k in range(n):
        closed_relay = kinds[k] == KIND_RELAY and chg[k] and dsg[k]
        if kinds[k] == KIND_RELAY and not closed_relay:
            assert sol.string_a[0, k] == 0.0
        if kinds[k] == KIND_MOSFET and not chg[k]:
            assert sol.string_a[0, k] >= 0.0
        if kinds[k] == KIND_MOSFET and not dsg[k]:
            assert sol.string_a[0, k] <= 0.0


def test_constant_power_picks_the_high_voltage_root() -> None:
    e, br, ch, ld = _setup([24.0], [KIND_RELAY], [True], [True], [0.1], (0.0, 0.0, 500.0, 0.0))
    sol = solve_bus(e, br, ch, ld)
    v = sol.bus_v[0]
    # V = E - R P / V  ->  V^2 - E V + R P = 0, the larger root.
    expected = (24.0 + np.sqrt(24.0**2 - 4 * 0.101 * 500.0)) / 2  # + relay 1 mOhm
    assert abs(v - expected) < 1e-9


def test_power_beyond_the_maximum_collapses_the_bus() -> None:
    # Max power of 24 V behind 0.101 Ohm is E^2 / 4R = 1426 W.
    e, br, ch, ld = _setup([24.0], [KIND_RELAY], [True], [True], [0.1], (0.0, 0.0, 1500.0, 0.0))
    sol = solve_bus(e, br, ch, ld)
    assert not sol.supplied[0]
    assert sol.load_a[0] == 0.0


def test_under_voltage_lockout_drops_the_load() -> None:
    e, br, ch, ld = _setup([24.0], [KIND_RELAY], [True], [True], [0.1], (30.0, 0.0, 0.0, 22.0))
    sol = solve_bus(e, br, ch, ld)  # 24 - 3 = 21 V < 22 V lock-out
    assert not sol.supplied[0]
    assert sol.string_a[0, 0] == 0.0


def test_cc_cv_charger_regulates_voltage_and_limits_current() -> None:
    # Charger at 25 V / 10 A into a 20 V battery behind 0.1 Ohm: current-limited at 10 A.
    e, br, ch, ld = _setup([20.0], [KIND_RELAY], [True], [True], [0.1], charger=(True, 25.0, 10.0))
    sol = solve_bus(e, br, ch, ld)
    assert abs(sol.charger_a[0] - 10.0) < 1e-9
    assert abs(sol.string_a[0, 0] + 10.0) < 1e-9
    # Into a 24.9 V battery: voltage-regulated, current = (25 - 24.9)/(0.1 + 0.001 + 0.01).
    e, br, ch, ld = _setup([24.9], [KIND_RELAY], [True], [True], [0.1], charger=(True, 25.0, 10.0))
    sol = solve_bus(e, br, ch, ld)
    assert abs(sol.charger_a[0] - 0.1 / 0.111) < 1e-9


def test_fleet_of_packs_solves_in_one_call() -> None:
    e = np.array([[24.0, 22.0], [23.0, 23.0], [20.0, 25.0]])
    n = 2
    br = switch_branches(
        np.array([KIND_RELAY] * n),
        np.zeros(n),
        np.full(n, 0.6),
        np.full(n, 0.002),
        np.ones((3, n), bool),
        np.ones((3, n), bool),
        np.ones((3, n), bool),
        np.full((3, n), 0.02),
    )
    ch = ChargerSource(np.zeros(3, bool), np.zeros(3), np.zeros(3), np.full(3, 0.01))
    ld = LoadSink(np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    sol = solve_bus(e, br, ch, ld)
    np.testing.assert_allclose(sol.bus_v, [23.0, 23.0, 22.5])
    np.testing.assert_allclose(sol.string_a[:, 0], [50.0, 0.0, -125.0])


@budget(300)
@given(
    st.lists(st.floats(5.0, 120.0), min_size=1, max_size=7),
    st.data(),
)
def test_compiled_kernel_matches_numpy_reference(e, data) -> None:  # type: ignore[no-untyped-def]
    from packpilot.model.bus_kernel import solve_bus_fast

    n = len(e)
    kinds = data.draw(st.lists(st.sampled_from([KIND_RELAY, KIND_MOSFET]), min_size=n, max_size=n))
    chg = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    dsg = data.draw(st.lists(st.booleans(), min_size=n, max_size=n))
    r = data.draw(st.lists(st.floats(0.001, 0.5), min_size=n, max_size=n))
    load = (
        data.draw(st.floats(0.0, 80.0)),
        data.draw(st.sampled_from([0.0, 0.05])),
        data.draw(st.sampled_from([0.0, 50.0, 800.0])),
        data.draw(st.sampled_from([0.0, 20.0])),
    )
    charger = data.draw(st.sampled_from([None, (True, 60.0, 20.0), (True, 130.0, 100.0)]))
    args = _setup(e, kinds, chg, dsg, r, load, charger)
    ref = solve_bus(*args)
    fast = solve_bus_fast(*args)
    np.testing.assert_allclose(fast.bus_v, ref.bus_v, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(fast.string_a, ref.string_a, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(fast.charger_a, ref.charger_a, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(fast.supplied, ref.supplied)
