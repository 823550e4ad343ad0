"""The state of power reads the SOC observer's polarisation and R0 where the observer is
trusted (issue #28: §1's estimates feed §3). Without them, after a heavy load the limits
from the cell set alone were up to 38 % too high at low SOC (benchmarks/RESULTS.md, h28b)."""

from __future__ import annotations

import math

import numpy as np

from packpilot.config import load_config
from packpilot.control.power import PowerInputs, state_of_power
from packpilot.sim.power import inputs_from_core, params_of
from tests.conftest import EXAMPLES

CFG = load_config(EXAMPLES / "uav_dual_parallel.toml")
PRM = params_of(CFG)


def _inputs(**observed: np.ndarray) -> PowerInputs:
    n = PRM.series.shape[0]
    v = float(np.interp(0.3, PRM.ocv_soc, PRM.ocv_v))
    yes = np.ones(n, bool)
    return inputs_from_core(
        CFG, soc=np.full(n, 0.3), temp_c=np.full(n, 25.0), current_a=np.zeros(n),
        voltage_v=PRM.series * v, min_cell_v=np.full(n, v), max_cell_v=np.full(n, v),
        present=yes, chg_on=yes, dsg_on=yes, prm=PRM, **observed,
    )  # fmt: skip


def _dsg_10s(inp: PowerInputs) -> float:
    return float(state_of_power(PRM, inp).pack_dsg_a[0, 1])


def test_observed_polarisation_and_resistance_lower_the_discharge_limit() -> None:
    n = PRM.series.shape[0]
    plain = _inputs()
    pol = np.full(n, 0.3)  # V, a battery still polarised by a long heavy load
    polarised = _inputs(polarisation_v=pol)
    assert np.all(polarised.v1_v[0] == 0.3) and np.all(polarised.v2_v[0] == 0.0)
    assert _dsg_10s(polarised) < 0.97 * _dsg_10s(plain)
    r0 = 2.0 * plain.r0_ohm[0]
    aged = _inputs(r0_ohm=r0)
    assert np.all(aged.r0_ohm[0] == r0) and np.all(aged.r_per_a[0] == 0.0)
    assert _dsg_10s(aged) < 0.97 * _dsg_10s(plain)


def test_where_the_observer_is_not_trusted_the_cell_set_stands() -> None:
    n = PRM.series.shape[0]
    plain = _inputs()
    untrusted = _inputs(polarisation_v=np.full(n, math.nan), r0_ohm=np.full(n, math.nan))
    assert np.array_equal(untrusted.v1_v, plain.v1_v)
    assert np.array_equal(untrusted.r0_ohm, plain.r0_ohm)
    assert _dsg_10s(untrusted) == _dsg_10s(plain)
