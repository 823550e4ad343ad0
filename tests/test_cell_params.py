"""Parameter sets: shipped data, provenance, PyBaMM equality, validation of user files."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.errors import ConfigError
from packpilot.model.cell import (
    PARAMETER_SETS,
    CellParams,
    initial_state,
    load_parameter_file,
    load_parameter_set,
    ocv_v,
    parameter_set_path,
    params_to_dict,
    thevenin,
    write_parameter_file,
)


@pytest.mark.parametrize("name", PARAMETER_SETS)
def test_shipped_sets_load(name: str) -> None:
    p = load_parameter_set(name)
    assert p.name == name
    assert p.n_rc == 1
    assert p.capacity_ah > 0 and p.v_min_v < p.v_max_v
    assert len(p.provenance) > 100
    assert load_parameter_set(name) is p  # parsed once
    # monotonic OCV over 0..1 and inside the voltage limits
    ocv = ocv_v(p, np.linspace(0, 1, 201), 25.0)
    assert np.all(np.diff(ocv) > 0)
    assert p.v_min_v <= ocv[0] and ocv[-1] <= p.v_max_v + 1e-9


def test_ecm_example_equals_pybamm() -> None:
    os.environ["PYBAMM_DISABLE_TELEMETRY"] = "true"
    pybamm = pytest.importorskip("pybamm")
    p = load_parameter_set("ecm_example")
    pv = pybamm.ParameterValues("ECM_Example")
    assert pv["Cell capacity [A.h]"] == p.capacity_ah
    assert pv["Cell thermal mass [J/K]"] == p.thermal.cell_heat_capacity_j_per_k
    assert pv["Jig thermal mass [J/K]"] == p.thermal.jig_heat_capacity_j_per_k
    assert pv["Cell-jig heat transfer coefficient [W/K]"] == p.thermal.cell_jig_w_per_k
    assert pv["Jig-air heat transfer coefficient [W/K]"] == p.thermal.jig_air_w_per_k
    assert pv["Lower voltage cut-off [V]"] == p.v_min_v
    assert pv["Upper voltage cut-off [V]"] == p.v_max_v
    from pybamm.input.parameters.ecm import example_set as ex  # type: ignore[import-untyped]

    for key, (name, (x, y)) in (
        ("r0_ohm", ex.r0_data),
        ("r1_ohm", ex.r1_data),
        ("c1_f", ex.c1_data),
    ):
        assert name
        for ours, theirs in zip((p.rc_temp_c, p.rc_current_a, p.rc_soc), x, strict=True):
            np.testing.assert_array_equal(ours, theirs)
        np.testing.assert_array_equal(getattr(p, key), y)
    _, (x, y) = ex.ocv_data
    np.testing.assert_array_equal(p.ocv_soc, x[0])
    np.testing.assert_array_equal(p.ocv_table_v, y)
    _, (x, y) = ex.dUdT_data
    np.testing.assert_array_equal(p.dudt_x, x[0])
    np.testing.assert_array_equal(p.dudt_temp_c, x[1])
    np.testing.assert_array_equal(p.dudt_v_per_k, y)
    assert p.dudt_axis == "ocv_v" and p.ocv_ref_temp_c is None


def test_uav_5ah_scaling() -> None:
    p = load_parameter_set("uav_5ah")
    assert p.capacity_ah == 5.0
    np.testing.assert_allclose(ocv_v(p, [0.0, 1.0], 25.0), [3.0, 4.2], atol=1e-12)
    s = initial_state(p, 1, 0.5, 25.0)
    _, r0 = thevenin(p, s, 30.0, 5.0, 1.0)
    from packpilot.model.cell.reference import _np_interp3

    r1 = _np_interp3(p, "r1_ohm", np.array([25.0]), np.array([30.0]), np.array([0.5]))
    assert r0[0] + r1[0] == pytest.approx(3.0e-3, rel=1e-9)
    assert 6 * (r0[0] + r1[0]) == pytest.approx(18e-3, rel=1e-6)  # 6S ~ 20 mOhm with wiring
    assert p.thermal.cell_heat_capacity_j_per_k == pytest.approx(50.0)
    ecm = load_parameter_set("ecm_example")
    # time constants unchanged by the scaling
    np.testing.assert_allclose(p.r1_ohm * p.c1_f, ecm.r1_ohm * ecm.c1_f, rtol=1e-12)
    # the discharge-protection cut-offs sit inside the OCV range
    soc_at = np.interp(
        [2.8, 3.0, 3.2], ocv_v(p, np.linspace(-0.05, 1, 400), 25.0), np.linspace(-0.05, 1, 400)
    )
    assert soc_at[0] < 0.0 <= soc_at[1] + 1e-9 and soc_at[2] < 0.1


def test_uav_5ah_resistance_is_arrhenius_20_kj_per_mol() -> None:
    """The documented temperature law of uav_5ah (README.md, docs/discharge_protection.md):
    R0 and R1 follow exp(Ea/R (1/T - 1/T')) with Ea = 20 kJ/mol on every table node, so the
    30 A / 50 % DCIR is 2.9x its 25 degC value at -10 degC and 4.1x at -20 degC."""
    p = load_parameter_set("uav_5ah")
    inv_t = 1.0 / (p.rc_temp_c + 273.15)
    for tab in (p.r0_ohm, p.r1_ohm):
        ea = np.diff(np.log(tab), axis=0) / np.diff(inv_t)[:, None, None] * 8.314462618
        np.testing.assert_allclose(ea, 20e3, rtol=1e-4)
    from packpilot.model.cell.reference import _np_interp3

    def dcir(temp_c: float) -> float:
        args = (np.array([temp_c]), np.array([30.0]), np.array([0.5]))
        return float((_np_interp3(p, "r0_ohm", *args) + _np_interp3(p, "r1_ohm", *args))[0])

    assert dcir(-10.0) / dcir(25.0) == pytest.approx(2.89, abs=0.01)
    assert dcir(-20.0) / dcir(25.0) == pytest.approx(4.15, abs=0.01)


def test_lipo_pouch_ocv_is_ecker2015_and_the_rest_uav_5ah() -> None:
    """lipo_pouch (#27: a sourced LiPo pouch OCV for `packpilot fit --chemistry`): its OCV is
    PyBaMM Ecker2015's full-cell curve (Kokam SLPB 75106100) between the 2.5 / 4.2 V limits,
    recomputed here from the electrode OCPs; resistances and thermal data are uav_5ah's."""
    pybamm = pytest.importorskip("pybamm")
    p = load_parameter_set("lipo_pouch")
    uav = load_parameter_set("uav_5ah")
    pv = pybamm.ParameterValues("Ecker2015")
    param = pybamm.LithiumIonParameters()
    x0, x100, y100, y0 = pybamm.lithium_ion.ElectrodeSOHSolver(
        pv, param
    ).get_min_max_stoichiometries()
    soc = np.array([0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0])
    up = pv.evaluate(param.p.prim.U(pybamm.Vector(y0 + soc * (y100 - y0)), 298.15)).ravel()
    un = pv.evaluate(param.n.prim.U(pybamm.Vector(x0 + soc * (x100 - x0)), 298.15)).ravel()
    np.testing.assert_allclose(ocv_v(p, soc, 25.0), up - un, atol=1e-9)
    np.testing.assert_allclose(ocv_v(p, [0.0, 1.0], 25.0), [2.5, 4.2], atol=1e-6)
    assert np.all(np.diff(p.ocv_table_v) > 0)
    np.testing.assert_array_equal(p.r0_ohm, uav.r0_ohm)
    np.testing.assert_array_equal(p.c1_f, uav.c1_f)
    assert p.thermal == uav.thermal
    assert "Ecker2015" in p.provenance and "BSD-3-Clause" in p.provenance


def test_lfp_storage_shape() -> None:
    p = load_parameter_set("lfp_storage")
    ocv = ocv_v(p, np.linspace(0, 1, 101), 25.0)
    assert ocv[0] == pytest.approx(3.0) and ocv[-1] == pytest.approx(3.45)
    plateau = ocv[10:95]
    assert plateau.max() - plateau.min() < 0.12  # flat
    assert np.all(np.diff(ocv) > 0)
    assert p.dudt_axis == "soc" and np.abs(p.dudt_v_per_k).max() <= 0.4e-3
    assert p.v_max_v == 3.65


def test_unknown_set_name() -> None:
    with pytest.raises(ConfigError, match="unknown"):
        load_parameter_set("nope")


def test_roundtrip(tmp_path: Path) -> None:
    p = load_parameter_set("uav_5ah")
    out = tmp_path / "uav.json"
    write_parameter_file(p, out)
    q = load_parameter_file(out)
    for key, value in params_to_dict(p).items():
        other = params_to_dict(q)[key]
        if isinstance(value, list):
            np.testing.assert_array_equal(np.array(value), np.array(other))
        else:
            assert value == other
    assert out.read_text() == parameter_set_path("uav_5ah").read_text()


def _user_file(tmp_path: Path, **changes: Any) -> Path:
    data = json.loads(parameter_set_path("ecm_example").read_text())
    for key, value in changes.items():
        if value is _DELETE:
            del data[key]
        elif callable(value):
            data[key] = value(data[key])
        else:
            data[key] = value
    path = tmp_path / "user.json"
    path.write_text(json.dumps(data))
    return path


_DELETE = object()


def _shuffle_axis(axis: list[float]) -> list[float]:
    return [axis[1], axis[0], *axis[2:]]


def _drop_last_soc(table: list[list[list[float]]]) -> list[list[list[float]]]:
    return [[row[:-1] for row in plane] for plane in table]


def _nan_corner(table: list[list[list[float]]]) -> list[list[list[float]]]:
    table[0][0][0] = float("nan")
    return table


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"capacity_ah": float("nan")}, "capacity_ah"),
        ({"capacity_ah": 0.0}, "capacity_ah"),
        ({"capacity_ah": -5.0}, "capacity_ah"),
        ({"rc_soc": _shuffle_axis}, "rc_soc"),
        ({"rc_temp_c": _shuffle_axis}, "rc_temp_c"),
        ({"ocv_soc": _shuffle_axis}, "ocv_soc"),
        ({"r1_ohm": _drop_last_soc}, "r1_ohm"),
        ({"c1_f": _nan_corner}, "c1_f"),
        ({"ocv_table_v": lambda v: v[:-1]}, "ocv_table_v"),
        ({"dudt_v_per_k": lambda v: v[:-1]}, "dudt_v_per_k"),
        ({"r0_ohm": lambda t: [[[-x for x in r] for r in pl] for pl in t]}, "r0_ohm"),
        ({"v_min_v": 4.3}, "v_min_v"),
        ({"extrapolation": "cubic"}, "extrapolation"),
        ({"dudt_axis": "voltage"}, "dudt_axis"),
        ({"r2_ohm": lambda _: None}, "c2_f"),  # r2 given without c2
        ({"thermal": lambda th: {**th, "nodes": 3}}, "thermal.nodes"),
        ({"thermal": lambda th: {**th, "cell_jig_w_per_k": 0}}, "thermal.cell_jig_w_per_k"),
        ({"thermal": lambda th: {k: v for k, v in th.items() if k != "nodes"}}, "thermal.nodes"),
        ({"provenance": _DELETE}, "provenance"),
        ({"colour": "red"}, "colour"),
    ],
)
def test_bad_files_rejected_naming_the_field(
    tmp_path: Path, changes: dict[str, Any], field: str
) -> None:
    if "r2_ohm" in changes:  # r2 without c2
        path = _user_file(tmp_path)
        data = json.loads(path.read_text())
        data["r2_ohm"] = data["r1_ohm"]
        path.write_text(json.dumps(data))
    else:
        path = _user_file(tmp_path, **changes)
    with pytest.raises(ConfigError) as err:
        load_parameter_file(path)
    msg = str(err.value)
    assert f"'{field}'" in msg or f"{field}:" in msg, msg
    assert str(path) in msg
    assert "\n" not in msg


def test_bad_json_and_missing_file(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"name": ')
    with pytest.raises(ConfigError, match="line 1"):
        load_parameter_file(bad)
    with pytest.raises(ConfigError, match="cannot read"):
        load_parameter_file(tmp_path / "missing.json")


def test_direct_construction_validates() -> None:
    p = load_parameter_set("ecm_example")
    from dataclasses import replace

    with pytest.raises(ConfigError, match="'rc_current_a'"):
        replace(p, rc_current_a=p.rc_current_a[::-1].copy())
    q: CellParams = replace(p, name="copy")
    assert not q.r0_ohm.flags.writeable
