"""`packpilot fit` (#27 §2-3): the fit recovers the plant's known parameters from synthetic logs
made by the plant (the acceptance figures), flags what the data cannot identify, validates on
held-out data, and writes a cell set that scenarios load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from packpilot.cli import app
from packpilot.model.cell import load_parameter_file, load_parameter_set, simulate_current
from packpilot.model.fit.fit import fit
from packpilot.model.fit.profile import EcmValues, Profile, predict
from packpilot.model.fit.synthetic import Truth, ocv_bump, ocv_plant_params, synthetic_log
from packpilot.model.fit.validate import fit_and_validate
from packpilot.replay.fitlogs import profiles_from_logs

UAV = load_parameter_set("uav_5ah")
REAL = Path(__file__).resolve().parents[1] / "examples" / "logs" / "real"
RUNNER = CliRunner()
NOISE_V = 0.010


def test_the_stepper_reproduces_the_plant_on_its_own_log() -> None:
    """Variable steps, sampled current and the charge counter: on a noise-free plant log the
    stepper with the true values is within 2 mV of the plant (the plant heats by a few K,
    which moves its OCV through dU/dT; the stepper has no thermal model)."""
    truth = Truth()
    prof = synthetic_log(truth, 1.0, noise_v=0.0, gain=1.0, seconds=600)
    vals = EcmValues(truth.capacity_ah, truth.r0_ohm, ((truth.r1_ohm, truth.tau1_s),))
    v, _ = predict(prof, vals, truth.soc0, UAV.ocv_soc, UAV.ocv_table_v)
    assert float(np.max(np.abs(v - prof.voltage_v))) < 0.002
    # Uneven steps: every third sample dropped, the counter still gives the state.
    keep = np.arange(len(prof.t_s)) % 3 != 1
    thin = Profile("thin", prof.t_s[keep], prof.current_a[keep], prof.voltage_v[keep],
                   None if prof.charge_ah is None else prof.charge_ah[keep])  # fmt: skip
    v2, _ = predict(thin, vals, truth.soc0, UAV.ocv_soc, UAV.ocv_table_v)
    assert float(np.sqrt(np.mean((v2 - thin.voltage_v) ** 2))) < 0.01


@pytest.mark.parametrize("rate_hz", [1.0, 10.0])
def test_acceptance_r0_and_capacity_from_a_synthetic_flight(rate_hz: float) -> None:
    """1 Hz and 10 Hz, 10 mV noise, 1 % current gain error, 30 s rest: R0 within 5 %,
    capacity within 3 % (SOC swing >= 30 %), held-out RMSE within 1.5 x the noise."""
    truth = Truth()
    prof = synthetic_log(truth, rate_hz, noise_v=NOISE_V, gain=1.01, rest_s=30)
    v = fit_and_validate([prof], UAV.ocv_soc, UAV.ocv_table_v)
    p = v.result.params
    assert p["r0_ohm"].value == pytest.approx(truth.r0_ohm, rel=0.05)
    assert p["capacity_ah"].value == pytest.approx(truth.capacity_ah, rel=0.03)
    assert p["capacity_ah"].identifiable and p["r0_ohm"].identifiable
    check = v.checks[0]
    assert check.soc_swing >= 0.30
    assert check.rmse_v <= 1.5 * NOISE_V
    assert check.noise_floor_v == pytest.approx(NOISE_V, rel=0.3)
    assert check.skill > 0.0
    assert v.verdict == "usable", v.reasons


def test_acceptance_short_tau_flagged_at_1hz() -> None:
    truth = Truth(tau1_s=1.0)
    prof = synthetic_log(truth, 1.0, noise_v=NOISE_V, gain=1.01, seconds=900)
    r = fit([prof], UAV.ocv_soc, UAV.ocv_table_v)
    tau = r.params["tau1_s"]
    assert not tau.identifiable and "logging periods" in tau.reason
    assert any(f.startswith("tau1_s: not identifiable") for f in r.flags())
    # R0 and R1 merge: the split is not claimed, their sum is what the data hold.
    r0, r1 = r.params["r0_ohm"], r.params["r1_ohm"]
    assert not r0.identifiable and "R0 + R1" in r0.reason
    assert r0.value + r1.value == pytest.approx(truth.r0_ohm + truth.r1_ohm, rel=0.05)


def test_small_soc_swing_flags_the_capacity() -> None:
    truth = Truth()
    prof = synthetic_log(truth, 1.0, noise_v=NOISE_V, seconds=300)
    r = fit([prof], UAV.ocv_soc, UAV.ocv_table_v)
    cap = r.params["capacity_ah"]
    assert not cap.identifiable and "SOC swing" in cap.reason


def test_capacity_the_data_cannot_see_stays_off_its_bounds() -> None:
    """A real 110 s flight with a 3 % SOC swing: without the weak prior the capacity ran to its
    upper bound (31 Ah for a 4.2 Ah pack) and the held-out part went worse than a straight
    line; with it the capacity stays near what the voltages suggest, still flagged."""
    from packpilot.replay.fitlogs import profiles_from_logs

    profs, _ = profiles_from_logs([REAL / "ardupilot_3x_mechanical_fail.log"], 4, None)
    v = fit_and_validate(profs, UAV.ocv_soc, UAV.ocv_table_v)
    cap = v.result.params["capacity_ah"]
    assert not cap.identifiable and "SOC swing" in cap.reason
    assert "at a bound" not in cap.reason and cap.value < 15.0
    assert v.checks[0].skill > 0.0


def test_a_second_rc_pair_only_where_resolved() -> None:
    """One-RC plant: the second pair is not kept, and the notes say why."""
    prof = synthetic_log(Truth(), 1.0, noise_v=NOISE_V, seconds=900)
    r = fit([prof], UAV.ocv_soc, UAV.ocv_table_v)
    assert r.n_rc == 1 and any(n.startswith("second RC pair not") for n in r.notes)


def test_several_logs_share_one_cell_and_get_their_own_initial_soc() -> None:
    a = synthetic_log(Truth(soc0=0.95), 1.0, seed=1, seconds=900)
    b = synthetic_log(Truth(soc0=0.70), 1.0, seed=2, seconds=900)
    r = fit([a, b], UAV.ocv_soc, UAV.ocv_table_v)
    assert r.soc0[a.name].value == pytest.approx(0.95, abs=0.02)
    assert r.soc0[b.name].value == pytest.approx(0.70, abs=0.02)
    assert r.params["r0_ohm"].value == pytest.approx(0.012, rel=0.05)


def test_fitted_set_runs_in_the_plant(tmp_path: Path) -> None:
    """The written file is a cell set the loader accepts; the plant with it reproduces the
    log it was fitted to (the same stepper and the plant agree)."""
    from packpilot.model.fit.cellset import cellset_dict

    prof = synthetic_log(Truth(), 1.0, noise_v=0.0, gain=1.0, seconds=900)
    v = fit_and_validate([prof], UAV.ocv_soc, UAV.ocv_table_v)
    out = tmp_path / "fitted.json"
    out.write_text(json.dumps(cellset_dict(v, "fitted", "uav_5ah")))
    cell = load_parameter_file(out)
    assert cell.capacity_ah == pytest.approx(5.0, rel=0.03)
    per_s = np.diff(prof.charge_ah) * 3600.0  # type: ignore[arg-type]
    tr = simulate_current(cell, per_s, 1.0, v.result.soc0[prof.name].value, 25.0)
    assert float(np.sqrt(np.mean((tr.voltage_v - prof.voltage_v) ** 2))) < 0.005


def test_cli_fit_real_log_writes_set_and_report(tmp_path: Path) -> None:
    log = REAL / "ardupilot_3x_underpowered.log"
    out, rep = tmp_path / "mine.json", tmp_path / "fit.html"
    res = RUNNER.invoke(app, ["fit", str(log), "--cells", "3", "--out", str(out),
                              "--report", str(rep), "--json"])  # fmt: skip
    assert res.exit_code == 0, res.output
    s = json.loads(res.stdout)
    assert s["verdict"] in ("usable", "low confidence", "refused")
    assert any("SOC swing" in f for f in s["not_identifiable"]), "13 % swing: capacity flagged"
    assert any("25.0 degC" in a for a in s["assumptions"]), "reference temperature stated"
    cell = load_parameter_file(out)
    # R0 at the reference temperature (the table follows the template's law around it)
    r0_25 = float(np.interp(25.0, cell.rc_temp_c, cell.r0_ohm[:, 0, 0]))
    assert 0.005 < r0_25 < 0.05
    assert float(cell.r0_ohm[0, 0, 0]) > r0_25  # colder: higher (-20 degC, borrowed law)
    page = rep.read_text()
    assert page.count("<svg") == 1 and "noise floor" in page and "straight line" in page
    assert "time to 3.5 V / 3.3 V" in page


@pytest.mark.parametrize(
    ("name", "args", "needle"),
    [
        ("ardupilot_3x_tradheli_brownout.log", ["--cells", "6"], "current sensor reads nothing"),
        ("ardupilot_3x_nan.log", ["--cells", "4"], "too short to validate"),
        ("ardupilot_3x_underpowered.log", [], "--cells"),
        ("px4_sample_log_small.ulg", [], "--battery"),
        ("px4_sample_px4_events.ulg", [], "no current measurement"),
    ],
)
def test_cli_fit_refuses_in_one_line(name: str, args: list[str], needle: str) -> None:
    res = RUNNER.invoke(app, ["fit", str(REAL / name), *args])
    assert res.exit_code == 2, res.output
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], lines


def test_time_to_a_level_ignores_a_pulse_dip() -> None:
    """A 2 s dip below 3.5 V under a pulse is not the pack reaching 3.5 V; a sustained fall is."""
    from packpilot.model.fit.validate import _first_below

    t = np.arange(0.0, 100.0)
    v = np.full(100, 3.7)
    v[20:22] = 3.4
    v[60:] = 3.45
    assert _first_below(t, v, 3.5) == pytest.approx(65.0)
    assert _first_below(t, v, 3.3) is None


def test_a_slow_branch_seen_through_its_capacitance_is_kept() -> None:
    """The real Maccor pulse test (a 9.4 A pulse, 30 min of relaxation, a 2C charge, a 2C
    discharge): its training part holds a rest after load, so the second RC pair is judged by
    Schwarz's criterion (BIC +29) and kept although its R2 and tau2 are not identified one by
    one — the data see it through C2 = tau2 / R2 — and the held-out discharge is predicted
    better than PyBOP's CMA-ES on the same split (42.55-42.9 mV over three runs,
    benchmarks/RESULTS.md). Before (a 10 % RMSE gain, here 7 %, and R2, tau2 each
    identified): one pair, 53.5 mV."""
    profs, _ = profiles_from_logs([REAL / "maccor_beep_xtesladiag_pulse.070"], None, None)
    v = fit_and_validate(profs, UAV.ocv_soc, UAV.ocv_table_v)
    r = v.result
    assert r.n_rc == 2
    kept = [n for n in r.notes if n.startswith("second RC pair kept")]
    assert kept and "rest(s) after load" in kept[0] and "C2 = tau2 / R2" in kept[0]
    taus = sorted(p.value for k, p in r.params.items() if k.startswith("tau"))
    assert taus[1] > 3.0 * taus[0]
    assert v.checks[0].rmse_v < 0.0425


def test_without_a_rest_after_load_a_second_pair_needs_a_clear_gain() -> None:
    """A plant-made 10 Hz flight whose OCV has an 80 mV bump (10 mV noise, one RC pair, no
    rest after load): a second pair lowers the training RMSE from 10.19 to 10.15 mV, which
    Schwarz's criterion alone accepts at 9,810 samples (+53); it then explains the corrected
    OCV's leftover shape (held-out 27.7 mV against 12.8 with one pair). Without a rest after
    load the second pair needs a 10 % gain: one pair kept, and the notes say why."""
    plant = ocv_plant_params(Truth(), ocv_bump(UAV.ocv_soc, 0.08))
    prof = synthetic_log(Truth(), 10.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=1,
                         plant=plant)  # fmt: skip
    v = fit_and_validate([prof], UAV.ocv_soc, UAV.ocv_table_v)
    assert v.result.n_rc == 1
    assert any("no rest after load" in n for n in v.result.notes)
    assert v.checks[0].rmse_v < 1.5 * NOISE_V
