"""The compiled plant step (``Pack.step``) against its NumPy reference (``Pack.step_reference``).

Two plants are built from the same scenario and driven with the same inputs — gates, welded
relays, shorted FETs, balancer and aux DC/DC currents, charger requests and faults, cooling
failures, loads of every kind — one stepped by each implementation; every ``Interval`` field
and the whole plant state must agree after every step.
"""

from __future__ import annotations

import copy
import json
from dataclasses import fields
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

from packpilot.config import parse_config
from packpilot.model import cell as cellmod
from packpilot.model.charger import FLAG_NAMES
from packpilot.model.numerics import pairwise_sum as _pairwise
from packpilot.model.numerics import segment_sum as _segment
from packpilot.model.pack import Interval, Pack
from packpilot.model.pack_kernel import segment_sums
from tests.budget import budget
from tests.conftest import dual_pack

TOL: dict[str, float] = {"rtol": 1e-9, "atol": 1e-9}
SETS = ("uav_5ah", "ecm_example", "lfp_storage")


@pytest.fixture(scope="module")
def two_rc_set(tmp_path_factory: pytest.TempPathFactory) -> str:
    """A 2-RC variant of ``uav_5ah`` (two ``eta_v`` columns) with a temperature-dependent OCV."""
    data = cellmod.params_to_dict(cellmod.load_parameter_set("uav_5ah"))
    data["name"] = "uav_5ah_2rc"
    data["r2_ohm"] = (np.asarray(data["r1_ohm"]) * 0.5).tolist()
    data["c2_f"] = (np.asarray(data["c1_f"]) * 20.0).tolist()
    data["ocv_ref_temp_c"] = 25.0
    path = tmp_path_factory.mktemp("cells") / "uav_5ah_2rc.json"
    path.write_text(json.dumps(data), encoding="utf-8")
    return str(path)


# ------------------------------------------------------------------------------ scenarios
@st.composite
def scenario(draw: st.DrawFn, extra_set: str) -> tuple[dict[str, Any], dict[str, Any], int]:
    """(config dict, Pack keyword arguments, seed of the per-step inputs)."""
    sets = (*SETS, extra_set)
    n_traction = draw(st.integers(1, 4))
    groups = draw(st.integers(1, 3))
    batteries: list[dict[str, Any]] = []
    for k in range(n_traction):
        kind = draw(st.sampled_from(["relay", "mosfet_pair"]))
        sw: dict[str, Any] = {
            "kind": kind,
            "on_ohm": draw(st.sampled_from([0.0, 1e-4, 5e-4, 2e-3])),
            "diode_drop_v": draw(st.floats(0.0, 0.8)),
            "diode_ohm": draw(st.floats(1e-3, 0.02)),
            "chg_on": draw(st.booleans()),
            "dsg_on": draw(st.booleans()),
            "welded": kind == "relay" and draw(st.booleans()),
        }
        batteries.append(
            {
                "name": f"B{k}",
                "cell": draw(st.sampled_from(sets)),
                "series_groups": groups,
                "cells_per_group": draw(st.integers(1, 3)),
                "soc0": draw(st.floats(0.05, 0.95)),
                "capacity_ah": draw(st.sampled_from([None, 5.0, 20.0])),
                "cell_soc_spread": draw(st.floats(0.0, 0.05)),
                "cell_capacity_spread": draw(st.floats(0.0, 0.1)),
                "switch": sw,
                "present_from_s": draw(st.sampled_from([0.0, 0.0, 0.35, 1.2])),
                "ambient_offset_c": draw(st.floats(-5.0, 10.0)),
            }
        )
    if draw(st.booleans()):
        batteries.insert(
            draw(st.integers(0, len(batteries))),
            {
                "name": "AUX",
                "role": "aux",
                "cell": "lfp_storage",
                "series_groups": draw(st.integers(1, 4)),
                "cells_per_group": 1,
                "capacity_ah": 10.0,
                "soc0": draw(st.floats(0.1, 0.9)),
            },
        )
    kind = draw(st.sampled_from(["current", "power", "resistance", "none"]))
    cfg = {
        "pack": {"cell": "uav_5ah", "seed": draw(st.integers(0, 99)), "batteries": batteries},
        "load": {"kind": kind, "value": 1.0, "v_min_v": draw(st.sampled_from([0.0, 2.0, 9.0]))},
        "charger": {
            "present": draw(st.booleans()),
            "connect_s": draw(st.sampled_from([0.0, 0.5])),
            "disconnect_s": draw(st.sampled_from([None, 1.5])),
            "r_out_ohm": draw(st.sampled_from([0.01, 0.1])),
            "rated_a": 40.0,
            "heartbeat_timeout_s": draw(st.sampled_from([0.25, 5.0])),
        },
        "balancer": {
            "present": draw(st.booleans()),
            "max_current_a": draw(st.floats(0.1, 3.0)),
            "bidirectional": draw(st.booleans()),
            "efficiency": draw(st.floats(0.5, 1.0)),
        },
        "aux": {
            "dcdc_max_a": draw(st.floats(0.5, 5.0)),
            "dcdc_efficiency": draw(st.floats(0.5, 1.0)),
            "dcdc_min_input_v": draw(st.sampled_from([0.0, 3.0, 20.0])),
            "bms_load_w": draw(st.floats(0.0, 20.0)),
        },
        "sim": {"dt_s": draw(st.sampled_from([0.05, 0.1, 1.0])), "progress": False},
    }
    n_packs = draw(st.integers(1, 3))
    kwargs: dict[str, Any] = {"n_packs": n_packs}
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    n_cells = sum(b["series_groups"] * b["cells_per_group"] for b in batteries)
    if draw(st.booleans()):
        shape = (n_packs,) if draw(st.booleans()) else (n_packs, n_cells)
        kwargs["capacity_scale"] = rng.uniform(0.8, 1.2, shape)
        kwargs["r_scale"] = rng.uniform(0.7, 1.5, shape)
        kwargs["soc_offset"] = rng.uniform(-0.05, 0.05, n_packs)
        kwargs["ambient_c"] = rng.uniform(-10.0, 40.0, n_packs)
    return cfg, kwargs, draw(st.integers(0, 2**31))


def _inputs(rng: np.random.Generator, pack: Pack, kind: str, t: float) -> dict[str, Any]:
    """One period's inputs, drawn once and applied identically to both plants."""
    P, S, G = pack.n_packs, pack.n_strings, pack.n_groups
    value = {
        "current": rng.uniform(0.0, 40.0, P),
        "power": rng.uniform(0.0, 400.0, P),
        "resistance": rng.choice([0.0, 0.3, 1.0, 5.0], P),
        "none": np.zeros(P),
    }[kind]
    inp: dict[str, Any] = {"value": value}
    if rng.random() < 0.4:
        inp["gates"] = (rng.random((P, S)) < 0.7, rng.random((P, S)) < 0.7)
    if rng.random() < 0.15:
        inp["welded"] = (int(rng.integers(S)), bool(rng.random() < 0.5))
    if rng.random() < 0.15:
        inp["shorted"] = (int(rng.integers(P)), int(rng.integers(S)), int(rng.integers(2)))
    if rng.random() < 0.5:
        inp["balancer"] = rng.uniform(-4.0, 4.0, (P, G))
    if rng.random() < 0.5:
        inp["aux"] = rng.uniform(-1.0, 8.0, P)
    inp["requests"] = [
        (p, rng.uniform(0.0, 60.0), rng.uniform(-1.0, 50.0), bool(rng.random() < 0.8), t)
        for p in range(P)
        if rng.random() < 0.7
    ]
    if rng.random() < 0.1:
        inp["fault"] = (int(rng.integers(P)), str(rng.choice(FLAG_NAMES[:4])), rng.random() < 0.5)
    if rng.random() < 0.08:
        inp["cooling"] = (int(rng.integers(S)), float(rng.choice([1.0, 0.3, 0.05])))
    return inp


def _apply(pack: Pack, inp: dict[str, Any]) -> None:
    if "gates" in inp:
        pack.set_gates(*inp["gates"])
    if "welded" in inp:
        pack.welded[inp["welded"][0]] = inp["welded"][1]
    if "shorted" in inp:
        p, s, f = inp["shorted"]
        pack.fet_shorted[p, s, f] = not pack.fet_shorted[p, s, f]
    if "balancer" in inp:
        pack.set_balancer(inp["balancer"])
    if "aux" in inp:
        pack.set_aux_charge(inp["aux"])
    for p, v, a, on, t in inp["requests"]:
        pack.charger.request(p, v, a, on, t)
    if "fault" in inp:
        p, name, on = inp["fault"]
        pack.charger.view(p).set_fault(name, on)
    if "cooling" in inp:
        pack.set_cooling(*inp["cooling"])


# ------------------------------------------------------------------------------ comparison
def _close(a: Any, b: Any, what: str) -> None:
    x, y = np.asarray(a), np.asarray(b)
    assert x.shape == y.shape, f"{what}: shape {x.shape} != {y.shape}"
    if x.dtype == bool or y.dtype == bool:
        np.testing.assert_array_equal(x, y, err_msg=what)
    else:
        np.testing.assert_allclose(x, y, **TOL, err_msg=what)


def _same_interval(a: Interval, b: Interval, k: int) -> None:
    for f in fields(Interval):
        _close(getattr(a, f.name), getattr(b, f.name), f"step {k}: Interval.{f.name}")


PLANT_STATE = (
    "t_s", "string_a", "cell_a", "bus_v", "group_v_prev", "e_cell", "r_cell",
    "chg_diode_s", "dsg_diode_s", "chg_diode_j", "dsg_diode_j", "charge_in_ah", "joule_j",
    "chg_on", "dsg_on", "welded", "fet_shorted", "balancer_a", "aux_charge_a",
)  # fmt: skip
CHARGER_STATE = ("connected", "v_req", "i_req", "on_req", "last_request_s", "flags", "out_v",
                 "out_a")  # fmt: skip


def _same_plant(a: Pack, b: Pack, k: int) -> None:
    for name in PLANT_STATE:
        _close(getattr(a, name), getattr(b, name), f"step {k}: Pack.{name}")
    for name in CHARGER_STATE:
        _close(getattr(a.charger, name), getattr(b.charger, name), f"step {k}: charger.{name}")
    for x, y, name in zip(a.cell_states(), b.cell_states(), ("soc", "temp_c"), strict=True):
        _close(x, y, f"step {k}: cell {name}")
    assert len(a.banks) == len(b.banks)
    for ba, bb in zip(a.banks, b.banks, strict=True):
        np.testing.assert_array_equal(ba.idx, bb.idx)
        for name in ("soc", "eta_v", "temp_c", "jig_temp_c"):
            _close(getattr(ba.state, name), getattr(bb.state, name), f"step {k}: bank {name}")


@budget(200,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(data=st.data())
def test_compiled_step_equals_numpy_reference(two_rc_set: str, data: st.DataObject) -> None:
    cfg_dict, kwargs, seed = data.draw(scenario(two_rc_set))
    cfg = parse_config(cfg_dict)
    fast, ref = Pack(cfg, **kwargs), Pack(cfg, **kwargs)
    _same_plant(fast, ref, -1)
    rng = np.random.default_rng(seed)
    kind, dt = cfg.load.kind, cfg.sim.dt_s
    for k in range(20):
        inp = _inputs(rng, fast, kind, fast.t_s)
        _apply(fast, inp)
        _apply(ref, inp)
        h = dt if rng.random() < 0.8 else 0.5 * dt
        a = fast.step(h, kind, inp["value"])
        b = ref.step_reference(h, kind, inp["value"])
        _same_interval(a, b, k)
        _same_plant(fast, ref, k)


def test_unsupplied_load_and_charger_timeout_match_reference() -> None:
    """Directed: a power load beyond the bus, each charger fault flag, a charger gone silent."""
    cfg = dual_pack(
        switch={"kind": "mosfet_pair", "on_ohm": 1e-4},
        load={"kind": "power", "value": 1.0, "v_min_v": 21.0},
    )
    cfg["charger"] = {"present": True, "heartbeat_timeout_s": 0.3, "rated_a": 20.0}
    fast, ref = (Pack(parse_config(cfg)) for _ in range(2))
    supplied: list[bool] = []
    charging: list[bool] = []
    for k in range(30):
        for pack in (fast, ref):
            if k < 20:
                pack.charger.request(0, 25.2, 10.0, True, pack.t_s)
            if 4 <= k < 12:  # raise, then clear, each fault flag in turn
                pack.charger.view(0).set_fault(FLAG_NAMES[(k - 4) // 2], k % 2 == 0)
        power = np.array([300.0 if k < 20 else 5000.0])
        a = fast.step(0.1, "power", power)
        b = ref.step_reference(0.1, "power", power)
        _same_interval(a, b, k)
        _same_plant(fast, ref, k)
        supplied.append(bool(a.supplied[0]))
        charging.append(bool(a.charger_a[0] > 0.0))
    assert supplied[0] and not supplied[-1]  # the scenario reaches the lock-out
    assert charging[:4] == [True] * 4 and charging[4:12] == [False, True] * 4
    assert fast.charger.flags[0, FLAG_NAMES.index("communication_timeout")]


def test_intervals_are_fresh_arrays() -> None:
    """A kept Interval is not overwritten by later steps (the reference allocates too)."""
    pack = Pack(parse_config(dual_pack(load={"kind": "current", "value": 20.0})))
    first = pack.step(0.1, "current", np.array([20.0]))
    kept = copy.deepcopy(first)
    pack.step(0.1, "current", np.array([35.0]))
    _same_interval(first, kept, 0)


def test_step_rejects_non_positive_dt() -> None:
    pack = Pack(parse_config(dual_pack()))
    with pytest.raises(ValueError, match="dt_s must be > 0"):
        pack.step(0.0, "none", np.zeros(1))


@budget(200)
@given(
    lengths=st.lists(st.integers(1, 600), min_size=1, max_size=4),
    rows=st.integers(1, 3),
    seed=st.integers(0, 2**31),
)
def test_kernel_sums_reproduce_numpy_order(lengths: list[int], rows: int, seed: int) -> None:
    """Segment sums are bit-identical to ``np.add.reduceat`` and ``ndarray.sum``."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal((rows, sum(lengths))) * 10.0 ** rng.uniform(-6, 6, (rows, 1))
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    out = np.empty((rows, len(lengths)))
    segment_sums(x, starts, out)
    assert np.array_equal(out, np.add.reduceat(x, starts, axis=1))
    assert _segment(x[0], starts, 0) == out[0, 0]
    assert _pairwise(x[0], 0, x.shape[1]) == x[0].sum()
