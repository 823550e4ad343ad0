"""State of power and the join planner (issue #28 items 3-4): the compiled prediction of
``control/power`` on hand-built packs whose answers are known in closed form, and its bus
solve against the plant's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from packpilot.control import power as pw
from packpilot.control.power import rules
from packpilot.errors import ConfigError
from packpilot.model.bus import ChargerSource, LoadSink
from packpilot.model.bus_kernel import solve_bus_fast
from packpilot.model.switches import switch_branches

N = 6  # cells in series
OCV = ([0.0, 1.0], [3.5, 3.5])  # a flat OCV: EMF = 21 V at every SOC


def params(b: int = 2, *, relay: bool = False, ocv: tuple[list[float], list[float]] = OCV,
           v_min: float = 3.0, t_max: float = 60.0, t_min_chg: float = 0.0,
           horizons: tuple[float, ...] = (2.0, 10.0, 30.0),
           iters: int = 30) -> pw.PowerParams:  # fmt: skip
    """30 bisection steps: these tests check the physics to 1e-6 (the default, 16, is
    checked for what it promises in test_the_default_bisection_is_within_its_bound_below)."""
    return pw.make_params(
        ocv_soc=ocv[0], ocv_v=ocv[1], series=[N] * b, relay=[relay] * b, on_ohm=[0.0005] * b,
        diode_drop_v=[0.6] * b, diode_ohm=[0.002] * b, cell_v_min=[v_min] * b,
        cell_v_max=[4.2] * b, temp_max_dsg_c=[t_max] * b, temp_max_chg_c=[45.0] * b,
        temp_min_chg_c=[t_min_chg] * b, heat_j_per_k=[1e9] * b, horizons_s=horizons,
        iters=iters,
    )  # fmt: skip


def inputs(r0: list[float], *, cap: float = 1e6, lim_d: float = math.inf,
           lim_c: float = math.inf, packs: int = 1) -> pw.PowerInputs:  # fmt: skip
    inp = pw.new_inputs(packs, len(r0))
    inp.soc[:] = 0.5
    inp.capacity_ah[:] = cap
    inp.r0_ohm[:] = r0
    inp.limit_dsg_a[:] = lim_d
    inp.limit_chg_a[:] = lim_c
    return inp


def test_cutoff_limit_is_the_ohms_law_answer() -> None:
    # No RC, no SOC change: the battery's own terminal (before its switch) reaches the
    # cut-off at (E - n*v_min) / R0.
    prm = params(1)
    out = pw.state_of_power(prm, inputs([0.02]))
    expect = (N * 3.5 - N * 3.0) / 0.02
    assert out.pack_dsg_a[0] == pytest.approx([expect] * 3, rel=1e-6)
    assert list(out.why_dsg[0]) == [pw.WHY_CUTOFF] * 3
    # power: that current at the bus voltage it leaves (n*v_min minus the switch drop)
    assert out.pack_dsg_w[0, 0] == pytest.approx(expect * (N * 3.0 - expect * 0.001), rel=1e-6)


def test_the_default_bisection_is_within_its_bound_below() -> None:
    """The published limit is at most ``2**-iters`` of the bisection's upper bound (here the
    short-circuit current, E / R) below the exact answer, and never above it."""
    prm = params(1, iters=pw.make_params.__kwdefaults__["iters"])
    assert prm.iters == 16
    out = pw.state_of_power(prm, inputs([0.02]))
    expect = (N * 3.5 - N * 3.0) / 0.02
    bound = N * 3.5 / (0.02 + 0.001)  # E over R0 and the two channels in series
    for got in out.pack_dsg_a[0]:
        assert expect - bound * 2.0**-16 <= got <= expect


def test_without_the_batteries_alone_the_packs_limits_are_the_same() -> None:
    """The runtime asks for the pack's limits only (``alone=False``): the same pack and
    share figures, each battery's own left NaN (not zeros: "none" is not "unknown")."""
    prm = params(3)
    inp = inputs([0.02, 0.03, 0.05], lim_d=80.0, lim_c=30.0)
    inp.soc[0] = [0.3, 0.5, 0.7]
    inp.r1_ohm[:] = 0.01
    inp.tau1_s[:] = 20.0
    full = pw.state_of_power(prm, inp)
    pack = pw.state_of_power(prm, inp, alone=False)
    for name in ("pack_dsg_a", "pack_chg_a", "pack_dsg_w", "pack_chg_w", "share_dsg_a",
                 "share_chg_a", "why_dsg", "who_dsg", "why_chg", "who_chg"):  # fmt: skip
        assert np.array_equal(getattr(pack, name), getattr(full, name)), name
    assert np.isnan(pack.alone_dsg_a).all() and np.isnan(pack.alone_chg_a).all()
    assert np.isfinite(full.alone_dsg_a).all() and (full.alone_dsg_a > 0).all()
    ten = pw.state_of_power(prm, inp, alone=10.0)  # the report's: the 10 s horizon only
    assert np.array_equal(ten.alone_dsg_a[:, :, 1], full.alone_dsg_a[:, :, 1])
    assert np.array_equal(ten.alone_chg_a[:, :, 1], full.alone_chg_a[:, :, 1])
    assert np.isnan(ten.alone_dsg_a[:, :, [0, 2]]).all()
    assert np.array_equal(ten.pack_dsg_a, full.pack_dsg_a)
    with pytest.raises(ConfigError, match=r"no horizon of 5\.0 s"):
        pw.state_of_power(prm, inp, alone=5.0)


def test_a_held_current_is_held_and_a_little_more_is_not() -> None:
    prm = params(2)
    inp = inputs([0.02, 0.03])
    inp.r1_ohm[:] = 0.02
    inp.tau1_s[:] = 20.0
    out = pw.state_of_power(prm, inp)
    wk = pw.new_work(1, 2)
    for k, t in enumerate(prm.horizons_s):
        i = out.pack_dsg_a[0, k]
        assert rules.hold(prm, inp, wk, 0, -1, i, t) == pw.WHY_NONE
        assert rules.hold(prm, inp, wk, 0, -1, i * 1.001, t) != pw.WHY_NONE
    # polarisation builds over the horizon: the longer the horizon, the less
    assert out.pack_dsg_a[0, 0] > out.pack_dsg_a[0, 1] > out.pack_dsg_a[0, 2]


def test_polarisation_already_there_lowers_the_limit() -> None:
    prm = params(1)
    inp = inputs([0.02])
    before = pw.state_of_power(prm, inp).pack_dsg_a[0, 0]
    inp.v1_v[:] = 0.5
    inp.tau1_s[:] = 1e6
    after = pw.state_of_power(prm, inp).pack_dsg_a[0, 0]
    assert after == pytest.approx(before - 0.5 / 0.02, rel=1e-6)


def test_a_sagging_soc_is_seen_over_the_horizon() -> None:
    # OCV falls with SOC: a small battery loses voltage within 30 s, a huge one does not.
    prm = params(1, ocv=([0.0, 1.0], [3.0, 4.2]))
    small = pw.state_of_power(prm, inputs([0.02], cap=0.5)).pack_dsg_a[0]
    big = pw.state_of_power(prm, inputs([0.02], cap=1e6)).pack_dsg_a[0]
    assert big[2] == pytest.approx(big[0], rel=1e-5)
    assert small[2] < 0.9 * big[2]


def test_identical_batteries_give_twice_one() -> None:
    prm = params(2)
    out = pw.state_of_power(prm, inputs([0.02, 0.02], lim_d=100.0))
    assert out.pack_dsg_a[0] == pytest.approx(2 * out.alone_dsg_a[0, 0], rel=1e-6)
    assert out.share_dsg_a[0, 0] == pytest.approx(out.share_dsg_a[0, 1], rel=1e-9)


def test_fresh_and_aged_get_what_the_split_gives_not_twice_the_weakest() -> None:
    # Same current limit (60 A) each; the fresh battery (10 mOhm) takes twice the aged one's
    # (20 mOhm) current, so it reaches 60 A when the aged one carries ~30 A: the pack holds
    # ~90 A, not 2 x 60 A (N x weakest), and the fresh battery is the one that binds.
    prm = params(2)
    out = pw.state_of_power(prm, inputs([0.01, 0.02], lim_d=60.0))
    r = (0.011, 0.021)
    expect = 60.0 + 60.0 * r[0] / r[1]
    assert out.pack_dsg_a[0, 0] == pytest.approx(expect, rel=1e-6)
    assert out.who_dsg[0, 0] == 0 and out.why_dsg[0, 0] == pw.WHY_CURRENT
    assert out.pack_dsg_a[0, 0] < 2 * min(out.alone_dsg_a[0, :, 0])
    assert out.share_dsg_a[0, 0, 0] == pytest.approx(60.0, rel=1e-6)
    # ... and where the split says so, the pack gets more than twice the weakest alone:
    # an aged battery with a low current limit but a high resistance takes a small share.
    inp2 = inputs([0.01, 0.05])
    inp2.limit_dsg_a[0, :] = [60.0, 15.0]
    out2 = pw.state_of_power(prm, inp2)
    assert out2.pack_dsg_a[0, 0] > 2 * out2.alone_dsg_a[0, 1, 0]


def test_p_packs_equal_one_pack_at_a_time() -> None:
    inp = inputs([0.01, 0.02], packs=3, lim_d=80.0)
    inp.soc[:] = [[0.2, 0.3], [0.5, 0.5], [0.9, 0.7]]
    inp.r1_ohm[:] = [[0.01, 0.02], [0.02, 0.02], [0.03, 0.01]]
    inp.tau1_s[:] = 15.0
    prm = params(2, ocv=([0.0, 1.0], [3.0, 4.2]))
    many = pw.state_of_power(prm, inp)
    for p in range(3):
        one = inputs([0.0, 0.0])
        for f in one._fields:
            getattr(one, f)[0] = getattr(inp, f)[p]
        single = pw.state_of_power(prm, one)
        assert np.array_equal(single.pack_dsg_a[0], many.pack_dsg_a[p])
        assert np.array_equal(single.share_chg_a[0], many.share_chg_a[p])


def test_temperature_limits() -> None:
    prm = params(1)
    inp = inputs([0.02])
    inp.temp_c[:] = 61.0
    out = pw.state_of_power(prm, inp)
    assert out.pack_dsg_a[0, 0] == 0.0 and out.why_dsg[0, 0] == pw.WHY_TEMP
    inp.temp_c[:] = -5.0  # below the charge minimum (0 degC): no charge, discharge fine
    out = pw.state_of_power(prm, inp)
    assert out.pack_chg_a[0, 0] == 0.0 and out.why_chg[0, 0] == pw.WHY_TEMP
    assert out.pack_dsg_a[0, 0] > 0.0


def test_heating_over_the_horizon_limits_a_long_hold() -> None:
    prm = params(1, t_max=30.0)
    prm = prm._replace(heat_j_per_k=np.array([200.0]))
    inp = inputs([0.02])
    inp.temp_c[:] = 25.0
    out = pw.state_of_power(prm, inp)
    # 5 K of headroom in 30 s with 200 J/K: I^2 R <= 5 * 200 / 30 -> I <= 40.8 A
    assert out.pack_dsg_a[0, 2] == pytest.approx(math.sqrt(1000.0 / 30.0 / 0.02), rel=1e-3)
    assert out.why_dsg[0, 2] == pw.WHY_TEMP


def test_charge_limit_and_cell_maximum() -> None:
    prm = params(1)
    inp = inputs([0.02], lim_c=15.0)
    out = pw.state_of_power(prm, inp)
    assert out.pack_chg_a[0, 0] == pytest.approx(15.0) and out.why_chg[0, 0] == pw.WHY_CURRENT
    inp = inputs([0.02])
    inp.high_cell_v[:] = 0.6  # the highest cell is already 0.1 V below the 4.2 V maximum
    out = pw.state_of_power(prm, inp)
    assert out.pack_chg_a[0, 0] == pytest.approx(N * 0.1 / 0.02, rel=1e-6)


def test_body_diodes_and_open_switches() -> None:
    prm = params(1)
    inp = inputs([0.02])
    inp.dsg_on[:] = False  # discharge FET off: its diode blocks discharge
    out = pw.state_of_power(prm, inp)
    assert out.pack_dsg_a[0, 0] == 0.0 and out.pack_chg_a[0, 0] > 0.0
    inp = inputs([0.02])
    inp.chg_on[:] = False  # charge FET off: discharge through its diode (0.6 V, 2 mOhm)
    diode = pw.state_of_power(prm, inp)
    assert diode.pack_chg_a[0, 0] == 0.0
    # the same current reaches the cut-off (it is the battery's), at a lower bus voltage
    assert diode.pack_dsg_a[0, 0] == pytest.approx(150.0, rel=1e-6)
    assert diode.pack_dsg_w[0, 0] == pytest.approx(150.0 * (18.0 - 0.6 - 150.0 * 0.0025), rel=1e-6)
    both = pw.state_of_power(prm, inputs([0.02]))
    assert both.pack_dsg_w[0, 0] == pytest.approx(150.0 * (18.0 - 150.0 * 0.001), rel=1e-6)
    relay = params(1, relay=True)
    inp = inputs([0.02])
    inp.chg_on[:] = False  # a relay is closed only with both
    out = pw.state_of_power(relay, inp)
    assert out.pack_dsg_a[0, 0] == 0.0 and out.pack_chg_a[0, 0] == 0.0


@pytest.mark.parametrize("seed", range(40))
def test_bus_solve_is_the_plants(seed: int) -> None:
    rng = np.random.default_rng(seed)
    b = int(rng.integers(1, 6))
    kind = rng.integers(0, 2, b)
    chg = rng.random(b) < 0.7
    dsg = rng.random(b) < 0.7
    e = rng.uniform(18.0, 25.0, b)
    r = rng.uniform(0.005, 0.05, b)
    load = float(rng.uniform(0.0, 300.0))
    prm = pw.make_params(
        ocv_soc=[0.0, 1.0], ocv_v=[3.0, 4.2], series=[6] * b, relay=list(kind == 0),
        on_ohm=[0.001] * b, diode_drop_v=[0.6] * b, diode_ohm=[0.003] * b,
        cell_v_min=[3.0] * b, cell_v_max=[4.2] * b, temp_max_dsg_c=[60.0] * b,
        temp_max_chg_c=[45.0] * b, heat_j_per_k=[1.0] * b,
    )  # fmt: skip
    inp = inputs(list(r))
    inp.chg_on[0] = chg
    inp.dsg_on[0] = dsg
    wk = pw.new_work(1, b)
    rules.start(prm, inp, wk, 0, -1)
    wk.e[0] = e
    v = rules.bus_voltage(wk, 0, load)
    br = switch_branches(kind, np.full(b, 0.001), np.full(b, 0.6), np.full(b, 0.003),
                         chg[None], dsg[None], np.ones((1, b), bool), r[None])  # fmt: skip
    no = np.zeros(1)
    sol = solve_bus_fast(e[None], br, ChargerSource(np.zeros(1, bool), no, no, np.ones(1)),
                         LoadSink(np.array([load]), no, no, no))  # fmt: skip
    if not sol.supplied[0]:
        assert math.isnan(v)
        return
    assert v == pytest.approx(sol.bus_v[0], rel=1e-12, abs=1e-12)
    for s in range(b):
        assert rules.string_current(wk, 0, s, v) == pytest.approx(sol.string_a[0, s], abs=1e-9)


def test_join_peak_is_dv_over_the_loop_resistance() -> None:
    for relay, sw in ((True, 0.0005), (False, 0.001)):
        prm = params(2, relay=relay)
        inp = inputs([0.02, 0.03])
        plan = pw.plan_join(prm, inp, 1, 1.5)
        assert plan.bus_v == pytest.approx(N * 3.5)
        assert plan.peak_a == pytest.approx(1.5 / (0.02 + 0.03 + 2 * sw), rel=1e-9)
        below = pw.plan_join(prm, inp, 1, -1.5)
        assert below.peak_a == pytest.approx(-plan.peak_a, rel=1e-9)


def test_join_decays_through_the_rc_branches_and_times_it() -> None:
    prm = params(2, relay=True)
    inp = inputs([0.02, 0.02])
    inp.r1_ohm[:] = 0.05
    inp.tau1_s[:] = 10.0
    plan = pw.plan_join(prm, inp, 1, 1.0, horizon_s=60.0, n_steps=6000, limit_a=20.0)
    r0 = 0.02 + 0.02 + 0.001
    assert plan.peak_a == pytest.approx(1.0 / r0, rel=1e-9)
    # settles towards dV / (R0s + R1s): 1 / 0.141 = 7.1 A, below the 20 A limit
    assert plan.end_a == pytest.approx(1.0 / 0.141, rel=1e-2)
    assert 0.0 < plan.over_s < 60.0
    # The loop's RC voltage builds with time constant tau * R0 / (R0 + R1): the current is
    # I(t) = dV/R_inf + (dV/R0 - dV/R_inf) exp(-t/tau_loop), tau_loop = tau*(R0/(R0+R1)).
    tau_loop = 10.0 * r0 / (r0 + 0.1)
    i_inf, i0 = 1.0 / 0.141, 1.0 / r0
    t_half = -tau_loop * math.log((0.5 * i0 - i_inf) / (i0 - i_inf))
    assert plan.half_s == pytest.approx(t_half, abs=0.02)


def test_join_under_load_and_admissible_dv() -> None:
    prm = params(2)
    inp = inputs([0.02, 0.02])
    # the other battery carries 40 A: the bus sits 40 * 0.021 V below its EMF. Joining at
    # that bus voltage (dV = 0) takes no current; joining at the other's EMF splits the load.
    plan = pw.plan_join(prm, inp, 1, 0.0, load_a=40.0)
    assert plan.bus_v == pytest.approx(N * 3.5 - 40.0 * 0.021)
    assert plan.peak_a == pytest.approx(0.0, abs=1e-9)
    plan = pw.plan_join(prm, inp, 1, 40.0 * 0.021, load_a=40.0)
    assert plan.peak_a == pytest.approx(20.0, rel=1e-9)
    # dV admissible for 50 A through the switch: 50 A x the loop resistance, per pack
    dv = pw.admissible_dv(prm, inputs([0.02, 0.02]), 1, 50.0)
    assert dv == pytest.approx(50.0 * 0.042, rel=1e-6)
    dv_aged = pw.admissible_dv(prm, inputs([0.02, 0.06]), 1, 50.0)
    assert dv_aged == pytest.approx(50.0 * 0.082, rel=1e-6)
    down = pw.admissible_dv(prm, inputs([0.02, 0.02]), 1, 10.0, sign=-1.0)
    assert down == pytest.approx(10.0 * 0.042, rel=1e-6)


def test_join_through_a_body_diode() -> None:
    # The joining MOSFET pair closes only its discharge FET: it can only discharge, through
    # the charge FET's diode (0.6 V); below the bus it takes nothing.
    prm = params(2)
    inp = inputs([0.02, 0.02])
    inp.chg_on[0, 1] = False
    up = pw.plan_join(prm, inp, 1, 1.0)
    assert up.peak_a == pytest.approx(0.4 / (0.02 + 0.001 + 0.02 + 0.0025), rel=1e-9)
    down = pw.plan_join(prm, inp, 1, -1.0)
    assert down.peak_a == 0.0
    assert pw.admissible_dv(prm, inp, 1, 5.0, sign=-1.0, dv_max=30.0) == 30.0


def test_bad_inputs_say_what() -> None:
    with pytest.raises(ConfigError, match="relay has 1 entries, need 2"):
        pw.make_params(
            ocv_soc=[0, 1], ocv_v=[3, 4], series=[6, 6], relay=[True], on_ohm=[0, 0],
            diode_drop_v=[0, 0], diode_ohm=[1, 1], cell_v_min=[3, 3], cell_v_max=[4, 4],
            temp_max_dsg_c=[60, 60], temp_max_chg_c=[45, 45], heat_j_per_k=[1, 1],
        )  # fmt: skip
    with pytest.raises(ConfigError, match="shaped"):
        pw.state_of_power(params(2), inputs([0.02]))
    with pytest.raises(ConfigError, match="no battery 5"):
        pw.plan_join(params(2), inputs([0.02, 0.02]), 5, 1.0)


def test_the_lowest_cell_reaches_the_cutoff_first() -> None:
    prm = params(1)
    inp = inputs([0.02])
    inp.low_cell_v[:] = 0.1  # one cell sits 0.1 V below the average
    out = pw.state_of_power(prm, inp)
    assert out.pack_dsg_a[0, 0] == pytest.approx((N * 3.5 - N * 3.1) / 0.02, rel=1e-6)


def test_a_warming_battery_loses_resistance_and_gains_power() -> None:
    prm = params(1, ocv=([0.0, 1.0], [3.0, 4.2]))._replace(heat_j_per_k=np.array([300.0]))
    inp = inputs([0.03], cap=5.0)
    inp.soc[:] = 0.2
    inp.temp_c[:] = 5.0
    still = pw.state_of_power(prm, inp).pack_dsg_a[0]
    inp.r_per_k[:] = -0.03
    warm = pw.state_of_power(prm, inp).pack_dsg_a[0]
    assert warm[0] == pytest.approx(still[0], rel=0.02)  # 2 s: barely warmer
    assert warm[2] > 1.05 * still[2]  # 30 s: a few kelvin, 10 % less resistance at the end
