"""``packpilot calibrate protection`` (#15 §4): the cut-off per (current, temperature) cell from
the cell set's OCV and resistance tables at the cell's worst corner."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.config.protection import ProtectionConfig
from packpilot.errors import ConfigError
from packpilot.model.cell import load_parameter_set, ocv_v
from packpilot.model.cell.calibrate import calibrate_protection, cutoff_at, to_toml

UAV = load_parameter_set("uav_5ah")


@pytest.fixture(scope="module")
def calibrated() -> tuple[ProtectionConfig, list[object]]:
    return calibrate_protection(UAV, 0.02)  # type: ignore[return-value]


def test_cutoff_at_zero_current_is_the_ocv_at_the_floor() -> None:
    cut, s_c, drop = cutoff_at(UAV, 0.02, 0.0, 25.0, 15.0)
    assert s_c == 0.02 and drop == 0.0
    assert cut == pytest.approx(float(ocv_v(UAV, [0.02], [25.0])[0]), abs=1e-9)


def test_cutoff_adds_the_charge_of_the_allowance_and_subtracts_i_r() -> None:
    cut, s_c, drop = cutoff_at(UAV, 0.02, 30.0, 25.0, 15.0)
    assert s_c == pytest.approx(0.02 + 30.0 * 15.0 / (3600.0 * 5.0))
    assert 30.0 * 0.002 < drop < 30.0 * 0.006  # ~3 mOhm DCIR at 25 degC
    assert cut == pytest.approx(float(ocv_v(UAV, [s_c], [25.0])[0]) - drop)
    # two cells in parallel: half the current per cell
    cut2, s2, _ = cutoff_at(UAV, 0.02, 30.0, 25.0, 15.0, parallel=2)
    assert s2 == pytest.approx(0.02 + 15.0 * 15.0 / (3600.0 * 5.0)) and cut2 > cut


def test_cutoff_falls_with_current_and_cold() -> None:
    warm = [cutoff_at(UAV, 0.02, i, 25.0, 5.0)[0] for i in (5, 15, 30, 60)]
    cold = [cutoff_at(UAV, 0.02, i, -10.0, 5.0)[0] for i in (5, 15, 30, 60)]
    assert warm == sorted(warm, reverse=True)
    assert all(c < w for c, w in zip(cold, warm, strict=True))


def test_each_cell_takes_its_worst_corner(calibrated: tuple[ProtectionConfig, list]) -> None:  # type: ignore[type-arg]
    cfg, cells = calibrated
    assert len(cells) == len(cfg.table) == len(cfg.parameters) == 121
    by_name = {p.name: p for p in cfg.parameters}
    for row, c in zip(cfg.table, cells, strict=True):
        p = by_name[row.param]
        assert p.cutoff_v == c.cutoff_v
        rng_i, rng_t = row.ranges["current_a"], row.ranges["temp_c"]
        # the corner lies on the cell's edges (clamped to 0 A / the set's coldest table T)
        assert c.corner_current_a in (max(rng_i.lo, 0.0), rng_i.hi, 60.0)
        assert c.corner_temp_c in (rng_t.lo, rng_t.hi, -20.0)
        # no corner of the cell gives a lower cut-off
        for ia in {max(rng_i.lo, 0.0) if math.isfinite(rng_i.lo) else 0.0,
                   rng_i.hi if math.isfinite(rng_i.hi) else 60.0}:  # fmt: skip
            for tc in {rng_t.lo if math.isfinite(rng_t.lo) else -20.0,
                       rng_t.hi if math.isfinite(rng_t.hi) else rng_t.lo}:  # fmt: skip
                assert cutoff_at(UAV, 0.02, ia, tc, p.t_max_s)[0] >= p.cutoff_v - 1e-12
        # rounded down to the mV, never above the exact value
        assert p.cutoff_v <= c.ocv_v - c.drop_v + 1e-12
        assert c.ocv_v - c.drop_v - p.cutoff_v < 1e-3


def test_t_max_comes_from_the_source_table(calibrated: tuple[ProtectionConfig, list]) -> None:  # type: ignore[type-arg]
    cfg, cells = calibrated
    by = {(c.current, c.temp): c for c in cells}
    assert by[("(60, inf)", "[25, 30)")].source_param == "P1"
    assert by[("(-inf, 5]", "[25, 30)")].source_param == "P3"
    assert by[("(15, 20]", "[25, 30)")].source_param == "P2"
    assert by[("(10, 15]", "[10, 15)")].source_param == "P2"
    assert by[("(10, 15]", "(-inf, -10)")].source_param == "P1"
    assert cfg.parameters[0].t_max_s == 15.0
    assert {p.t_max_s for p in cfg.parameters} == {5.0, 10.0, 15.0}


def test_floor_raises_every_cutoff() -> None:
    lo, _ = calibrate_protection(UAV, 0.0)
    hi, _ = calibrate_protection(UAV, 0.05)
    assert all(a.cutoff_v <= b.cutoff_v for a, b in zip(lo.parameters, hi.parameters, strict=True))
    assert (
        sum(a.cutoff_v < b.cutoff_v for a, b in zip(lo.parameters, hi.parameters, strict=True))
        > 100
    )


@pytest.mark.parametrize(
    "kw",
    [
        {"soc_floor": -0.1},
        {"soc_floor": math.nan},
        {"parallel": 0},
        {"current_edges_a": (10, 5)},
        {"temp_edges_c": ()},
    ],
)
def test_bad_arguments_refused(kw: dict[str, object]) -> None:
    floor = kw.pop("soc_floor", 0.02)
    with pytest.raises(ConfigError):
        calibrate_protection(UAV, floor, **kw)  # type: ignore[arg-type]


def test_toml_round_trip(calibrated: tuple[ProtectionConfig, list]) -> None:  # type: ignore[type-arg]
    cfg, cells = calibrated
    text = to_toml(cfg, cells, "header line")
    assert text.startswith("# header line\n[protection]\n")
    back = ProtectionConfig.model_validate(tomllib.loads(text)["protection"])
    assert back == cfg


def test_cli_writes_a_usable_section(tmp_path: Path) -> None:
    out = tmp_path / "prot.toml"
    res = CliRunner().invoke(
        app,
        ["calibrate", "protection", "--cell", "uav_5ah", "--soc-floor", "0.02", "--out", str(out)],
    )
    assert res.exit_code == 0, res.output
    cfg = ProtectionConfig.model_validate(tomllib.loads(out.read_text())["protection"])
    assert cfg == calibrate_protection(UAV, 0.02)[0]
    res = CliRunner().invoke(app, ["calibrate", "protection", "--cell", "uav_5ah"])
    assert res.exit_code == 0 and "[protection]" in res.output


def test_cli_refuses_a_bad_floor_and_an_unknown_cell() -> None:
    res = CliRunner().invoke(
        app, ["calibrate", "protection", "--cell", "uav_5ah", "--soc-floor", "0.7"]
    )
    assert res.exit_code == 2 and "soc floor" in res.output
    res = CliRunner().invoke(app, ["calibrate", "protection", "--cell", "no_such_cell"])
    assert res.exit_code == 2
