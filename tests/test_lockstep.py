"""Lockstep batches (many packs through one vectorized plant and a batch controller) give, per
pack, the metrics of a per-pack closed-loop run with the same draw."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import ScenarioConfig, load_config, parse_config
from packpilot.sim.campaign import (
    Draw,
    draw_run,
    flatten_metrics,
    parse_spreads,
    run_batch,
    run_lockstep_batch,
    run_one,
)
from packpilot.sim.lockstep import run_lockstep, stack_overrides, unsupported_reason

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SPREAD = parse_spreads("capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35")
ID_KEYS = {"run", "seed", "capacity_scale", "r0_scale", "soc0_offset", "ambient_c"}


def _mission(duration_s: float, controller: list[str]) -> ScenarioConfig:
    """The campaign benchmark's mission: two 6S batteries 2 V apart, 20 A."""
    return parse_config(
        {
            "controller": controller,
            "pack": {
                "cell": "ecm_example",
                "switch": {"kind": "mosfet_pair", "on_ohm": 0.0001},
                "batteries": [
                    {"name": "A", "cells_per_group": 6, "ocv0_v": 24.2, "resistance_ohm": 0.02},
                    {"name": "B", "cells_per_group": 6, "ocv0_v": 22.2, "resistance_ohm": 0.02},
                ],
            },
            "load": {"kind": "current", "value": 20.0},
            "sim": {"dt_s": 0.1, "duration_s": duration_s, "progress": False},
        }
    )


def _example(name: str, duration_s: float | None = None) -> ScenarioConfig:
    cfg = load_config(EXAMPLES / name)
    sim = cfg.sim.model_copy(update={"progress": False})
    if duration_s is not None:
        sim = sim.model_copy(update={"duration_s": duration_s})
    return cfg.model_copy(update={"sim": sim})


def _assert_rows_match(rows: list[dict[str, Any]], ref: list[dict[str, Any]]) -> None:
    for row, want in zip(rows, ref, strict=True):
        assert row["status"] == want["status"] == "ok", (row.get("error"), want.get("error"))
        keys = (set(row) | set(want)) - {"wall_time_s", "status", "error"}
        for k in sorted(keys):
            # An event kind a run never emitted is absent (0); any other key must be on both.
            default = 0 if k.startswith("events_") else "missing"
            a, b = row.get(k, default), want.get(k, default)
            if isinstance(b, float) and math.isnan(b):
                assert isinstance(a, float) and math.isnan(a), k
            else:
                assert a == pytest.approx(b, rel=1e-9, abs=1e-12), (k, a, b, row["run"])


def _compare(cfg: ScenarioConfig, draws: list[Draw]) -> list[dict[str, Any]]:
    rows = run_lockstep_batch(cfg, draws)
    assert rows is not None
    _assert_rows_match(rows, [run_one(cfg, d) for d in draws])
    return rows


def test_no_controller_pack_matches_per_pack_runs() -> None:
    """Directly paralleled batteries (no method): cross-charging, drawn spreads per pack."""
    cfg = _mission(120.0, [])
    rows = _compare(cfg, [draw_run(SPREAD, 3, i, 25.0) for i in range(5)])
    assert len({r["capacity_scale"] for r in rows}) == 5
    assert max(r["peak_cross_current_a"] for r in rows) > 5.0  # the plant really cross-charges


def test_sequencing_mission_matches_per_pack_runs() -> None:
    cfg = _mission(120.0, ["sequencing"])
    rows = _compare(cfg, [draw_run(SPREAD, 4, i, 25.0) for i in range(6)])
    assert all(r.get("events_StateChanged", 0) + r.get("events_BatteryJoined", 0) > 0 for r in rows)


@pytest.mark.parametrize(
    ("name", "duration_s"),
    [
        ("sequencing_dual_hover.toml", None),
        ("sequencing_four_spread.toml", 300.0),
        ("sequencing_hot_insert.toml", 400.0),
    ],
)
def test_sequencing_examples_match_per_pack_runs(name: str, duration_s: float | None) -> None:
    """The spec scenarios with drawn spreads; dual_hover runs to its brown-out stop, so packs
    leave the batch at different times (``stop_when_unsupplied_s``)."""
    cfg = _example(name, duration_s)
    spread = parse_spreads("capacity=8%,r0=10%,soc0=0.04")
    draws = [draw_run(spread, 7, i, cfg.pack.ambient_c) for i in range(4)]
    rows = _compare(cfg, draws)
    if duration_s is None:
        steps = {r["steps"] for r in rows}
        assert len(steps) > 1, "packs should stop at different times"
        assert all(r["sim_time_s"] < cfg.sim.duration_s for r in rows)


def test_batch_of_one_equals_member_of_a_batch() -> None:
    cfg = _mission(60.0, ["sequencing"])
    draws = [draw_run(SPREAD, 5, i, 25.0) for i in range(3)]
    many = run_lockstep(cfg, stack_overrides([d.pack_overrides() for d in draws])).metrics
    one = run_lockstep(cfg, stack_overrides([draws[1].pack_overrides()])).metrics[0]
    assert flatten_metrics(one) == flatten_metrics(many[1])


def test_failing_run_in_a_lockstep_batch_is_recorded_and_the_others_finish() -> None:
    """A run that raises aborts the lockstep batch; the batch is split in halves until the
    failing run is alone (run per pack for its error row), and the others give the lockstep
    figures."""
    cfg = _mission(30.0, ["sequencing"])
    draws = [draw_run(SPREAD, 6, i, 25.0) for i in range(4)]
    assert run_lockstep_batch(cfg, draws, frozenset({2})) is None
    rows = run_batch(cfg, draws, frozenset({2}))
    assert [r["status"] for r in rows] == ["ok", "ok", "error", "ok"]
    assert "DeliberateFailure" in rows[2]["error"]
    ok = [d for d in draws if d.run != 2]
    _assert_rows_match([r for r in rows if r["status"] == "ok"], run_lockstep_batch(cfg, ok) or [])


def test_non_finite_pack_is_an_error_row_and_leaves_the_others_alone() -> None:
    """A pack whose state goes non-finite (a NaN ambient temperature, which the draws' clipping
    would never produce, fed in directly) gives the per-pack runner's error row; its
    neighbours in the batch are untouched."""
    cfg = _mission(10.0, ["sequencing"])
    draws = [draw_run(SPREAD, 8, i, 25.0) for i in range(3)]
    draws[1] = Draw(draws[1].run, draws[1].seed, ambient_c=math.nan)
    rows = run_lockstep_batch(cfg, draws)
    assert rows is not None
    ref = [run_one(cfg, d) for d in draws]
    assert [r["status"] for r in rows] == [r["status"] for r in ref] == ["ok", "error", "ok"]
    assert rows[1]["error"] == ref[1]["error"] and "max_temp_c" in rows[1]["error"]
    _assert_rows_match([rows[0], rows[2]], [ref[0], ref[2]])


@pytest.mark.parametrize(
    ("name", "reason"),
    [
        ("evtol_charging.toml", "charger link runs per pack"),
        ("telecom_string.toml", "charger link runs per pack"),
        ("uav_mission.toml", "supervisor / safety layers run per pack"),
        ("protection_cold_heavy.toml", None),
        ("equalization_uav12s.toml", None),
        ("sequencing_dual_hover.toml", None),
        ("smart_battery.toml", None),
    ],
)
def test_unsupported_scenarios_are_named(name: str, reason: str | None) -> None:
    got = unsupported_reason(_example(name))
    if reason is None:
        assert got is None
    else:
        assert got is not None and reason in got
        with pytest.raises(ValueError, match="cannot run in lockstep"):
            run_lockstep(_example(name, 1.0), {"ambient_c": np.array([20.0])})


@pytest.mark.parametrize(
    ("name", "duration_s", "spread"),
    [
        # Runs to its trip and the brown-out stop: packs trip at different times.
        ("protection_cold_heavy.toml", None, "capacity=5%,r0=10%,soc0=0.03,ambient_c=-14:-6"),
        ("protection_warming_flight.toml", 900.0, "capacity=5%,r0=10%,ambient_c=-5:5"),
        ("equalization_uav12s.toml", 240.0, "capacity=3%,r0=10%,soc0=0.02"),
    ],
)
def test_methods_without_twin_match_per_pack_runs(
    name: str, duration_s: float | None, spread: str
) -> None:
    """Methods without a batch twin run one scalar controller per pack on the lockstep plant
    and batch sensors; every metric and event count equals the per-pack run's."""
    cfg = _example(name, duration_s)
    draws = [draw_run(parse_spreads(spread), 9, i, cfg.pack.ambient_c) for i in range(3)]
    rows = _compare(cfg, draws)
    if duration_s is None:
        assert len({r["steps"] for r in rows}) > 1, "packs should stop at different times"
        assert all(r.get("events_ProtectionTripped", 0) == 1 for r in rows)


def test_unsupported_scenario_batch_runs_per_pack() -> None:
    cfg = _example("evtol_charging.toml", 20.0)
    draws = [draw_run({}, 0, i, cfg.pack.ambient_c) for i in range(2)]
    rows = run_batch(cfg, draws)
    assert [r["status"] for r in rows] == ["ok", "ok"]
    assert rows == [
        run_one(cfg, d) | {"wall_time_s": r["wall_time_s"]}
        for d, r in zip(draws, rows, strict=True)
    ]


def test_default_batch_sizes() -> None:
    from packpilot.sim.campaign import LOCKSTEP_MAX_BATCH, default_batch

    assert default_batch(1000, 2) == 32  # per pack: ~4 tasks per worker, at most 32
    assert default_batch(1000, 2, lockstep=True) == 125
    assert default_batch(100_000, 2, lockstep=True) == LOCKSTEP_MAX_BATCH
    assert default_batch(8, 1, lockstep=True) == 8  # small campaigns: one batch, not 4 of 2
    assert default_batch(40, 2, lockstep=True) == 16


def test_campaign_reports_its_engine(tmp_path: Path) -> None:
    from packpilot.sim.campaign import run_campaign

    rep = run_campaign(_mission(5.0, ["sequencing"]), 3, tmp_path / "a.parquet", scheduler="sync")
    assert rep.engine == "lockstep" and rep.failures == 0
    per = run_campaign(
        _mission(5.0, ["sequencing"]), 3, tmp_path / "b.parquet", scheduler="sync", lockstep=False
    )
    assert per.engine == "per-pack: disabled"
    assert set(rep.table.column_names) == set(per.table.column_names)
    for c in rep.table.column_names:
        if c == "wall_time_s":
            continue
        for a, b in zip(rep.table[c].to_pylist(), per.table[c].to_pylist(), strict=True):
            assert a == (pytest.approx(b, rel=1e-9) if isinstance(b, float) else b), c
    prot = run_campaign(_example("protection_warm_light.toml", 2.0), 1, tmp_path / "c.parquet")
    assert prot.engine == "lockstep, per-pack controllers"
    chg = run_campaign(_example("evtol_charging.toml", 2.0), 1, tmp_path / "d.parquet")
    assert chg.engine == "per-pack: charger link runs per pack"
