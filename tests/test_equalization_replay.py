"""Replay of group-voltage logs through the equalization controller."""

from __future__ import annotations

from pathlib import Path

import pytest

from packpilot.control.equalization import EqualizationConfig
from packpilot.errors import InputError
from packpilot.replay.equalization import replay


def write_log(path: Path, rows: list[list[float]], m: int) -> Path:
    header = ["t_s", "current_a"] + [f"v_{k}" for k in range(m)]
    lines = [",".join(header)] + [",".join(f"{x:.6f}" for x in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_replay_lagging_group(tmp_path: Path) -> None:
    # 400 s at 1 s: group 2 lags by 40 mV while discharging at 3 A.
    rows = [[float(t), 3.0, 13.0, 13.0, 12.96, 13.0] for t in range(400)]
    res = replay(write_log(tmp_path / "log.csv", rows, 4), EqualizationConfig())
    assert len(res.rows) == 400
    assert res.columns[:6] == ["t_s", "current_a", "dv_mv_g0", "ah_g0", "time_s_g0", "i_eq_a_g0"]
    ah2 = res.columns.index("ah_g2")
    assert [r[ah2] for r in res.rows if r[0] in (118.0, 119.0, 239.0, 359.0)] == [
        0.0,
        0.25,
        0.375,
        0.4375,
    ]
    dv2 = res.columns.index("dv_mv_g2")
    assert res.rows[0][dv2] == pytest.approx(30.0)
    i2 = res.columns.index("i_eq_a_g2")
    assert res.rows[200][i2] == 2.0  # 3 A clamped to the 2 A equalizer rating
    s = res.summary
    assert s["final_ah"] == [0.0, 0.0, 0.4375, 0.0]
    assert s["updates"] == {"formula1": 3, "formula2": 18, "subtract_min": 0}
    assert s["balancing_events"] == 3
    # Owed raised to AH = 0.4375 Ah at t = 359 s, then 41 s delivered at 2 A; the rest owed.
    owed = res.columns.index("owed_ah_g2")
    assert res.rows[-1][owed] == pytest.approx(0.4375 - 2.0 * 41 / 3600)
    assert s["charge_owed_ah"] == [0.0, 0.0, pytest.approx(0.4375 - 2.0 * 41 / 3600), 0.0]


def test_replay_subtract_min_counted(tmp_path: Path) -> None:
    # First every group but 0 lags (group 0 far high), then group 0 drops and lags too.
    rows = []
    for t in range(240):
        rows.append([float(t), -5.0, 13.2, 13.0, 13.0, 13.0])
    for t in range(240, 600):
        rows.append([float(t), -5.0, 12.8, 13.0, 13.0, 13.01])
    res = replay(write_log(tmp_path / "log.csv", rows, 4), EqualizationConfig())
    s = res.summary
    assert isinstance(s["updates"], dict)
    assert s["updates"]["subtract_min"] >= 1
    final = s["final_ah"]
    assert isinstance(final, list)
    assert min(final) == 0.0


def test_replay_rejects_nan(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("t_s,current_a,v_0,v_1\n0,1,13,13\n1,1,nan,13\n")
    with pytest.raises(InputError, match="row 3, column v_0"):
        replay(p, EqualizationConfig())


def test_replay_missing_columns(tmp_path: Path) -> None:
    p = tmp_path / "bad.csv"
    p.write_text("t_s,v_0,v_1\n0,13,13\n")
    with pytest.raises(InputError, match="current_a"):
        replay(p, EqualizationConfig())


def test_replay_writes_csv(tmp_path: Path) -> None:
    rows = [[float(t), 1.0, 13.0, 13.0] for t in range(5)]
    res = replay(write_log(tmp_path / "log.csv", rows, 2), EqualizationConfig())
    out = tmp_path / "out.csv"
    res.write_csv(out)
    assert out.read_text().splitlines()[0].startswith("t_s,current_a,dv_mv_g0")
