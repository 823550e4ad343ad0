"""Replay of hand-made parallel-discharge logs: R1, R2, R3, R4, reverse current, bad input."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pytest

from packpilot.control.sequencing import SequencingConfig
from packpilot.errors import InputError
from packpilot.replay.common import ReplayResult
from packpilot.replay.sequencing import replay

CFG = SequencingConfig()


def _write(path: Path, header: Sequence[str], rows: Sequence[Sequence[float]]) -> Path:
    lines = [",".join(header)] + [",".join(f"{x:g}" for x in r) for r in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


def _col(res: ReplayResult, name: str) -> list[object]:
    j = res.columns.index(name)
    return [row[j] for row in res.rows]


def _rows_2(ts: Sequence[float], v0, v1, i0, i1) -> list[list[float]]:  # type: ignore[no-untyped-def]
    return [[t, v0(t), v1(t), i0(t), i1(t)] for t in ts]


HDR2 = ["t_s", "v_0", "v_1", "i_0", "i_1"]


def test_r1_high_battery_discharges_low_one_stands_by(tmp_path: Path) -> None:
    ts = [0.1 * k for k in range(30)]
    rows = _rows_2(
        ts, lambda t: 25.0, lambda t: 23.0, lambda t: 0.0 if t < 1.0 else 10.0, lambda t: 0.0
    )
    res = replay(_write(tmp_path / "r1.csv", HDR2, rows), CFG)
    assert set(_col(res, "state_0")) == {"DISCHARGING"}
    assert set(_col(res, "state_1")) == {"STANDBY"}
    assert set(_col(res, "chg_1")) == {0}, "a standby battery never has its charge FET on"
    assert set(_col(res, "dsg_1")) == {1}, "standby keeps the discharge FET on (diode-OR)"
    assert res.summary["final_states"] == ["DISCHARGING", "STANDBY"]
    assert res.summary["joins"] == []


def test_r1_spread_below_v_th_admits_both(tmp_path: Path) -> None:
    rows = [[0.0, 24.0, 23.6, 0.0, 0.0], [0.1, 24.0, 23.6, 0.0, 0.0]]
    res = replay(_write(tmp_path / "r1b.csv", HDR2, rows), CFG)
    assert res.rows[0][2::3] == ["DISCHARGING", "DISCHARGING"]


def test_r2_standby_joins_when_the_fast_voltages_meet(tmp_path: Path) -> None:
    # Battery 0 sags from 24.0 V by 0.1 V per row under 20 A; battery 1 rests at 23.0 V.
    ts = [float(k) for k in range(25)]
    rows = _rows_2(ts, lambda t: 24.0 - 0.1 * t, lambda t: 23.0, lambda t: 20.0, lambda t: 0.0)
    res = replay(_write(tmp_path / "r2.csv", HDR2, rows), CFG)
    state1 = _col(res, "state_1")
    first = state1.index("DISCHARGING")
    # Battery 0's fast voltage (no current step seen: V + I x r_batt_ohm) is
    # 24.4 - 0.1 t; it is less than v_co = 50 mV above battery 1's 23.0 V from t = 14 on.
    # (The source's terminal-voltage R2 would have joined at t = 13, 0.1 V, 2.5 A, earlier.)
    assert ts[first] == pytest.approx(14.0)
    assert all(s == "STANDBY" for s in state1[:first])
    # R2 switches the joiner's charge FET in the same period, and it stays on.
    chg1 = _col(res, "chg_1")
    assert set(chg1[first:]) == {1} and set(chg1[:first]) == {0}
    # the battery as the log names it (a numbered log: "1"), its position in "index"
    assert res.summary["joins"] == [{"t_s": ts[first], "battery": "1", "index": 1, "rule": "R2"}]


@pytest.mark.parametrize(("dt", "debounce"), [(0.05, 0.02), (0.05, 0.1), (0.01, 0.02), (0.3, 0.02)])
def test_r3_charge_fet_on_within_t_on_of_diode_conduction(
    tmp_path: Path, dt: float, debounce: float
) -> None:
    cfg = SequencingConfig(t_debounce=debounce)
    n = int(3.0 / dt)
    ts = [round(dt * k, 9) for k in range(n)]
    # Battery 0 discharges; from t=1.5 the load pulls battery 1's diode into conduction too.
    rows = _rows_2(
        ts,
        lambda t: 24.0,
        lambda t: 23.0,
        lambda t: 0.0 if t < 0.5 else 10.0,
        lambda t: 0.0 if t < 1.5 else 5.0,
    )
    res = replay(_write(tmp_path / "r3.csv", HDR2, rows), cfg)
    chg0, chg1 = _col(res, "chg_0"), _col(res, "chg_1")
    # Battery 0 is engaged at power-up by the engage rule (alone it cannot be charged), so
    # its diode never conducts.
    assert set(chg0) == {1}
    seen1 = next(k for k, t in enumerate(ts) if t >= 1.5)
    on1 = chg1.index(1)
    assert ts[on1] - ts[seen1] <= cfg.t_on + 1e-9
    assert _col(res, "state_1")[on1] == "DISCHARGING"
    join = {"t_s": ts[on1], "battery": "1", "index": 1, "rule": "R3"}
    assert join in res.summary["joins"]  # type: ignore[operator]
    assert res.summary["max_diode_conduction_s"] <= cfg.t_on + 1e-9  # type: ignore[operator]
    if dt < cfg.t_on:
        assert ts[on1] - ts[seen1] >= min(debounce, cfg.t_on - dt) - 1e-9
    # R3 outranks the charge limit: at zero load battery 0 (fast 24.2 V) would push far more
    # than 2.5 A into battery 1 (23.1 V): reported once as a risk.
    risk = res.summary["cross_current_risk"]
    assert isinstance(risk, list) and [(r["t_s"], r["index"]) for r in risk] == [(ts[on1], 1)]


def test_r3_debounce_ignores_a_single_spike(tmp_path: Path) -> None:
    ts = [round(0.005 * k, 9) for k in range(40)]
    rows = _rows_2(
        ts,
        lambda t: 24.0,
        lambda t: 23.0,
        lambda t: 10.0,
        lambda t: 5.0 if 0.1 <= t < 0.105 else 0.0,
    )
    res = replay(_write(tmp_path / "spike.csv", HDR2, rows), CFG)
    assert set(_col(res, "chg_1")) == {0}
    assert set(_col(res, "state_1")) == {"STANDBY"}


def test_r4_discharge_fet_on_within_t_on_of_charging_current(tmp_path: Path) -> None:
    hdr = [*HDR2, "docked"]
    ts = [round(0.05 * k, 9) for k in range(40)]
    rows = [[t, 23.0, 22.0, -3.0 if t >= 0.5 else 0.0, -3.0 if t >= 1.0 else 0.0, 1.0] for t in ts]
    res = replay(_write(tmp_path / "r4.csv", hdr, rows), CFG)
    assert set(_col(res, "mode")) == {"charge"}
    assert set(_col(res, "state_0")) == {"CHARGING"}
    assert set(_col(res, "chg_0")) == {1}, "charging keeps the charge FET on throughout"
    dsg0, dsg1 = _col(res, "dsg_0"), _col(res, "dsg_1")
    assert dsg0[: ts.index(0.5)] == [0] * ts.index(0.5), "no charging current: FET stays off"
    on0 = dsg0.index(1)
    on1 = dsg1.index(1)
    assert 0.5 <= ts[on0] <= 0.5 + CFG.t_on + 1e-9
    assert 1.0 <= ts[on1] <= 1.0 + CFG.t_on + 1e-9


def test_charge_mode_from_sustained_negative_current_without_dock_flag(tmp_path: Path) -> None:
    ts = [round(0.1 * k, 9) for k in range(50)]
    rows = _rows_2(
        ts, lambda t: 23.0, lambda t: 23.0, lambda t: -4.0 if t >= 1.0 else 3.0, lambda t: 0.0
    )
    res = replay(_write(tmp_path / "chg.csv", HDR2, rows), CFG)
    mode = _col(res, "mode")
    first = mode.index("charge")
    assert ts[first] == pytest.approx(1.0 + CFG.t_mode)
    assert res.summary["transitions"]["ModeChanged"] == 1  # type: ignore[index]
    # An engaged battery charged from outside is not mistaken for a cross-current victim.
    assert "ReverseCurrent" not in res.summary["transitions"]  # type: ignore[operator]


def test_reverse_current_opens_the_charge_fet(tmp_path: Path) -> None:
    ts = [round(0.1 * k, 9) for k in range(30)]
    rows = _rows_2(
        ts,
        lambda t: 23.0,
        lambda t: 22.95,
        lambda t: 10.0 if t < 2.0 else 6.0,
        lambda t: 10.0 if t < 2.0 else -2.0,
    )
    res = replay(_write(tmp_path / "rev.csv", HDR2, rows), CFG)
    k = ts.index(2.0)
    assert res.rows[k - 1][2::3] == ["DISCHARGING", "DISCHARGING"]
    assert _col(res, "chg_1")[k - 1] == 1
    # The reverse cut opens the charge FET in the same period; the battery stays admitted.
    assert _col(res, "state_1")[k] == "DISCHARGING"
    assert set(_col(res, "chg_1")[k:]) == {0}
    assert res.summary["reverse_current"] == [
        {"t_s": 2.0, "battery": "1", "index": 1, "current_a": -2.0}
    ]


def test_hot_insertion_with_present_columns(tmp_path: Path) -> None:
    hdr = [*HDR2, "present_0", "present_1"]
    ts = [float(k) for k in range(20)]
    # Battery 1 (22.0 V) arrives at t=5 while battery 0 sags from 23.0 V by 0.1 V/s.
    rows = [[t, 23.0 - 0.1 * t, 22.0, 20.0, 0.0, 1.0, float(t >= 5)] for t in ts]
    res = replay(_write(tmp_path / "ins.csv", hdr, rows), CFG)
    s1 = _col(res, "state_1")
    assert s1[:5] == ["OFF"] * 5
    assert s1[5] == "STANDBY"
    assert s1.index("DISCHARGING") == 14  # fast voltages: (23.0 - 1.4 + 0.4) - 22.0 < v_co
    assert set(_col(res, "dsg_1")[:5]) == {0}


def test_missing_current_column_is_named(tmp_path: Path) -> None:
    path = _write(tmp_path / "m.csv", ["t_s", "v_0", "v_1", "i_0"], [[0, 24, 23, 0]])
    with pytest.raises(InputError, match="i_1"):
        replay(path, CFG)


def test_orphan_current_column_is_named(tmp_path: Path) -> None:
    path = _write(tmp_path / "o.csv", ["t_s", "v_0", "i_0", "i_1"], [[0, 24, 0, 0]])
    with pytest.raises(InputError, match="i_1"):
        replay(path, CFG)


def test_nan_cell_names_row_and_column(tmp_path: Path) -> None:
    path = tmp_path / "nan.csv"
    path.write_text("t_s,v_0,v_1,i_0,i_1\n0,24,23,0,0\n0.1,nan,23,0,0\n")
    with pytest.raises(InputError, match=r"row 3, column v_0"):
        replay(path, CFG)


def test_bad_present_flag_is_named(tmp_path: Path) -> None:
    path = _write(
        tmp_path / "p.csv", [*HDR2, "present_0", "present_1"], [[0, 24, 23, 0, 0, 1, 0.5]]
    )
    with pytest.raises(InputError, match=r"row 2, column present_1"):
        replay(path, CFG)


def test_partial_present_columns_are_rejected(tmp_path: Path) -> None:
    path = _write(tmp_path / "pp.csv", [*HDR2, "present_0"], [[0, 24, 23, 0, 0, 1]])
    with pytest.raises(InputError, match="present_1"):
        replay(path, CFG)


def test_output_table_shape_and_csv(tmp_path: Path) -> None:
    hdr = ["t_s", "v_0", "v_1", "v_2", "i_0", "i_1", "i_2"]
    rows = [[0.1 * k, 25.0, 24.8, 22.0, 5.0, 0.0, 0.0] for k in range(5)]
    res = replay(_write(tmp_path / "n3.csv", hdr, rows), CFG)
    assert res.columns == [
        "t_s",
        "mode",
        "state_0",
        "chg_0",
        "dsg_0",
        "state_1",
        "chg_1",
        "dsg_1",
        "state_2",
        "chg_2",
        "dsg_2",
    ]
    assert len(res.rows) == 5
    assert res.summary["final_states"] == ["DISCHARGING", "DISCHARGING", "STANDBY"]
    out = tmp_path / "out.csv"
    res.write_csv(out)
    assert out.read_text().splitlines()[0].startswith("t_s,mode,state_0")
