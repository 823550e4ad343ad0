"""Physics of the pack plant on the real cell model: cross-currents, diodes, conservation."""

from __future__ import annotations

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.sim.runner import Runner
from tests.conftest import dual_pack


def test_parallel_batteries_two_volts_apart_cross_current_50a_and_decay() -> None:
    res = Runner(parse_config(dual_pack(duration_s=120.0))).run()
    cur = res.trace.channel("current_a")
    # 2 V across 2 x 20 mOhm: 50 A, the spec's example, flowing from A into B.
    assert cur[0, 0] == pytest.approx(50.0, abs=1.0)
    assert cur[0, 1] == pytest.approx(-50.0, abs=1.0)
    # Decays as they equalize (monotone once the RC branches have charged).
    assert abs(cur[-1, 0]) < 0.5 * abs(cur[0, 0])
    assert np.all(np.diff(np.abs(cur[10:, 0])) <= 1e-9)


def test_charge_conserved_between_parallel_batteries() -> None:
    runner = Runner(parse_config(dual_pack(duration_s=300.0)))
    soc0, _ = runner.pack.cell_states()
    cap = runner.pack.capacity_ah[0]
    q0 = soc0[0] * cap
    runner.run()
    soc1, _ = runner.pack.cell_states()
    q1 = soc1[0] * cap
    dq_a = q1[:6].mean() - q0[:6].mean()
    dq_b = q1[6:].mean() - q0[6:].mean()
    assert dq_a < -0.01  # A gave charge
    assert abs(dq_a + dq_b) <= 1e-9 * abs(dq_a)


def test_charge_fet_off_blocks_charging_but_discharges_through_body_diode() -> None:
    sw = {"kind": "mosfet_pair", "on_ohm": 0.0005, "diode_drop_v": 0.6}
    cfg = dual_pack(switch=sw, duration_s=5.0)
    runner = Runner(parse_config(cfg))
    # Battery B (the low one) has its charge FET off: it must not be charged by A.
    runner.pack.set_gates(np.array([[True, False]]), np.array([[True, True]]))
    runner.controller = _Hold()
    res = runner.run()
    cur = res.trace.channel("current_a")
    assert np.all(cur[:, 1] >= -1e-9)
    assert np.all(np.abs(cur[:, 0]) <= 1e-9)  # nothing else to supply: no current at all

    # Now a load that pulls the bus below B + diode drop: B discharges through the diode.
    cfg2 = dual_pack(
        switch=sw, v_a=22.2, v_b=22.2, duration_s=2.0, load={"kind": "current", "value": 40.0}
    )
    runner2 = Runner(parse_config(cfg2))
    runner2.pack.set_gates(np.array([[True, False]]), np.array([[True, True]]))
    runner2.controller = _Hold()
    res2 = runner2.run()
    i_a = res2.trace.channel("current_a")[0]
    v_bat = res2.trace.channel("voltage_v")[0]
    bus = res2.trace.bus_v[0]
    assert i_a[1] > 1.0  # B supplies through its charge-FET body diode
    assert res2.trace.channel("chg_diode_a")[0, 1] == pytest.approx(i_a[1])
    # Drop across B's switch = diode drop + slope + one FET channel.
    drop = v_bat[1] - bus
    expected = 0.6 + i_a[1] * (0.002 + 0.0005)
    assert drop == pytest.approx(expected, abs=1e-9)


def test_both_fets_off_pass_nothing() -> None:
    sw = {"kind": "mosfet_pair", "chg_on": False, "dsg_on": False}
    cfg = dual_pack(switch=sw, duration_s=1.0, load={"kind": "current", "value": 5.0})
    res = Runner(parse_config(cfg)).run()
    assert np.all(res.trace.channel("current_a") == 0.0)
    assert res.metrics["events"].get("LoadUnsupplied", 0) == 1
    assert res.metrics["load_unsupplied_s"] == pytest.approx(1.0)


class _Hold:
    """Expresses no opinion: the gates stay as set on the plant."""

    def step(self, meas, dt_s):  # type: ignore[no-untyped-def]
        from packpilot.contract.bms import Commands, ControlOutput

        return ControlOutput(commands=Commands())


def test_fleet_of_packs_steps_in_one_call_and_matches_single_packs() -> None:
    """Pack(n_packs=N) advances N independent packs together; each equals its own run."""
    from packpilot.model.pack import Pack

    cfg = parse_config(dual_pack(load={"kind": "current", "value": 20.0}))
    scales = np.array([0.9, 1.0, 1.1])
    fleet = Pack(cfg, n_packs=3, capacity_scale=scales, ambient_c=np.array([0.0, 25.0, 40.0]))
    singles = [
        Pack(cfg, n_packs=1, capacity_scale=scales[k : k + 1], ambient_c=np.array([a]))
        for k, a in enumerate([0.0, 25.0, 40.0])
    ]
    for _ in range(50):
        out = fleet.step(0.1, "current", np.full(3, 20.0))
        for k, single in enumerate(singles):
            one = single.step(0.1, "current", np.array([20.0]))
            np.testing.assert_allclose(out.string_a[k], one.string_a[0], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(out.bus_v[k], one.bus_v[0], rtol=1e-12)
    soc_f, temp_f = fleet.cell_states()
    assert soc_f[0].mean() < soc_f[2].mean()  # less capacity drains faster
    assert temp_f[2].mean() > temp_f[0].mean()
