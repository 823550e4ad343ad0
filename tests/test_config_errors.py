"""Bad configuration and bad data files give one clear line naming the culprit."""

from __future__ import annotations

import copy
import time
from pathlib import Path
from typing import Any

import pytest

from packpilot.config import load_config, parse_config
from packpilot.errors import ConfigError, InputError
from packpilot.model import loads
from tests.conftest import dual_pack


def _write(tmp_path: Path, text: str, name: str = "c.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


BASE = """
[pack]
cell = "ecm_example"
[[pack.batteries]]
name = "A"
cells_per_group = 6
soc0 = 0.5
"""


def test_unknown_key_is_named(tmp_path: Path) -> None:
    p = _write(tmp_path, BASE + "bogus_key = 1\n")
    with pytest.raises(ConfigError, match=r"c\.toml: pack\.batteries\.0\.bogus_key: unknown key"):
        load_config(p)


def test_negative_capacity_is_named(tmp_path: Path) -> None:
    p = _write(tmp_path, BASE + "capacity_ah = -5.0\n")
    with pytest.raises(
        ConfigError, match=r"pack\.batteries\.0\.capacity_ah: .*greater than or equal to 0\.001"
    ):
        load_config(p)


def test_nan_capacity_is_named(tmp_path: Path) -> None:
    p = _write(tmp_path, BASE + "capacity_ah = nan\n")
    with pytest.raises(ConfigError, match=r"pack\.batteries\.0\.capacity_ah"):
        load_config(p)


def test_soc_out_of_range_is_named() -> None:
    cfg = dual_pack()
    cfg["pack"]["batteries"][0]["soc0"] = 1.5
    cfg["pack"]["batteries"][0].pop("ocv0_v")
    with pytest.raises(ConfigError, match=r"pack\.batteries\.0\.soc0"):
        parse_config(cfg)


def test_group_list_length_mismatch() -> None:
    cfg = dual_pack()
    cfg["pack"]["batteries"][0].update(series_groups=2, group_soc0=[0.5])
    with pytest.raises(ConfigError, match="group_soc0 has 1 entries but series_groups is 2"):
        parse_config(cfg)


def test_duplicate_battery_names() -> None:
    cfg = dual_pack()
    cfg["pack"]["batteries"][1]["name"] = "A"
    with pytest.raises(ConfigError, match="repeated: A"):
        parse_config(cfg)


def test_not_toml(tmp_path: Path) -> None:
    p = _write(tmp_path, "[pack\nname=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml")


def test_unknown_cell_set_is_named() -> None:
    from packpilot.sim.runner import Runner

    cfg = dual_pack(cell="no_such_cell")
    with pytest.raises(ConfigError, match="no_such_cell"):
        Runner(parse_config(cfg))


@pytest.mark.parametrize(
    ("body", "match"),
    [
        ("t_s,current_a\n0,1\n1,\n2,3\n", r"row 3, column current_a: empty cell \(gap\)"),
        ("t_s,current_a\n0,1\n1,abc\n", r"row 3, column current_a: 'abc' is not a number"),
        ("t_s,current_a\n0,1\n0,2\n", r"row 3, column t_s: time 0 does not increase"),
        ("t_s,volts\n0,1\n", "header must be t_s plus exactly one of"),
        ("t_s,current_a\n", "no data rows"),
        ("t_s,current_a\n0,1\n1,12,5\n", r"row 3 has 3 cells, header has 2"),
    ],
)
def test_bad_profile_csv_names_the_row(tmp_path: Path, body: str, match: str) -> None:
    p = _write(tmp_path, body, "prof.csv")
    with pytest.raises(InputError, match=match):
        loads.from_csv(p)


def test_profile_csv_zero_order_hold(tmp_path: Path) -> None:
    p = _write(tmp_path, "t_s,power_w\n0,100\n10,200\n20,0\n", "prof.csv")
    prof = loads.from_csv(p)
    assert prof.kind == "power"
    assert prof.at(0.0) == 100.0
    assert prof.at(9.99) == 100.0
    assert prof.at(10.0) == 200.0
    assert prof.at(25.0) == 0.0


@pytest.mark.parametrize("axis", ["ocv_soc", "rc_soc"])
def test_non_monotonic_soc_axis_is_named(tmp_path: Path, axis: str) -> None:
    """A cell parameter file whose SOC axis is not strictly increasing (issue 2, bad input)."""
    import json

    from packpilot.model.cell import load_parameter_file

    data = json.loads((Path(loads.__file__).parent.parent / "data/cells/uav_5ah.json").read_text())
    data[axis][1], data[axis][2] = data[axis][2], data[axis][1]
    p = _write(tmp_path, json.dumps(data), "bad_cell.json")
    with pytest.raises(ConfigError, match=rf"bad_cell.json.*{axis}.*strictly increasing"):
        load_parameter_file(p)
    toml = _write(tmp_path, BASE.replace('"ecm_example"', f'"{p}"'))
    from packpilot.sim.runner import Runner

    with pytest.raises(ConfigError, match=axis):
        Runner(load_config(toml))


@pytest.mark.parametrize(
    ("section", "match"),
    [
        (
            {"protection": {"parameters": [{"name": "P1", "cutoff_v": "x", "t_max_s": 1}]}},
            r"c\.toml: protection\.parameters\.0\.cutoff_v: .*valid number.* \(got 'x'\)",
        ),
        ({"sequencing": {"v_th": -1.0}}, r"c\.toml: sequencing\.v_th: .*greater than 0"),
        ({"charging": {"eps_eq_v": 5.0}}, r"c\.toml: charging: eps_eq_v \(5\.0\) must be smaller"),
        ({"equalization": {"bogus": 1}}, r"c\.toml: equalization\.bogus: unknown key"),
        ({"supervisor": {"join_limit_v": 0}}, r"c\.toml: supervisor\.join_limit_v: .*greater"),
        ({"limits": {"rows": [{"bogus": 1}]}}, r"c\.toml: limits\.rows\.0\.limit: Field required"),
        ({"plausibility": {"stuck_time_s": 0.0}}, r"c\.toml: plausibility: stuck_time_s must"),
        ({"soc": {"blend": 2}}, r"c\.toml: soc: blend must be within 0\.\.1"),
        (
            {"controller": ["protection", "bogus"]},
            r"c\.toml: controller\.1: Input should be 'protection', .* \(got 'bogus'\)",
        ),
    ],
)
def test_a_section_error_names_the_field_path(section: dict[str, object], match: str) -> None:
    """Every method / safety section is typed in ScenarioConfig: one formatter, one line, the
    whole path from the top of the file."""
    cfg = dual_pack()
    cfg.update(section)
    with pytest.raises(ConfigError, match=match):
        parse_config(cfg, "c.toml")


def test_sections_are_typed_and_a_listed_method_defaults() -> None:
    from packpilot.config.protection import ProtectionConfig
    from packpilot.config.sequencing import SequencingConfig

    cfg = parse_config({**dual_pack(), "controller": ["sequencing"], "protection": {}})
    assert isinstance(cfg.protection, ProtectionConfig)
    assert cfg.sequencing is None and cfg.section("sequencing") == SequencingConfig()
    assert not cfg.supervised
    assert parse_config({**dual_pack(), "soc": {}}).supervised


@pytest.mark.parametrize(
    ("sim", "match"),
    [
        ({"dt_s": 1.1754943508222875e-38}, r"sim\.dt_s: .*greater than or equal to 0\.0001"),
        ({"dt_s": 1e-4, "duration_s": 1.0e5}, r"sim: duration_s / dt_s = 1e\+09 periods"),
    ],
)
def test_a_run_without_end_is_refused(sim: dict[str, float], match: str) -> None:
    # dt_s = 1.2e-38 (drawn by the config fuzz) meant ~1e37 periods: a hang, not an error
    d = dual_pack()
    d["sim"] = {**d.get("sim", {}), **sim}
    with pytest.raises(ConfigError, match=match):
        parse_config(d)


def test_the_longest_allowed_run_is_accepted() -> None:
    d = dual_pack()
    d["sim"] = {**d.get("sim", {}), "dt_s": 1e-3, "duration_s": 1.0e5}  # exactly 1e8 periods
    assert parse_config(d).sim.dt_s == 1e-3


# ------------------------------------------------------- issue #26 §3: ranges and list sizes


def _full_scenario() -> dict[str, Any]:
    """Every section present with its defaults (dumped), on a two-battery pack with a charger:
    the schema's every number, from the models, not from an example."""
    from packpilot.config.scenario import SECTIONS, ScenarioConfig

    cfg: dict[str, Any] = {
        "pack": {
            "batteries": [
                {"name": "A", "cells_per_group": 6, "soc0": 0.5},
                {"name": "B", "cells_per_group": 6, "soc0": 0.5},
            ]
        },
        "controller": ["sequencing", "protection", "charging", "equalization"],
        "charger": {"present": True, "rated_a": 50.0, "current_a": 10.0, "voltage_v": 30.0},
        "load": {"kind": "current", "value": 5.0},
        "balancer": {"present": True},
    }
    for name, model in SECTIONS.items():
        cfg[name] = model().model_dump(mode="json", exclude_none=True)
    full = ScenarioConfig.model_validate(cfg).model_dump(mode="json", exclude_none=True)
    full.pop("faults")
    return full


def _numbers(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    if isinstance(node, dict):
        return [p for k, v in node.items() for p in _numbers(v, (*path, k))]
    if isinstance(node, list):
        return [p for i, v in enumerate(node) for p in _numbers(v, (*path, i))]
    is_num = isinstance(node, int | float) and not isinstance(node, bool)
    return [path] if is_num else []


def _at(cfg: Any, path: tuple[Any, ...]) -> Any:
    for key in path[:-1]:
        cfg = cfg[key]
    return cfg


@pytest.mark.parametrize("value", [1e300, -1e300])
def test_every_number_of_the_schema_has_a_physical_range(value: float) -> None:
    """Issue #26: thresholds that switch a rule off were accepted (``i_rev = 1e300``). Every
    number anywhere in a full scenario, set to +-1e300, is refused with the field named."""
    full = _full_scenario()
    parse_config(full)
    accepted, unnamed = [], []
    for path in _numbers(full):
        cfg = copy.deepcopy(full)
        _at(cfg, path)[path[-1]] = value
        try:
            parse_config(cfg, "f.toml")
        except ConfigError as err:
            names = [str(k) for k in path if not isinstance(k, int)]
            if names[-1] not in str(err) and names[-2] not in str(err):
                unnamed.append(f"{'.'.join(map(str, path))}: {err}")
        else:
            accepted.append(".".join(map(str, path)))
    assert len(_numbers(full)) > 200
    assert not accepted, accepted
    assert not unnamed, unnamed


@pytest.mark.parametrize(
    ("section", "key", "value"),
    [
        ("sequencing", "i_rev", 1e300),
        ("sequencing", "i_det", 1e300),
        ("sequencing", "v_th", 1e300),
        ("sequencing", "q_rev_as", 1e300),
        ("sequencing", "i_rev", 25.0),
        ("equalization", "dv_set_v", 9.2e18),
        ("equalization", "dv_set_v", 1.5),
        ("charging", "v_sat_v", 1e-12),
        ("charger", "current_a", 1e308),
        ("charger", "current_a", 60.0),  # above rated_a = 50
        ("charger", "heartbeat_timeout_s", 1e6),
        ("supervisor", "join_limit_v", 1e6),
        ("plausibility", "range_delay_s", 1e6),
        ("soc", "rest_current_a", 1e6),
    ],
)
def test_thresholds_of_issue_26_are_refused(section: str, key: str, value: float) -> None:
    cfg = _full_scenario()
    cfg[section][key] = value
    with pytest.raises(ConfigError, match=rf"f\.toml: {section}\b.*{key}"):
        parse_config(cfg, "f.toml")


def test_repeated_method_in_controller_is_refused() -> None:
    cfg = _full_scenario()
    cfg["controller"] = ["protection", "protection"]
    with pytest.raises(ConfigError, match=r"controller: each method runs once; repeated: prot"):
        parse_config(cfg, "f.toml")


def test_more_methods_than_exist_is_refused_before_each_is_checked() -> None:
    cfg = _full_scenario()
    cfg["controller"] = ["protection", "sequencing", "charging", "equalization"] * 4
    with pytest.raises(ConfigError, match=r"controller: at most 4 methods"):
        parse_config(cfg, "f.toml")


def test_t_max_below_a_millisecond_is_refused() -> None:
    """``t_max_s = 1e-12`` rounded to 0 ms passed and divided by zero compiling the table."""
    cfg = _full_scenario()
    cfg["protection"]["parameters"][0]["t_max_s"] = 1e-12
    with pytest.raises(ConfigError, match=r"protection\.parameters\.0.*t_max_s.*0\.001"):
        parse_config(cfg, "f.toml")


def test_a_million_entry_list_is_refused_at_once(tmp_path: Path) -> None:
    """A 10^6-entry list took 34 s and 5.4 GB before a traceback: the length is checked on the
    parsed TOML first (and a file past 1 MiB is not parsed at all)."""
    cfg = _full_scenario()
    cfg["limits"]["rows"] = cfg["limits"]["rows"] * 50  # 1,200 rows, well under 1 MiB
    t0 = time.perf_counter()
    with pytest.raises(
        ConfigError, match=r"f\.toml: limits\.rows: at most 1,024 entries, got 1,200"
    ):
        parse_config(cfg, "f.toml")
    p = tmp_path / "big.toml"
    p.write_text("[pack]\nbatteries = [" + "0," * 1_000_000 + "]\n")
    with pytest.raises(ConfigError, match=r"big\.toml: 2,000,0\d\d bytes; a scenario file has at"):
        load_config(p)
    assert time.perf_counter() - t0 < 2.0


def test_a_table_whose_coverage_grid_is_too_large_is_refused_before_the_check() -> None:
    cfg = _full_scenario()
    rows = [
        {"param": "P1", "ranges": {"current_a": f"({k}, {k + 1}]", "temp_c": f"({k}, {k + 1}]"}}
        for k in range(250)
    ]  # 250 rows x 503 x 503 grid cells: minutes of coverage check
    cfg["protection"]["table"] = rows
    t0 = time.perf_counter()
    with pytest.raises(ConfigError, match=r"protection.*grid too large"):
        parse_config(cfg, "f.toml")
    assert time.perf_counter() - t0 < 2.0
