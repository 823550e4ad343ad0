"""SocEstimator: exact coulomb counting, OCV correction after a rest (not under load), and the
same against the simulated plant (which the estimator never imports)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import parse_config
from packpilot.contract.bms import BatteryMeasurement, ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.soc import SocConfig, SocEstimator
from packpilot.errors import ConfigError
from packpilot.model.cell import load_parameter_set
from packpilot.sim.runner import Runner
from tests.test_limits_helpers import healthy

OCV_SOC = (0.0, 0.5, 1.0)
OCV_V = (3.0, 3.7, 4.2)


def est(**kw: Any) -> SocEstimator:
    args: dict[str, Any] = dict(
        capacity_ah=(5.0, 10.0), ocv_soc=OCV_SOC, ocv_v=OCV_V, rest_current_a=0.1, rest_time_s=60.0
    )
    args.update(kw)
    return SocEstimator(**args)


def meas(t: float, *bms: BatteryMeasurement) -> Measurements:
    return Measurements(t_s=t, batteries=bms, bus_v=22.0)


def test_coulomb_counting_is_exact() -> None:
    e = est(soc0=(0.8, 0.8))
    for k in range(3600):  # 2 A for an hour (5 Ah: -0.4; 10 Ah charged at 1 A: +0.1)
        e.update(meas(k + 1.0, healthy(current_a=2.0), healthy(current_a=-1.0)), 1.0)
    assert e.soc[0] == pytest.approx(0.4, abs=1e-12)
    assert e.soc[1] == pytest.approx(0.9, abs=1e-12)


def test_counting_clamps_to_zero_and_one_and_skips_unknown_current() -> None:
    e = est(soc0=(0.01, 0.99))
    e.update(meas(1.0, healthy(current_a=50.0), healthy(current_a=-50.0)), 60.0)
    assert e.soc == (0.0, 1.0)
    e = est(soc0=(0.5, 0.5))
    e.update(meas(1.0, healthy(current_a=math.nan), healthy(current_a=1.0)), 3600.0)
    assert e.soc == (0.5, pytest.approx(0.4))


def test_rest_pulls_a_wrong_initial_soc_to_the_ocv_value() -> None:
    e = est(soc0=(0.2, 0.9))
    rest = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95)  # OCV table: SOC 0.75
    events = []
    for k in range(59):
        _, ev = e.update(meas(k + 1.0, rest, rest), 1.0)
        events += ev
    assert e.soc == (0.2, 0.9) and not events  # 59 s < rest_time_s
    _, ev = e.update(meas(60.0, rest, rest), 1.0)
    assert e.soc == (pytest.approx(0.75), pytest.approx(0.75))
    assert [x.kind for x in ev] == ["SocCorrected", "SocCorrected"]
    assert ev[0].data["before"] == pytest.approx(0.2) and ev[0].data["ocv_soc"] == 0.75


def test_blend_moves_part_of_the_way_once_per_rest_period() -> None:
    e = est(soc0=(0.2, 0.2), blend=0.5)
    rest = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95)
    for k in range(60):
        e.update(meas(k + 1.0, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.475)
    for k in range(59):
        e.update(meas(61.0 + k, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.475)  # next correction only after another 60 s
    e.update(meas(120.0, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.6125)


def test_no_correction_under_load() -> None:
    e = est(soc0=(0.2, 0.2))
    loaded = healthy(current_a=0.5, min_cell_v=3.95, max_cell_v=3.95)
    for k in range(3600):
        _, ev = e.update(meas(k + 1.0, loaded, loaded), 1.0)
        assert not ev
    assert e.soc[0] == pytest.approx(0.2 - 0.5 / 5.0)


def test_a_pulse_restarts_the_rest_clock() -> None:
    e = est(soc0=(0.2, 0.2))
    rest = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95)
    pulse = healthy(current_a=1.0, min_cell_v=3.95, max_cell_v=3.95)
    for k in range(200):
        e.update(meas(k + 1.0, pulse if k % 50 == 49 else rest, rest), 1.0)
    assert e.soc[0] < 0.2  # never 60 s of rest in a row
    assert e.soc[1] == pytest.approx(0.75)


def test_average_cell_voltage_and_initialisation_from_ocv() -> None:
    e = est(voltage="avg", series_cells=(6, 6))
    bm = healthy(current_a=0.0, voltage_v=6 * 3.35, min_cell_v=3.0, max_cell_v=3.5)
    e.update(meas(0.0, bm, bm), 1.0)
    assert e.soc == (pytest.approx(0.25), pytest.approx(0.25))
    e2 = est()
    e2.update(meas(0.0, bm, bm), 1.0)  # 'min': the weakest cell, 3.0 V -> 0
    assert e2.soc == (0.0, 0.0)


def test_step_reports_status_and_no_commands() -> None:
    e = est(soc0=(0.5, math.nan))
    out = e.step(meas(0.0, healthy(current_a=0.0), healthy(current_a=0.0)), 1.0)
    assert isinstance(out, ControlOutput)
    assert all(x is None for x in (*out.commands.chg_on, *out.commands.dsg_on))
    assert out.status["soc_est"] == [0.5, pytest.approx(0.5)]  # 3.7 V on the OCV table


@pytest.mark.parametrize(
    ("kw", "needle"),
    [
        ({"ocv_v": (3.0, 3.0, 4.2)}, "point 1 .* is not above point 0"),
        ({"ocv_soc": (0.0, 1.0)}, "equal lengths"),
        ({"capacity_ah": (5.0, 0.0)}, r"capacity_ah\[1\] must be > 0"),
        ({"voltage": "avg"}, "needs series_cells"),
        ({"soc0": (0.5,)}, "soc0 has 1 entries"),
    ],
)
def test_bad_inputs_are_config_errors(kw: dict[str, Any], needle: str) -> None:
    with pytest.raises(ConfigError, match=needle):
        est(**kw)


def test_config_validation() -> None:
    with pytest.raises(ConfigError, match=r"soc: rest_time_s must be > 0 s"):
        SocConfig.load({"rest_time_s": 0})
    with pytest.raises(ConfigError, match=r"soc: blend must be within 0\.\.1"):
        SocConfig.load({"blend": 2})


# -- against the plant ----------------------------------------------------------------


class Recorder:
    """A controller that only runs the estimator and keeps (estimate, measured SOC) pairs."""

    def __init__(self, estimator: SocEstimator) -> None:
        self.estimator = estimator
        self.pairs: list[tuple[float, float, float]] = []

    def step(self, m: Measurements, dt_s: float) -> ControlOutput:
        out = self.estimator.step(m, dt_s)
        self.pairs.append((m.t_s, self.estimator.soc[0], m.batteries[0].soc))
        return out


def _one_battery(tmp_path: Path, profile: list[tuple[float, float]], duration_s: float) -> Any:
    csv = tmp_path / "load.csv"
    csv.write_text("t_s,current_a\n" + "".join(f"{t},{a}\n" for t, a in profile))
    return parse_config(
        {
            "pack": {
                "cell": "uav_5ah",
                "batteries": [{"name": "A", "cells_per_group": 6, "soc0": 0.9}],
            },
            "load": {"kind": "current", "profile": str(csv)},
            "sim": {"dt_s": 1.0, "duration_s": duration_s, "progress": False},
        }
    )


def _info() -> PackInfo:
    return PackInfo(
        n_batteries=1,
        groups_per_battery=(1,),
        cells_per_group=(6,),
        switch_kind=(SwitchKind.MOSFET_PAIR,),
        capacity_ah=(5.0,),
    )


def test_tracks_the_plant_exactly_under_load(tmp_path: Path) -> None:
    params = load_parameter_set("uav_5ah")
    cfg = _one_battery(tmp_path, [(0.0, 10.0), (300.0, 4.0), (600.0, 4.0)], 600.0)
    e = SocEstimator.from_config(SocConfig(), _info(), params.ocv_soc, params.ocv_table_v, (0.9,))
    rec = Recorder(e)
    Runner(cfg, controller=rec).run()
    err = np.array([abs(a - b) for _, a, b in rec.pairs])
    assert err.max() < 1e-9
    assert rec.pairs[-1][2] == pytest.approx(0.9 - (10.0 * 300 + 4.0 * 299) / 3600 / 5.0, abs=1e-3)


def test_rest_correction_recovers_a_wrong_start_on_the_plant(tmp_path: Path) -> None:
    params = load_parameter_set("uav_5ah")
    cfg = _one_battery(tmp_path, [(0.0, 10.0), (200.0, 0.0)], 900.0)
    cfg_soc = SocConfig(rest_time_s=600.0)
    e = SocEstimator.from_config(cfg_soc, _info(), params.ocv_soc, params.ocv_table_v, (0.6,))
    rec = Recorder(e)
    Runner(cfg, controller=rec).run()
    before = [abs(a - b) for t, a, b in rec.pairs if t < 790.0]
    after = [abs(a - b) for t, a, b in rec.pairs if t > 805.0]
    assert min(before) > 0.29  # the 0.3 start error is carried by coulomb counting
    assert max(after) < 0.01  # OCV after 10 min of rest: within 1 % of the plant's truth


def test_a_nan_current_neither_counts_nor_rests() -> None:
    """Unknown current: the estimate holds and no OCV correction happens (the battery is not
    known to be resting), however long it lasts."""
    e = est(soc0=(0.2, 0.2))
    rest = healthy(current_a=math.nan, min_cell_v=3.95, max_cell_v=3.95)  # OCV: SOC 0.75
    events = []
    for k in range(180):
        _, ev = e.update(meas(k + 1.0, rest, rest), 1.0)
        events.extend(ev)
    assert e.soc == (0.2, 0.2)
    assert not events


def test_an_ocv_table_beyond_zero_and_one_is_clamped() -> None:
    """A fitted OCV table may run past 0..1 at its ends; the estimate never does."""
    e = est(ocv_soc=(-0.1, 0.5, 1.1))
    full = healthy(current_a=0.0, min_cell_v=4.2, max_cell_v=4.2)
    empty = healthy(current_a=0.0, min_cell_v=3.0, max_cell_v=3.0)
    e.update(meas(1.0, full, empty), 1.0)  # initialised from the OCV
    assert e.soc == (1.0, 0.0)


def test_the_initialising_sample_is_not_also_counted() -> None:
    """The first sample sets the SOC from the OCV; its current belongs to the time before the
    estimator existed, so that tick counts no charge (generated mutant 3a56847a33)."""
    e = est()
    first = healthy(current_a=5.0, min_cell_v=3.95, max_cell_v=3.95)  # OCV table: SOC 0.75
    e.update(meas(0.0, first, first), 360.0)  # counted, it would be 0.75 - 0.1 (5 Ah)
    assert e.soc == (pytest.approx(0.75, abs=1e-12), pytest.approx(0.75, abs=1e-12))


@pytest.mark.parametrize("dt_s", [math.nan, -1.0, 0.0])
def test_a_bad_tick_length_counts_no_charge(dt_s: float) -> None:
    """A NaN, negative or zero ``dt_s`` counts nothing (not a default tick; generated mutant
    47bc5aaba2)."""
    e = est(soc0=(0.5, 0.5))
    bm = healthy(current_a=18.0)  # 18 A over a 1 s default tick would be -0.001 of 5 Ah
    e.update(meas(1.0, bm, bm), dt_s)
    assert e.soc == (0.5, 0.5)


def test_a_reinserted_battery_is_read_afresh_and_rests_a_full_period_from_its_return() -> None:
    """A battery back in its slot may not be the one that left (a swap), so the estimator
    reads it as at power-up: its first present sample's OCV, not the slot's old SOC. Removal
    resets the rest clock and its next correction time: it is corrected rest_time_s after that
    first sample, not at the schedule of its earlier rest (generated mutants 59d73c3db6,
    2ae4277705)."""
    e = est(soc0=(0.2, 0.2), blend=0.5)
    rest = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95)  # OCV: SOC 0.75
    gone = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95, present=False)
    back = healthy(current_a=0.0, min_cell_v=3.56, max_cell_v=3.56)  # OCV: SOC 0.4
    relaxed = healthy(current_a=0.0, min_cell_v=3.63, max_cell_v=3.63)  # OCV: SOC 0.45
    for k in range(60):
        e.update(meas(k + 1.0, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.475)  # one correction; the next one was due at 120 s
    e.update(meas(61.0, gone, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.475)  # absent: held
    e.update(meas(62.0, back, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.4)  # read afresh, not the slot's 0.475
    events = []
    for k in range(59):
        _, ev = e.update(meas(63.0 + k, relaxed, rest), 1.0)
        events += [x for x in ev if x.battery == 0]
    assert e.soc[0] == pytest.approx(0.4) and not events  # (mutant 2ae4277705: after 1 s)
    _, ev = e.update(meas(122.0, relaxed, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.425)  # corrected 60 s after its first sample back
    assert [x.battery for x in ev if x.battery == 0] == [0]


@pytest.mark.parametrize("cut", [math.nan, 0.1, 0.5])
def test_an_unknown_or_load_current_restarts_the_whole_rest(cut: float) -> None:
    """A rest is 60 s of known current below ``rest_current_a``: one sample of unknown current,
    or of a current at or above it, restarts both the rest clock and the correction schedule
    (generated mutants 22953693fe, df8cacd066, 3b8a79f88b, 3808912b19, 75200311fa,
    3c33695500, f3fdfa0689)."""
    e = est(soc0=(0.2, 0.2), blend=0.5)
    rest = healthy(current_a=0.0, min_cell_v=3.95, max_cell_v=3.95)  # OCV: SOC 0.75
    blip = healthy(current_a=cut, min_cell_v=3.95, max_cell_v=3.95)
    for k in range(60):
        e.update(meas(k + 1.0, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.475)  # the first correction; the next one due at 120 s
    before = e.soc[0] - (0.0 if math.isnan(cut) else cut / 3600.0 / 5.0)
    e.update(meas(61.0, blip, rest), 1.0)
    for k in range(59):
        out = e.step(meas(62.0 + k, rest, rest), 1.0)
        assert e.soc[0] == pytest.approx(before)  # no correction before 60 s of new rest
    assert out.status["soc_rest_s"][0] == pytest.approx(59.0)
    e.update(meas(121.0, rest, rest), 1.0)
    assert e.soc[0] == pytest.approx(0.5 * before + 0.5 * 0.75)


def test_an_unknown_cell_voltage_during_a_rest_holds_the_estimate() -> None:
    """Due for a correction but the cell voltage is unknown: no blend with NaN; the estimate
    holds and the correction is retried (generated mutant 588605600e)."""
    e = est(soc0=(0.2, 0.2))
    blind = healthy(current_a=0.0, min_cell_v=math.nan, max_cell_v=math.nan)
    for k in range(61):
        e.update(meas(k + 1.0, blind, blind), 1.0)
    assert e.soc == (0.2, 0.2)
