"""A campaign batch (P packs through the one closed loop) gives every pack exactly the
metrics of a single run with the same draw: one loop, one metrics definition, P = 1 or N."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.campaign import (
    Draw,
    default_batch,
    draw_run,
    parse_spreads,
    run_batch,
    run_campaign,
    unsupported_reason,
)
from packpilot.campaign.execute import _row
from packpilot.config import ScenarioConfig, load_config, parse_config
from packpilot.contract.record import BATTERY_CHANNELS
from packpilot.errors import InputError
from packpilot.sim.runner import Runner
from packpilot.sim.verdict import PhysicsLimits, PhysicsWatch

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"
SPREAD = parse_spreads("capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35")


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


def _single(cfg: ScenarioConfig, draw: Draw) -> dict[str, Any]:
    """The run alone, its row built as a campaign builds it, with the physics alarms that the
    single run's own trace shows (``PhysicsWatch``, what ``simulate``'s verdict reads)."""
    res = Runner(cfg, progress=False, pack_overrides=draw.pack_overrides()).run()
    names = [b.name for b in cfg.pack.batteries]
    limits = PhysicsLimits.of_config(cfg.model_dump(mode="json"), names)
    watch = PhysicsWatch(limits)
    tr = res.trace
    watch.feed(tr.t_s, tr.battery, tr.load_demand_a, tr.load_a, tr.charger_a)
    alarms = [(a.category, a.severity) for a in watch.alarms()]
    ch = {c: i for i, c in enumerate(BATTERY_CHANNELS)}
    last = tr.battery[-1] if len(tr.t_s) else np.full((len(names), len(ch)), np.nan)
    ended = bool(
        np.any(last[:, ch["min_cell_v"]] < np.array(limits.cell_v_min))
        or np.any(last[:, ch["soc"]] < 0.0)
    )
    return _row(draw, res.metrics, 0.0, (alarms, ended))


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return bool(a == b)


def _assert_exact(rows: list[dict[str, Any]], ref: list[dict[str, Any]]) -> None:
    for row, want in zip(rows, ref, strict=True):
        keys = (set(row) | set(want)) - {"wall_time_s"}
        for k in sorted(keys):
            a, b = row.get(k, "missing"), want.get(k, "missing")
            assert _same(a, b), (k, a, b)


def _compare(cfg: ScenarioConfig, draws: list[Draw]) -> list[dict[str, Any]]:
    rows = run_batch(cfg, draws)
    _assert_exact(rows, [_single(cfg, d) for d in draws])
    return rows


def test_no_controller_pack_matches_single_runs() -> None:
    """Directly paralleled batteries (no method): cross-charging, drawn spreads per pack."""
    rows = _compare(_mission(120.0, []), [draw_run(SPREAD, 3, i, 25.0) for i in range(5)])
    assert len({r["capacity_scale"] for r in rows}) == 5
    assert max(r["peak_cross_current_a"] for r in rows) > 5.0  # the plant really cross-charges


@pytest.mark.parametrize(
    ("name", "duration_s", "spread"),
    [
        ("sequencing_dual_hover.toml", None, "capacity=8%,r0=10%,soc0=0.04"),
        ("sequencing_four_spread.toml", 300.0, "capacity=8%,r0=10%,soc0=0.04"),
        ("sequencing_hot_insert.toml", 400.0, "capacity=8%,r0=10%,soc0=0.04"),
        ("protection_cold_heavy.toml", None, "capacity=5%,r0=10%,soc0=0.03,ambient_c=-14:-6"),
        ("equalization_uav12s.toml", 240.0, "capacity=3%,r0=10%,soc0=0.02"),
        ("evtol_charging.toml", 600.0, "capacity=3%,r0=10%,soc0=0.02"),
        ("telecom_string.toml", 3000.0, "capacity=3%,r0=10%"),
        ("uav_mission.toml", 1500.0, "capacity=5%,r0=10%,soc0=0.03,ambient_c=5:30"),
    ],
)
def test_examples_match_single_runs(name: str, duration_s: float | None, spread: str) -> None:
    """Every method, the supervised BMS with its safety layers, charger links (uav_mission's
    over a virtual CAN bus) and brown-out stops: packs that leave the batch early included."""
    cfg = _example(name, duration_s)
    draws = [draw_run(parse_spreads(spread), 7, i, cfg.pack.ambient_c) for i in range(3)]
    rows = _compare(cfg, draws)
    assert all(r["status"] == "ok" for r in rows), [r["error"] for r in rows]
    if duration_s is None:
        assert len({r["steps"] for r in rows}) > 1, "packs should stop at different times"


def test_a_fault_schedule_runs_in_a_batch() -> None:
    cfg = _example("uav_mission.toml", 400.0)
    faults = [{"kind": "sensor_nan", "at_s": 100.0, "battery": "B", "quantity": "temp_c"}]
    cfg = parse_config(cfg.model_dump(mode="json") | {"faults": faults})
    rows = _compare(cfg, [draw_run(SPREAD, 2, i, cfg.pack.ambient_c) for i in range(2)])
    assert all(r.get("events_Fault", 0) >= 1 for r in rows)


def test_batch_of_one_equals_member_of_a_batch() -> None:
    cfg = _mission(60.0, ["sequencing"])
    draws = [draw_run(SPREAD, 5, i, 25.0) for i in range(3)]
    _assert_exact(run_batch(cfg, draws[1:2]), run_batch(cfg, draws)[1:2])


def test_failing_run_is_recorded_and_the_others_finish() -> None:
    cfg = _mission(30.0, ["sequencing"])
    draws = [draw_run(SPREAD, 6, i, 25.0) for i in range(4)]
    rows = run_batch(cfg, draws, frozenset({2}))
    assert [r["status"] for r in rows] == ["ok", "ok", "error", "ok"]
    assert "DeliberateFailure" in rows[2]["error"]
    ok = [d for d in draws if d.run != 2]
    _assert_exact([r for r in rows if r["status"] == "ok"], run_batch(cfg, ok))


def test_non_finite_pack_is_an_error_row_and_leaves_the_others_alone() -> None:
    """A pack whose state goes non-finite (a NaN ambient temperature, which the draws'
    clipping would never produce, fed in directly) is an error row; its neighbours are
    untouched."""
    cfg = _mission(10.0, ["sequencing"])
    draws = [draw_run(SPREAD, 8, i, 25.0) for i in range(3)]
    draws[1] = Draw(draws[1].run, draws[1].seed, ambient_c=math.nan)
    rows = run_batch(cfg, draws)
    ref = [_single(cfg, d) for d in draws]
    assert [r["status"] for r in rows] == [r["status"] for r in ref] == ["ok", "error", "ok"]
    assert rows[1]["error"] == ref[1]["error"] and "max_temp_c" in rows[1]["error"]
    _assert_exact([rows[0], rows[2]], [ref[0], ref[2]])


def test_only_a_real_can_interface_cannot_batch(tmp_path: Path) -> None:
    for name in ("uav_mission.toml", "evtol_charging.toml", "telecom_string.toml"):
        assert unsupported_reason(_example(name)) is None
    data = _example("uav_mission.toml", 2.0).model_dump(mode="json")
    data["can"] = {"interface": "socketcan", "channel": "can0"}
    cfg = parse_config(data)
    assert "real CAN interface (socketcan)" in (unsupported_reason(cfg) or "")
    with pytest.raises(InputError, match="socketcan"):
        run_campaign(cfg, 2, tmp_path / "x.parquet", scheduler="sync")


def test_default_batch_sizes() -> None:
    from packpilot.campaign.schedule import MAX_BATCH

    assert default_batch(1000, 2) == 125
    assert default_batch(100_000, 2) == MAX_BATCH
    assert default_batch(8, 1) == 8  # small campaigns: one batch, not 4 of 2
    assert default_batch(40, 2) == 16


def test_campaign_reports_its_engine(tmp_path: Path) -> None:
    rep = run_campaign(_mission(5.0, ["sequencing"]), 3, tmp_path / "a.parquet", scheduler="sync")
    assert rep.engine == "batches of up to 3 packs" and rep.failures == 0
