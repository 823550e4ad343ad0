"""Bad configuration and bad data files give one clear line naming the culprit."""

from __future__ import annotations

from pathlib import Path

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
