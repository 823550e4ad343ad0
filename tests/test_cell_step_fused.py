"""The fused closed-loop step ``cell.step`` == ``thevenin`` (at the start state) + ``advance``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.model.cell import (
    CellParams,
    CellState,
    advance,
    initial_state,
    load_parameter_set,
    step,
    thevenin,
)
from tests.budget import budget


def _variants() -> dict[str, CellParams]:
    """Shipped sets plus 2-RC, linear-extrapolation and one-node thermal variants."""
    sets = {name: load_parameter_set(name) for name in ("ecm_example", "uav_5ah", "lfp_storage")}
    ecm = sets["ecm_example"]
    sets["ecm_example_2rc"] = replace(
        ecm, name="ecm_2rc", r2_ohm=ecm.r1_ohm * 0.5, c2_f=ecm.c1_f * 20.0
    )
    sets["ecm_example_linear"] = replace(ecm, extrapolation="linear")
    sets["uav_5ah_linear_1node"] = replace(
        sets["uav_5ah"],
        extrapolation="linear",
        thermal=replace(sets["uav_5ah"].thermal, nodes=1),
    )
    sets["lfp_1node"] = replace(
        sets["lfp_storage"], thermal=replace(sets["lfp_storage"].thermal, nodes=1)
    )
    return sets


SETS = _variants()


def _random_case(
    p: CellParams, seed: int, wide: bool, n: int = 96
) -> tuple[CellState, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Random states; ``wide`` puts SoC and temperatures outside the tables as well."""
    rng = np.random.default_rng(seed)
    lo, hi = (-0.3, 1.3) if wide else (0.0, 1.0)
    t_lo, t_hi = (-45.0, 80.0) if wide else (-20.0, 50.0)
    state = CellState(
        soc=rng.uniform(lo, hi, n),
        eta_v=rng.uniform(-0.05, 0.2, (n, p.n_rc)),
        temp_c=rng.uniform(t_lo, t_hi, n),
        jig_temp_c=rng.uniform(t_lo, t_hi, n),
    )
    scale = p.capacity_ah / 100.0
    cur = rng.uniform(-600.0, 900.0, n) * scale  # charge and discharge
    cur[:4] = [0.0, p.rc_current_a[0], p.rc_current_a[-1], p.rc_current_a[1]]  # on nodes
    state.temp_c[4:7] = [p.rc_temp_c[0], p.rc_temp_c[-1], p.dudt_temp_c[1]]
    amb = rng.uniform(-20.0, 45.0, n)
    cap = p.capacity_ah * rng.uniform(0.9, 1.1, n)
    rs = rng.uniform(0.7, 1.5, n)
    return state, cur, amb, cap, rs


def _assert_same_state(a: CellState, b: CellState) -> None:
    for name in ("soc", "eta_v", "temp_c", "jig_temp_c"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@budget(200)
@given(
    name=st.sampled_from(sorted(SETS)),
    seed=st.integers(0, 2**32 - 1),
    dt=st.sampled_from([0.01, 0.1, 1.0, 10.0]),
    wide=st.booleans(),
)
def test_step_equals_thevenin_then_advance(name: str, seed: int, dt: float, wide: bool) -> None:
    p = SETS[name]
    state, cur, amb, cap, rs = _random_case(p, seed, wide)
    before = state.copy()
    e, r0 = thevenin(p, state, cur, cap, rs)
    ref, heat_ref = advance(p, state, cur, dt, amb, cap, rs)
    v, new, heat = step(p, state, cur, dt, amb, cap, rs)
    # the kernel may fuse e - r0 I into one FMA: equal to rounding
    np.testing.assert_allclose(v, e - r0 * cur, rtol=1e-14, atol=1e-12)
    _assert_same_state(new, ref)
    np.testing.assert_array_equal(heat, heat_ref)
    _assert_same_state(state, before)  # the input state is not modified


@pytest.mark.parametrize("name", sorted(SETS))
def test_step_trajectory_matches_thevenin_advance_loop(name: str) -> None:
    """200 closed-loop steps with changing current and ambient: same voltages and states."""
    p = SETS[name]
    n = 16
    rng = np.random.default_rng(7)
    a = initial_state(p, n, rng.uniform(0.3, 0.9, n), rng.uniform(-10.0, 40.0, n))
    b = a.copy()
    cap, rs = p.capacity_ah * rng.uniform(0.95, 1.05, n), rng.uniform(0.9, 1.2, n)
    for k in range(200):
        cur = p.capacity_ah * rng.uniform(-1.0, 3.0, n)
        amb = 25.0 + 10.0 * np.sin(0.05 * k)
        e, r0 = thevenin(p, a, cur, cap, rs)
        a, qa = advance(p, a, cur, 0.5, amb, cap, rs)
        v, b, qb = step(p, b, cur, 0.5, amb, cap, rs)
        np.testing.assert_allclose(v, e - r0 * cur, rtol=0.0, atol=1e-12)
        np.testing.assert_array_equal(qa, qb)
    _assert_same_state(a, b)


def test_step_broadcasts_scalars_and_validates() -> None:
    p = load_parameter_set("uav_5ah")
    s = initial_state(p, 3, [0.2, 0.5, 0.9], 25.0)
    v, new, heat = step(p, s, 10.0, 1.0, 25.0, p.capacity_ah, 1.0)
    assert v.shape == heat.shape == new.soc.shape == (3,)
    e, r0 = thevenin(p, s, 10.0, p.capacity_ah, 1.0)
    np.testing.assert_allclose(v, e - 10.0 * r0, rtol=0.0, atol=1e-12)
    with pytest.raises(ValueError, match="dt_s"):
        step(p, s, 10.0, 0.0, 25.0, p.capacity_ah, 1.0)
    bad = CellState(s.soc, np.zeros((3, 2)), s.temp_c, s.jig_temp_c)
    with pytest.raises(ValueError, match="eta_v"):
        step(p, bad, 10.0, 1.0, 25.0, p.capacity_ah, 1.0)


def test_step_nan_stays_nan() -> None:
    p = load_parameter_set("ecm_example")
    s = initial_state(p, 3, [np.nan, 0.5, 0.5], [25.0, np.nan, 25.0])
    v, new, heat = step(p, s, np.array([10.0, 10.0, np.nan]), 1.0, 25.0, 100.0, 1.0)
    assert np.isnan(v[0]) and np.isnan(new.soc[0]) and np.isnan(new.temp_c[1])
    assert np.isnan(heat[2]) and np.isnan(v[2])
