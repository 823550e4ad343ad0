"""Leave one flight out (#27 §3, "or leave one flight out with several"): logs split into
flights at their rests, each flight left out of one fit by mask (the state still runs through
it) and predicted by the fit of the others; the CLI's ``--validate flights``."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.errors import InputError
from packpilot.model.cell import load_parameter_set
from packpilot.model.fit.fit import fit
from packpilot.model.fit.profile import flights, predict
from packpilot.model.fit.synthetic import Truth, synthetic_log
from packpilot.model.fit.validate import fit_and_validate
from packpilot.replay.fitlogs import profiles_from_logs

UAV = load_parameter_set("uav_5ah")
REAL = Path(__file__).resolve().parents[1] / "examples" / "logs" / "real"
RUNNER = CliRunner()
NOISE_V = 0.010


def test_the_real_tlog_splits_into_its_three_flights() -> None:
    """The dronekit tlog: ground idle 0.43 A (1.2 A armed), flights at 15-25 A; landings
    resting 36 s and 65 s split it, touch-downs of 18 s and 14 s inside a flight do not."""
    tlog = REAL / "arducopter_dronekit_flight_battery.tlog"
    prof = profiles_from_logs([tlog], 3, None)[0][0]
    got = [(float(prof.t_s[lo]), float(prof.t_s[hi - 1])) for lo, hi in flights(prof)]
    assert len(got) == 3, got
    starts = [a for a, _ in got]
    # take-offs at 467 s, 794 s and 924 s (the first loaded sample after each rest)
    assert starts == pytest.approx([467.0, 794.0, 924.0], abs=3.0)
    assert got[-1][1] == pytest.approx(float(prof.t_s[-1]))
    # the rest before the first take-off belongs to no flight: it is always fitted
    assert flights(prof)[0][0] > 1000


def test_a_flight_left_out_keeps_the_state_and_is_not_fitted() -> None:
    """Masking a flight out changes the fit (its voltages are not seen) but not the state:
    the one initial SOC per log carries through the flight by the charge counter."""
    prof = synthetic_log(Truth(), 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=2,
                         flights=3)  # fmt: skip
    lo, hi = flights(prof)[1]
    held = prof.holding_out(lo, hi)
    assert not held.fitted[lo:hi].any() and held.fitted[:lo].all() and held.fitted[hi:].all()
    r = fit([held], UAV.ocv_soc, UAV.ocv_table_v)
    assert r.window.samples == len(prof.t_s) - (hi - lo)
    _, soc = predict(held, r.values, r.soc0[prof.name].value, r.ocv_soc, r.ocv_v)
    assert soc[hi] == pytest.approx(
        r.soc0[prof.name].value - prof.drawn_ah[hi] / r.values.capacity_ah
    )


@pytest.mark.parametrize("seed", [1, 2])
def test_leave_one_flight_out_on_a_three_flight_plant_log(seed: int) -> None:
    """Three plant-made flights (1 Hz, 10 mV noise, 1 % current gain error): R0 within 5 %,
    capacity within 3 %, each interior flight's held-out RMSE within 1.5 x the injected noise;
    the last flight is extrapolation (nothing below it fitted) and is not judged."""
    truth = Truth()
    prof = synthetic_log(truth, 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=seed,
                         flights=3)  # fmt: skip
    assert len(flights(prof)) == 3
    v = fit_and_validate([prof], UAV.ocv_soc, UAV.ocv_table_v, mode="flights")
    assert v.mode == "flights"
    p = v.result.params
    assert abs(p["r0_ohm"].value / truth.r0_ohm - 1) < 0.05
    assert abs(p["capacity_ah"].value / truth.capacity_ah - 1) < 0.03
    assert [c.interior for c in v.checks] == [True, True, False]
    for c in v.checks:
        assert c.rmse_v < 1.5 * NOISE_V, (c.name, c.rmse_v)
        assert c.skill > 0.3, (c.name, c.skill)
    held = [c.test for c in v.checks]
    assert held == [slice(lo, hi) for lo, hi in flights(prof)]
    assert v.verdict == "usable", v.reasons
    assert any("flight 3" in r and "not judged" in r for r in v.reasons)


def test_cli_refuses_leave_one_flight_out_with_too_few_flights() -> None:
    res = RUNNER.invoke(app, ["fit", str(REAL / "ardupilot_3x_underpowered.log"), "--cells", "3",
                              "--validate", "flights"])  # fmt: skip
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), lines
    assert "at least 3 flights" in lines[0] and "found 1" in lines[0], lines


def test_cli_refuses_an_unknown_validation_mode() -> None:
    res = RUNNER.invoke(app, ["fit", str(REAL / "ardupilot_3x_underpowered.log"), "--cells", "3",
                              "--validate", "seasons"])  # fmt: skip
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "time, flights" in lines[0], lines


def test_cli_leave_one_flight_out_report_shows_the_held_out_flights(tmp_path: Path) -> None:
    """A three-flight PX4 log through the CLI: the verdict, one chart per flight with its
    held-out span shaded, and the written set saying which samples each check held out."""
    from packpilot.io.flightlog.ulog import write_battery_ulog

    prof = synthetic_log(Truth(), 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=1,
                         flights=3)  # fmt: skip
    assert prof.charge_ah is not None
    log = tmp_path / "three.ulg"
    write_battery_ulog(log, prof.t_s, prof.voltage_v, prof.current_a, prof.charge_ah)
    out, rep = tmp_path / "cell.json", tmp_path / "fit.html"
    res = RUNNER.invoke(app, ["fit", str(log), "--validate", "flights", "--out", str(out),
                              "--report", str(rep), "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    import json

    doc = json.loads(out.read_text())
    val = doc["notes"]["validation"]
    assert [x["mode"] for x in val] == ["flights"] * 3
    assert [x["judged"] for x in val] == [True, True, False]
    spans = [x["held_out_t_s"] for x in val]
    assert all(a < b for a, b in spans) and spans[0][1] < spans[1][0] < spans[2][0]
    page = rep.read_text()
    assert "Leave one flight out" in page and page.count("<svg") == 3
    assert len(re.findall(r"\(interior\)", page)) == 2 and "extrapolation: not judged" in page
    assert np.isfinite([x["heldout_rmse_v"] for x in val]).all()


def test_a_log_without_a_flight_long_enough_has_none() -> None:
    """Bursts of load shorter than MIN_FLIGHT_S (a motor test) start no flight; a log of them
    has no flight at all (and leave one flight out refuses it in one line)."""
    from packpilot.model.fit.profile import Profile

    t = np.arange(0.0, 300.0)
    i = np.where((t > 100) & (t < 110), 20.0, 0.3)
    prof = Profile("bench test", t, i, 4.1 - 0.03 * i)
    assert flights(prof) == []
    with pytest.raises(InputError, match=r"at least 3 flights.*found 0"):
        fit_and_validate([prof], UAV.ocv_soc, UAV.ocv_table_v, mode="flights")


def test_flights_are_counted_across_the_logs_given_together() -> None:
    """A two-flight log and a one-flight log of the same battery: three flights in all, so
    leave one flight out runs; each log keeps its own initial SOC, and only the flight its own
    log's training samples bracket is judged (a log's last flight is extrapolation)."""
    truth = Truth()
    two = synthetic_log(truth, 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=3,
                        seconds=1000, flights=2)  # fmt: skip
    one = synthetic_log(truth, 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=4,
                        seconds=600)  # fmt: skip
    one = replace(one, name="second log")
    assert (len(flights(two)), len(flights(one))) == (2, 1)
    with pytest.raises(InputError, match=r"found 2 \(synthetic_1hz_seed3: 2\)"):
        fit_and_validate([two], UAV.ocv_soc, UAV.ocv_table_v, mode="flights")
    v = fit_and_validate([two, one], UAV.ocv_soc, UAV.ocv_table_v, mode="flights")
    assert [c.name for c in v.checks] == [
        "synthetic_1hz_seed3 flight 1", "synthetic_1hz_seed3 flight 2", "second log flight 1",
    ]
    assert [c.interior for c in v.checks] == [True, False, False]
    assert set(v.result.soc0) == {"synthetic_1hz_seed3", "second log"}
    assert v.checks[0].rmse_v < 1.5 * NOISE_V
    assert v.verdict == "usable", v.reasons
