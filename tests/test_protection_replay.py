"""replay(): the worked examples from hand-made CSV logs, timing conventions, bad input."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

import pytest

from packpilot.control.protection import ProtectionConfig, ProtectionParameter, TableRow
from packpilot.errors import InputError
from packpilot.replay.protection import OUTPUT_COLUMNS, replay


def _write(path: Path, rows: Sequence[Sequence[object]]) -> Path:
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_s", "current_a", "temp_c", "min_cell_v"])
        w.writerows(rows)
    return path


def _segments(*segs: tuple[int, float, float, float], dt: float = 1.0) -> list[list[object]]:
    """(n_rows, I, T, V) segments -> rows with t_s formatted as a logger would write it."""
    rows: list[list[object]] = []
    for n, i, t, v in segs:
        for _ in range(n):
            rows.append([f"{len(rows) * dt:.6g}", i, t, v])
    return rows


def test_p3_only_trips_at_5_s(tmp_path: Path) -> None:
    log = _write(tmp_path / "p3.csv", _segments((8, 10.0, 25.0, 3.1)))
    res = replay(log, ProtectionConfig())
    assert res.summary["tripped"] is True
    assert res.summary["trip_time_s"] == 5.0
    assert res.summary["param_at_trip"] == "P3"
    assert res.summary["m_s"] == 30.0
    assert res.summary["weights"] == {"P1": 2, "P2": 3, "P3": 6}
    assert res.columns == OUTPUT_COLUMNS == ["t_s", "param", "cutoff_v", "weighted_s", "tripped"]
    assert [r[3] for r in res.rows] == [6.0, 12.0, 18.0, 24.0, 30.0, 30.0, 30.0, 30.0]
    assert [r[4] for r in res.rows] == [False] * 4 + [True] * 4
    assert res.rows[0][:3] == [0.0, "P3", 3.2]


def test_p1_only_trips_at_15_s(tmp_path: Path) -> None:
    log = _write(tmp_path / "p1.csv", _segments((20, 30.0, -10.0, 2.7)))
    res = replay(log, ProtectionConfig())
    assert (res.summary["trip_time_s"], res.summary["param_at_trip"]) == (15.0, "P1")


def test_mixed_trips_at_10_s(tmp_path: Path) -> None:
    rows = _segments(
        (6, 30.0, 25.0, 2.7),
        (2, 20.0, 25.0, 2.9),
        (4, 10.0, 25.0, 3.1),
    )
    res = replay(_write(tmp_path / "mixed.csv", rows), ProtectionConfig())
    assert res.summary["trip_time_s"] == 10.0
    assert res.summary["param_at_trip"] == "P3"
    assert [r[1] for r in res.rows[:10]] == ["P1"] * 6 + ["P2"] * 2 + ["P3"] * 2
    assert [r[3] for r in res.rows[:10]] == [2, 4, 6, 8, 10, 12, 15, 18, 24, 30]


def test_heavy_load_between_cutoffs_then_light_load(tmp_path: Path) -> None:
    rows = _segments((60, 30.0, 25.0, 3.0), (10, 10.0, 25.0, 3.0))
    res = replay(_write(tmp_path / "drop.csv", rows), ProtectionConfig())
    assert all(r[3] == 0.0 for r in res.rows[:60])
    assert res.rows[60][3] == 6.0
    assert res.summary["trip_time_s"] == 65.0


def test_tenth_second_sampling_trips_exactly(tmp_path: Path) -> None:
    rows = _segments((80, 10.0, 25.0, 3.1), dt=0.1)
    res = replay(_write(tmp_path / "fast.csv", rows), ProtectionConfig())
    assert res.summary["trip_time_s"] == 5.0
    assert sum(1 for r in res.rows if not r[4]) == 49


def test_irregular_rows_hold_until_the_next_timestamp(tmp_path: Path) -> None:
    # durations 2, 1, 0.5, 0.5 (last repeats previous) -> 12, 18, 21, 24: no trip
    rows = [[0, 10, 25, 3.1], [2, 10, 25, 3.1], [3, 10, 25, 3.1], [3.5, 10, 25, 3.1]]
    res = replay(_write(tmp_path / "irr.csv", rows), ProtectionConfig())
    assert [r[3] for r in res.rows] == [12.0, 18.0, 21.0, 24.0]
    assert res.summary["tripped"] is False and res.summary["trip_time_s"] is None
    assert res.summary["final_fraction"] == pytest.approx(0.8)
    rows.append([4.5, 10, 25, 3.1])  # 1 s -> 30: trips at 4.5 + 1
    res = replay(_write(tmp_path / "irr2.csv", rows), ProtectionConfig())
    assert res.summary["trip_time_s"] == 5.5


def test_healthy_log_does_not_trip(tmp_path: Path) -> None:
    rows = _segments((100, 30.0, -10.0, 3.3), (100, 10.0, 25.0, 3.6))
    res = replay(_write(tmp_path / "ok.csv", rows), ProtectionConfig())
    assert res.summary["tripped"] is False
    assert res.summary["param_at_trip"] is None
    assert all(r[3] == 0.0 for r in res.rows)


def test_charge_in_log_resets(tmp_path: Path) -> None:
    rows = _segments((4, 10.0, 25.0, 3.1), (10, -2.0, 25.0, 3.7), (4, 10.0, 25.0, 3.1))
    res = replay(_write(tmp_path / "cycle.csv", rows), ProtectionConfig())
    assert res.summary["tripped"] is False
    assert [r[3] for r in res.rows[13:]] == [0.0, 6.0, 12.0, 18.0, 24.0]


def test_config_is_used(tmp_path: Path) -> None:
    cfg = ProtectionConfig(
        parameters=(ProtectionParameter(name="fixed", cutoff_v=3.2, t_max_s=5.0),),
        table=(TableRow(param="fixed"),),
    )
    res = replay(_write(tmp_path / "p1.csv", _segments((20, 30.0, -10.0, 3.1))), cfg)
    assert res.summary["trip_time_s"] == 5.0
    assert res.summary["m_s"] == 5.0 and res.summary["weights"] == {"fixed": 1}


def test_table_writes(tmp_path: Path) -> None:
    res = replay(_write(tmp_path / "p3.csv", _segments((6, 10.0, 25.0, 3.1))), ProtectionConfig())
    out = tmp_path / "out.csv"
    res.write_csv(out)
    lines = out.read_text().splitlines()
    assert lines[0] == "t_s,param,cutoff_v,weighted_s,tripped"
    assert lines[5] == "4.0,P3,3.2,30.0,True"


def test_missing_column_names_it(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("t_s,current_a,min_cell_v\n0,1,3.5\n")
    with pytest.raises(InputError, match="temp_c"):
        replay(p, ProtectionConfig())


def test_non_finite_cell_names_row_and_column(tmp_path: Path) -> None:
    p = _write(tmp_path / "nan.csv", [[0, 10, 25, 3.1], [1, 10, "nan", 3.1]])
    with pytest.raises(InputError, match="row 3, column temp_c"):
        replay(p, ProtectionConfig())
