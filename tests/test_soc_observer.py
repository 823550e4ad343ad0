"""Issue #28: the plant's sensor errors and the battery observer (EKF) of the SOC estimator,
on the real plant (the observer never imports it)."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from packpilot.config import SensorError, SensorsConfig, parse_config, read_toml
from packpilot.config.scenario import ScenarioConfig
from packpilot.errors import ConfigError
from packpilot.sim.loop import ClosedLoop
from packpilot.sim.sensors import Sensors, sensors_of

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def scenario(duration_s: float, **over: Any) -> ScenarioConfig:
    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["sim"]["duration_s"] = duration_s
    for key, val in over.items():
        data[key] = val
    return parse_config(data, "soc_observer_sensors")


def soc_state(loop: ClosedLoop) -> Any:
    return next(x for x in loop.core.compiled if x.method.name == "soc").st


def true_soc(loop: ClosedLoop) -> float:
    """The weakest cell's remaining / full charge (what the BMS should show)."""
    pack = loop.plant.pack
    soc, _ = pack.cell_states()
    cap = pack.capacity_ah[0]
    return float(np.min(soc[0] * cap) / np.min(cap))


def run(cfg: ScenarioConfig, soc0_error: float = 0.0, steps: int | None = None) -> ClosedLoop:
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    if soc0_error:
        st.soc[0, 0] = true_soc(loop) + soc0_error
    dt = cfg.sim.dt_s
    for k in range(steps if steps is not None else round(cfg.sim.duration_s / dt)):
        loop.step(k, dt)
    return loop


# ------------------------------------------------------------------------ sensor errors


def test_sensor_reads_gain_offset_quantum_and_delay() -> None:
    err = SensorError(gain=1.01, offset=0.2, quantum=0.05, delay_s=0.25)
    s = Sensors(SensorsConfig(current=err))
    truth = [np.array([[10.0 * k]]) for k in range(6)]
    reads = [float(s.current.read(0.1 * k, truth[k])[0, 0]) for k in range(6)]
    # at t = 0.5 the sample 0.25 s old is the one of t = 0.2 (latest at or before t - delay)
    assert reads[5] == pytest.approx(round((20.0 * 1.01 + 0.2) / 0.05) * 0.05)
    assert reads[0] == pytest.approx(round(0.2 / 0.05) * 0.05)  # before any: the oldest
    assert all(abs(r / 0.05 - round(r / 0.05)) < 1e-9 for r in reads)
    assert truth[5][0, 0] == 50.0  # the truth is never touched


def test_sensor_noise_is_seeded_and_absent_sections_read_truth() -> None:
    def draws(seed: int) -> np.ndarray:
        s = Sensors(SensorsConfig(seed=seed, cell_v=SensorError(noise_sigma=0.005)))
        return np.array([s.cell_v.read(0.0, np.full((1, 6), 3.7)) for _ in range(200)])

    a, b, c = draws(1), draws(1), draws(2)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.std(a - 3.7) == pytest.approx(0.005, rel=0.15)
    assert sensors_of(None) is None
    assert sensors_of(SensorsConfig()) is None  # every quantity perfect: the truth


def test_sensor_config_errors_name_the_field() -> None:
    with pytest.raises(ConfigError, match=r"sensors\.current\.gain"):
        scenario(1.0, sensors={"current": {"gain": 3.0}})


def test_plant_measures_with_the_configured_errors() -> None:
    cfg = scenario(5.0, sensors={"current": {"gain": 1.01, "offset": 0.2}})
    loop = run(cfg, steps=20)
    truth = float(loop.plant.pack.string_a[0, 0])
    loop.step(20, cfg.sim.dt_s)  # the step measures the plant as it was before it
    assert float(loop.m.bat.current_a[0, 0]) == pytest.approx(truth * 1.01 + 0.2, rel=1e-12)


# ------------------------------------------------------------------------ the observer


def test_observer_corrects_a_wrong_initial_soc_under_sensor_errors() -> None:
    """10 % wrong at the start, 5 mV noise, +1 % gain, +0.2 A offset: within 2 % after
    4 minutes of flight, where the coulomb counter is still ~10 % off; R0 near the plant's."""
    loop = run(scenario(240.0), soc0_error=-0.10)
    st = soc_state(loop)
    truth = true_soc(loop)
    assert bool(st.obs_ok[0, 0])
    assert abs(st.shown_soc[0, 0] - truth) < 0.02
    assert abs(st.soc[0, 0] - truth) > 0.08  # the fallback alone has not recovered
    r_true = float(np.sum(loop.plant.pack.r_cell[0]))
    assert st.r0_ohm[0, 0] == pytest.approx(r_true, rel=0.10)
    status = loop.core.status_of(0)
    assert status["soc_est"][0] == pytest.approx(st.shown_soc[0, 0])
    assert status["soc_fallback"][0] == pytest.approx(st.soc[0, 0])
    # terminal = EMF - R0 I - polarisation: the outputs reproduce the measured voltage
    m = loop.m.bat
    model_v = st.emf_v[0, 0] - st.r0_ohm[0, 0] * (m.current_a[0, 0] - st.offset_a[0, 0])
    assert model_v - st.v_rc_v[0, 0] == pytest.approx(m.voltage_v[0, 0], abs=6 * 0.03)


def test_diverged_observer_falls_back_to_the_coulomb_counter_with_an_event() -> None:
    """A cell-voltage sensor reading 0.8 V high: no SOC explains it, the innovations stay large,
    the window test fails, and the SOC shown is the fallback's."""
    cfg = scenario(120.0, sensors={"cell_v": {"offset": 0.8}})
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    kinds: list[str] = []
    dt = cfg.sim.dt_s
    for k in range(1200):
        loop.step(k, dt)
        kinds += [e.kind for e in loop.core.events()[0]]
    assert "SocObserverDiverged" in kinds
    assert "SocObserverResumed" not in kinds
    assert not bool(st.obs_ok[0, 0])
    assert st.shown_soc[0, 0] == st.soc[0, 0]
    assert loop.core.status_of(0)["soc_observer_ok"][0] is False


def test_observer_off_shows_the_coulomb_counter() -> None:
    cfg = scenario(30.0, soc={"observer": False})
    loop = run(cfg)
    st = soc_state(loop)
    assert st.shown_soc[0, 0] == st.soc[0, 0]
    assert np.isnan(st.emf_v[0, 0])


# ------------------------------------------------------------------------ predictions


def constant_load(current_a: float, soc0: float, cutoff_v: float, dt_s: float) -> ScenarioConfig:
    """The example at a constant load (a negative one: a charger at that current instead)."""
    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["pack"]["batteries"][0]["soc0"] = soc0
    data["load"] = {"kind": "current", "value": current_a}
    if current_a < 0:
        data["load"] = {"kind": "none"}
        data["charger"] = {"present": True, "rated_v": 60.0, "rated_a": 20.0, "voltage_v": 25.2,
                           "current_a": -current_a, "enable": True}  # fmt: skip
    data["soc"] = {"cutoff_cell_v": cutoff_v}
    data["sim"] = {"dt_s": dt_s, "duration_s": 7200.0}
    return parse_config(data, "constant_load")


def test_time_to_cutoff_and_to_go_match_the_plant_at_constant_load() -> None:
    """14 A from 95 %: over the last 10 minutes before the weakest cell reaches 3.3 V, the
    predicted time to cut-off is within 10 % (or 5 s) of the time the plant takes, and moves
    smoothly (load constant: never more than 5 % + 5 s between 1 s samples); the time to go is
    the remaining charge over the load (to the SOC's accuracy)."""
    cfg = constant_load(14.0, 0.95, 3.3, 0.5)
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    pred: list[tuple[float, float, float, float]] = []
    k = 0
    while float(np.min(loop.plant.pack.cell_voltage_now()[0])) > 3.3:
        loop.step(k, 0.5)
        k += 1
        if k % 2 == 0:
            pack = loop.plant.pack
            soc, _ = pack.cell_states()
            left = float(np.min(soc[0] * pack.capacity_ah[0]))
            amps = float(pack.string_a[0, 0])
            pred.append((loop.plant.t_s, st.time_to_cutoff_s[0, 0], st.time_to_go_s[0, 0],
                         left * 3600.0 / amps))  # fmt: skip
        assert k < 20000
    t_trip = loop.plant.t_s
    arr = np.array(pred)
    last = (arr[:, 0] >= t_trip - 600.0) & (arr[:, 0] >= 120.0)
    assert last.sum() > 300
    left = t_trip - arr[last, 0]
    err = np.abs(arr[last, 1] - left)
    assert np.all(err <= np.maximum(0.10 * left, 5.0)), float(np.max(err / np.maximum(left, 1)))
    jumps = np.abs(np.diff(arr[last, 1]))
    assert np.all(jumps <= 0.05 * arr[last, 1][:-1] + 5.0 + 1.0)  # + the 1 s that elapsed
    late = arr[:, 0] >= 300.0  # right to the SOC's accuracy: 2 % of 5 Ah at 14 A, and 3 %
    tol = 0.02 * 5.0 * 3600 / 14 + 0.03 * arr[late, 3]
    assert np.all(np.abs(arr[late, 2] - arr[late, 3]) <= tol)


def test_time_to_full_while_charging_and_none_while_discharging() -> None:
    """A CC/CV charge from 30 % at 5 A to 25.2 V (4.2 V per cell), with the example's sensor
    errors: sampled every 10 s from 10 minutes in to the end, the predicted time to full is
    within 5 % (or 15 s) of the time the plant takes until its charge current has tapered to
    the end current (C/20); the CV phase is part of it (a constant-current-to-100 % rule reads
    -9 % in the CC phase and cannot follow the taper). While charging there is no time to go
    or to cut-off, while discharging no time to full."""
    cfg = constant_load(-5.0, 0.30, 3.3, 0.5)
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    prm = next(x for x in loop.core.compiled if x.method.name == "soc").prm
    end_a = float(prm.full_current_a[0])
    assert end_a == pytest.approx(0.05 * float(np.min(loop.plant.pack.capacity_ah[0])))
    rows: list[tuple[float, float, float]] = []
    k = 0
    while loop.plant.t_s < 200.0 or -float(loop.plant.pack.string_a[0, 0]) > end_a:
        loop.step(k, 0.5)
        k += 1
        if k % 20 == 0:
            rows.append((loop.plant.t_s, float(st.time_to_full_s[0, 0]),
                         -float(loop.plant.pack.string_a[0, 0])))  # fmt: skip
            assert np.isnan(st.time_to_go_s[0, 0]) and np.isnan(st.time_to_cutoff_s[0, 0])
        assert k < 20000
    t_end = loop.plant.t_s
    arr = np.array(rows)
    cv = arr[arr[:, 2] < 0.95 * 5.0, 0]
    assert cv.size and t_end - cv[0] > 300.0  # the taper is a real part of the charge
    judged = arr[:, 0] >= 600.0
    left = t_end - arr[judged, 0]
    err = np.abs(arr[judged, 1] - left)
    assert np.all(err <= np.maximum(0.05 * left, 15.0)), float(np.max(err / left))
    dsg = constant_load(14.0, 0.95, 3.3, 0.5)
    loop = ClosedLoop.of(dsg, 1)
    for k in range(20):
        loop.step(k, 0.5)
    assert np.isfinite(soc_state(loop).time_to_go_s[0, 0])
    assert np.isnan(soc_state(loop).time_to_full_s[0, 0])


def test_time_to_full_from_60_percent_with_the_charge_path_and_the_cooling_taper() -> None:
    """h28full: the same CC/CV charge from 60 %, where the CV phase (420 s) is a third of
    the charge: from 10 minutes in to the end the prediction is within 5 % (or 15 s) of the
    plant's time. It needs the charge path (the charger's 10 mOhm output slope and the
    switch's 1 mOhm: the CV voltage reaches the cells 9 mV lower at 5 A, so the CC phase
    ends ~20 s earlier and the taper runs ~45 s longer than on the bare cell; 6.9 % before),
    the taper solved exactly and at a temperature on the way back to the charge's start
    (6.6 % with the present one); the model's CV phase begins within 10 s of the plant's.
    The charge path reaches the BMS from the pack's config."""
    cfg = constant_load(-5.0, 0.60, 3.3, 0.5)
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    prm = next(x for x in loop.core.compiled if x.method.name == "soc").prm
    assert loop.plant.infos[0].charge_path_ohm == pytest.approx((0.01 + 2 * 0.0005,))
    assert float(prm.full_path_ohm[0]) == pytest.approx(0.011 / 6)
    end_a = float(prm.full_current_a[0])
    rows: list[tuple[float, float]] = []
    corner = cv_model = math.nan  # when the plant's / the model's CV phase begins
    k = 0
    while loop.plant.t_s < 200.0 or -float(loop.plant.pack.string_a[0, 0]) > end_a:
        loop.step(k, 0.5)
        k += 1
        if math.isnan(corner) and -float(loop.plant.pack.string_a[0, 0]) < 0.99 * 5.0:
            corner = loop.plant.t_s
        if math.isnan(cv_model) and math.isfinite(st.cv_left_s[0, 0]):
            cv_model = loop.plant.t_s
        if k % 20 == 0:
            rows.append((loop.plant.t_s, float(st.time_to_full_s[0, 0])))
        assert k < 20000
    # measured 4 s late; on the bare cell (the path's drop left out of the CC phase) 42 s
    assert 0.0 <= cv_model - corner <= 10.0, (corner, cv_model)
    arr = np.array(rows)
    judged = arr[:, 0] >= 600.0
    left = loop.plant.t_s - arr[judged, 0]
    err = np.abs(arr[judged, 1] - left)
    assert np.all(err <= np.maximum(0.05 * left, 15.0)), float(np.max(err / left))


def test_charge_path_is_configurable_and_checked() -> None:
    """``[soc] charge_path_ohm`` overrides the pack's stated path (per series cell in the
    rules); a negative or non-finite one is refused naming the field."""
    from packpilot.control.soc.controller import build

    cfg = constant_load(-5.0, 0.60, 3.3, 0.5)
    loop = ClosedLoop.of(cfg, 1)
    info = loop.plant.infos[0]
    assert cfg.soc is not None
    prm, _st = build(cfg.soc.model_copy(update={"charge_path_ohm": 0.06}), [info])
    assert float(prm.full_path_ohm[0]) == pytest.approx(0.01)
    prm, _st = build(cfg.soc, [info])
    assert float(prm.full_path_ohm[0]) == pytest.approx(0.011 / 6)
    for bad in (-0.01, math.inf):
        data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
        data["soc"] = {"charge_path_ohm": bad}
        with pytest.raises(ConfigError, match="charge_path_ohm"):
            parse_config(data, "charge_path")


def test_time_to_cutoff_moves_smoothly_through_the_flight_profile() -> None:
    """The shipped example's flight (take-off, hover, manoeuvres: the current steps by tens of
    %): sampled every second after the first 5 minutes, the time to cut-off never moves by more
    than 5 % + 5 s (+ the second that passed), because it assumes the recent average load."""
    cfg = scenario(900.0)
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    samples = []
    for k in range(9000):
        loop.step(k, 0.1)
        if k % 10 == 9 and loop.plant.t_s >= 300.0:
            samples.append(float(st.time_to_cutoff_s[0, 0]))
    ttc = np.array(samples)
    assert np.isfinite(ttc).all()
    assert np.all(np.abs(np.diff(ttc)) <= 0.05 * ttc[:-1] + 5.0 + 1.0)


# ------------------------------------------------------------------------ issue #28, h28cut


@functools.cache
def cutoff_trace(flight: bool) -> tuple[np.ndarray, float]:
    """The acceptance's time-to-cut-off run: the shipped example with its sensor errors
    (5 mV cell noise, current +1 % and +0.2 A), the BMS started 10 % low, from 95 % at a
    constant 14 A (or the example's flight repeated) until the weakest cell's true voltage
    reaches 3.3 V. Every 0.1 s step: (t, time to cut-off, recent average load); and the trip."""
    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["soc"] = {"cutoff_cell_v": 3.3}
    data["sim"]["duration_s"] = 20000.0
    if flight:
        data["load"]["repeat"] = True
    else:
        data["load"] = {"kind": "current", "value": 14.0}
    cfg = parse_config(data, "cutoff")
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    st.soc[0, 0] = true_soc(loop) - 0.10
    rows = []
    k = 0
    while float(np.min(loop.plant.pack.cell_voltage_now()[0])) > 3.3:
        loop.step(k, 0.1)
        k += 1
        rows.append((loop.plant.t_s, float(st.time_to_cutoff_s[0, 0]), float(st.load_avg_a[0, 0])))
        assert k < 20000
    return np.array(rows), float(loop.plant.t_s)


@pytest.mark.parametrize("flight", [False, True], ids=["constant_14a", "flight_repeated"])
def test_time_to_cutoff_within_10_percent_over_the_last_10_minutes(flight: bool) -> None:
    """Issue #28's acceptance: over the last 10 minutes before the trip (after the first 5,
    up to 10 s before it, where 10 % is one second), read at every 0.1 s step, the time to
    cut-off is within 10 % of the time the plant takes; sampled every second it never moves by
    more than 5 % + 5 s (+ the second that passed) while the recent load moves by < 20 %. On
    the flight the trip comes on a gust above the average load (the margin ``load_exc_a``)."""
    arr, t_trip = cutoff_trace(flight)
    t, ttc = arr[:, 0], arr[:, 1]
    left = t_trip - t
    judged = (left <= 600.0) & (t >= 300.0) & (left >= 10.0)
    assert judged.sum() > 5000
    rel = np.abs(ttc[judged] - left[judged]) / left[judged]
    assert np.all(rel <= 0.10), (float(np.max(rel)), float(left[judged][np.argmax(rel)]))
    sec = arr[9::10]
    sec = sec[(t_trip - sec[:, 0] <= 600.0) & (sec[:, 0] >= 300.0)]
    steady = np.abs(np.diff(sec[:, 2])) <= 0.2 * np.abs(sec[:-1, 2])
    jumps = np.abs(np.diff(sec[:, 1])) > 0.05 * sec[:-1, 1] + 5.0 + 1.0
    assert not np.any(jumps & steady)


def test_time_to_cutoff_counts_down_like_a_clock_near_the_trip() -> None:
    """At a constant load, in the last minute before the trip: the time to cut-off falls by
    the 0.1 s of every step between its 1 s predictions (counted down, never a stale reading:
    at least 9 steps in 10), and over every second by 1 s within 0.5 s (each new prediction
    is approached over 5 s, so the filter's ~1 mV jitter, ~1 s at the knee, does not show)."""
    arr, t_trip = cutoff_trace(False)
    last = arr[(t_trip - arr[:, 0] <= 60.0) & (arr[:, 1] > 0.0)]
    assert len(last) > 500
    assert np.mean(np.isclose(np.diff(last[:, 1]), -0.1, atol=1e-9)) >= 0.85
    per_s = np.diff(last[::10, 1])
    assert np.all(np.abs(per_s + 1.0) <= 0.5), per_s


# ------------------------------------------------------------------------ issue #28, h28soc


@pytest.mark.parametrize("cell", ["uav_5ah", "lfp_storage"])
def test_observer_ocv_is_the_plants_at_every_temperature(cell: str) -> None:
    """The observer's OCV carries the cell set's entropic term as the plant has it (at -10 degC
    the plant's OCV moves by up to 6.4 mV on uav_5ah and 12.2 mV on lfp_storage, where 1 mV is
    ~2 % of SOC on the plateau): within 0.5 mV of the plant's OCV from -20 to 50 degC over the
    SOC range."""
    from packpilot.control.soc import rules
    from packpilot.model.cell import load_parameter_set, ocv_v

    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["pack"]["cell"] = cell
    cfg = parse_config(data, "ocv_temperature")
    loop = ClosedLoop.of(cfg, 1)
    prm = next(x for x in loop.core.compiled if x.method.name == "soc").prm
    params = load_parameter_set(cell)
    worst = 0.0
    for temp in (-20.0, -10.0, 0.0, 12.5, 25.0, 40.0, 50.0):
        for soc in np.linspace(0.02, 0.98, 49):
            mine, _ = rules.ocv_t(prm, float(soc), temp)
            plant = float(ocv_v(params, soc, temp))
            worst = max(worst, abs(mine - plant))
    assert worst < 5e-4, worst
    moved = max(abs(rules.ocv_t(prm, s, -10.0)[0] - rules.ocv_t(prm, s, 25.0)[0])
                for s in (0.02, 0.3, 0.98))  # fmt: skip
    assert moved > 0.005  # the term is there


def true_socs(loop: ClosedLoop) -> np.ndarray:
    """Per battery, its weakest cell's remaining / full charge."""
    pack = loop.plant.pack
    soc, _ = pack.cell_states()
    cap = pack.capacity_ah[0]
    out = []
    for i in loop.plant.topology.traction:
        cells = pack.cell_string == i
        out.append(float(np.min(soc[0, cells] * cap[cells]) / np.min(cap[cells])))
    return np.array(out)


def test_an_inserted_battery_starts_from_its_rested_ocv() -> None:
    """A battery plugged in at 120 s, whose slot held a belief 10 % off (the BMS cannot know
    where it has been): its first reading, at rest, gives the observer its SOC at once, with
    the variance that reading supports, and the observer is the source from that sample on;
    under the example's sensor errors the SOC shown stays within 3 % of the plant's from the
    insertion on. The fallback (the coulomb counter) drops the stale belief too and reads the
    same sample's OCV (as at power-up), so the consistency check compares the observer with a
    counter that starts where the battery is, and never rejects it here."""
    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["sensors"] = {"seed": 28, "cell_v": {"noise_sigma": 0.005},
                       "current": {"gain": 1.01, "offset": 0.2}}  # the acceptance's  # fmt: skip
    main = data["pack"]["batteries"][0]
    data["pack"]["batteries"] = [  # B about as charged as A is by then: a small inrush
        {**main, "name": "A", "soc0": 0.80},
        {**main, "name": "B", "soc0": 0.72, "present_from_s": 120.0},
    ]
    data["load"] = {"kind": "current", "value": 12.0}
    data["sim"]["duration_s"] = 400.0
    cfg = parse_config(data, "insertion")
    loop = ClosedLoop.of(cfg, 1)
    st = soc_state(loop)
    st.soc[0, 1] = true_socs(loop)[1] - 0.10  # the slot's stale belief
    errs, ok = [], []
    for k in range(4000):
        loop.step(k, 0.1)
        if loop.m.bat.present[0, 1]:  # the BMS has seen it (from its 120 s sample on)
            errs.append(float(st.shown_soc[0, 1] - true_socs(loop)[1]))
            ok.append(bool(st.obs_ok[0, 1]))
            if len(ok) == 1:
                assert abs(st.soc[0, 1] - true_socs(loop)[1]) < 0.03  # the fallback: afresh
                sigma = math.sqrt(st.soc_var[0, 1])
                assert 0.002 < sigma < 0.06, sigma  # what one rested reading supports
    assert all(ok)
    assert np.max(np.abs(errs)) < 0.03, np.max(np.abs(errs))


@pytest.mark.parametrize("belief", [0.90, 1.10])
def test_capacity_is_learned_within_5_percent_over_one_full_cycle(
    belief: float, tmp_path: Path
) -> None:
    """The BMS told a capacity 10 % off: one full cycle (10 A from 95 % to ~8 %, rest, CC/CV
    charge to full, rest; the acceptance's sensor errors) brings the observer's capacity within
    5 % of the plant's weakest cell, and its 1-sigma says so (below the 10 % prior)."""
    from benchmarks.bench_observer import capacity_cycle

    res = capacity_cycle(belief, tmp_path / "cycle.csv")
    assert abs(res["cap_err_end"]) <= 0.05, res
    assert res["cap_sigma_rel"] < 0.05, res
    assert res["soc_max"] <= 0.03, res


def test_the_current_sensor_offset_is_learned_over_one_full_cycle(tmp_path: Path) -> None:
    """The offset state is estimated by default (h28mis): over one full cycle (10 A down,
    rest, CC/CV 5 A up; the acceptance's +1 % gain and +0.2 A offset) the charge in both
    directions tells the offset apart from the capacity, so the state ends within 0.05 A of
    the sensor's +0.2 A and its 1-sigma says it is known (below its 0.3 A prior); the SOC
    and the capacity stay within their targets."""
    from benchmarks.bench_observer import SENSORS, capacity_cycle

    res = capacity_cycle(1.0, tmp_path / "cycle.csv")
    assert abs(res["offset_end_a"] - SENSORS["current"]["offset"]) <= 0.05, res
    assert res["offset_sigma_end_a"] < 0.1, res
    assert abs(res["cap_err_end"]) <= 0.05, res
    assert res["soc_max"] <= 0.03, res


def test_an_inrush_at_the_start_is_not_read_as_soc_or_polarisation() -> None:
    """uav_dual_parallel with the campaign's draw of run 16 (seed 28: A at 1.6 degC) and the
    acceptance's sensors: the batteries are 2 V apart, so A's first seconds are a 37 A inrush
    into B. The observer starts from an open-circuit reading (its SOC read off the OCV), so
    its polarisation prior is narrow: over the first 10 s A's SOC state stays within 3 sigma
    of the plant's (with a 50 mV prior it read the inrush as +7 % SOC, sigma 0.8 %, and 118 mV
    of polarisation within 3 s), and its capacity state within 10 % of the prior over the
    first minute (it fell to 0.62x to undo that)."""
    from benchmarks.bench_soc_campaign import FAMILIES, SPREAD
    from benchmarks.bench_soc_campaign import scenario as campaign_scenario

    from packpilot.campaign import draw_run, parse_spreads
    from packpilot.campaign.execute import stack_overrides

    cfg = campaign_scenario(next(f for f in FAMILIES if f.name == "parallel"))
    draw = draw_run(parse_spreads(SPREAD), 28, 16, cfg.pack.ambient_c)
    loop = ClosedLoop.of(cfg, n_packs=1, overrides=stack_overrides([draw]))
    st = soc_state(loop)
    dt = cfg.sim.dt_s
    cap0 = float(loop.core.tp.capacity_ah[0, 0])
    worst_z = 0.0
    caps = []
    for k in range(round(60.0 / dt)):
        loop.step(k, dt)
        if loop.plant.t_s <= 10.0 + 1e-9:
            err = st.x[0, 0, 0] - true_socs(loop)[0]
            worst_z = max(worst_z, abs(err) / math.sqrt(st.cov[0, 0, 0, 0]))
        caps.append(float(st.x[0, 0, 3]))
    assert worst_z <= 3.0, worst_z
    assert min(caps) >= 0.9 * cap0, (min(caps), cap0)
    assert max(caps) <= 1.1 * cap0, (max(caps), cap0)


def test_the_observer_counts_the_equalizer_currents_of_the_group_it_reads() -> None:
    """The cells of the group the observer reads carry the battery current, plus what every
    equalizer draws from the battery as power (over the efficiency into a group), minus that
    group's own equalizer current; the currents are the last step's final commands, clipped to
    the equalizers' range (telecom_string's weakest group got 2.8 Ah over a recharge that the
    battery's current sensor never saw)."""
    from packpilot.contract.arrays import cmd_arrays
    from packpilot.control.soc import rules

    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["balancer"] = {"present": True, "max_current_a": 2.0, "efficiency": 0.8}
    loop = ClosedLoop.of(parse_config(data, "equalizers"), 1)
    part = next(x for x in loop.core.compiled if x.method.name == "soc")
    prm, st = part.prm, part.st
    for k in range(5):
        loop.step(k, 0.1)
    cmd = cmd_arrays(1, 1, 6)
    cmd.balancer_set[0] = True
    cmd.balancer_a[0, 0, :] = (0.0, 0.0, 7.0, 0.0, 0.5, 0.0)  # 7 A: beyond the 2 A range
    rules.note_balancer_packs(prm, st, loop.core.tp, loop.m, cmd)
    assert list(st.bal_a[0, 0]) == [0.0, 0.0, 2.0, 0.0, 0.5, 0.0]
    st.weak_g[0, 0] = 2
    gv = loop.m.bat.group_v[0, 0, :6]
    drawn = (2.0 * gv[2] + 0.5 * gv[4]) / 0.8 / float(np.sum(gv))
    got = rules._group_current(prm, st, loop.m, 0, 0, 10.0)
    assert got == pytest.approx(10.0 + drawn - 2.0, rel=1e-12)
    st.weak_g[0, 0] = -1  # the min cell, group unknown: the battery current
    assert rules._group_current(prm, st, loop.m, 0, 0, 10.0) == 10.0


# ------------------------------------------------------------------------ issue #28, h28cold


def test_a_charge_from_the_foot_of_the_ocv_with_a_wrong_start_keeps_soc_and_capacity() -> None:
    """Issue #28 campaign, staged charging: every miss was a battery starting at 0-2 % SOC (the
    OCV's steep, curved foot) with the BMS 10 % high. Linearised at its point estimate, the
    filter's first corrections overshot and left a SOC deviation of ~0.1 % with the error still
    ~1 %; so over-confident, it put the next innovations into the capacity (+26 % here within
    minutes) and the SOC missed 2 % RMS. Here: the test pack charged at 2C from empty at -5 degC
    with the acceptance's sensor errors and a 10 % wrong start. From 5 minutes on the SOC is
    within 2 % RMS and 3 % max, and the capacity state never leaves 5 % of the weakest cell's
    (the OCV term linearised over the SOC's uncertainty, ``observer.ocv_over_spread``)."""
    from packpilot.control.soc import observer as ob

    data = constant_load(-10.0, 0.0, 3.3, 1.0).model_dump(mode="json")
    data["pack"]["ambient_c"] = -5.0
    data["sensors"]["soc0_error"] = 0.10
    data["sim"]["duration_s"] = 900.0
    loop = ClosedLoop.of(parse_config(data, "foot_of_the_ocv"), 1)
    st = soc_state(loop)
    q_true = float(np.min(loop.plant.pack.capacity_ah[0]))
    errs, caps = [], []
    for k in range(900):
        loop.step(k, 1.0)
        caps.append(float(st.x[0, 0, ob.X_CAP]))
        if loop.plant.t_s >= 300.0:
            errs.append(abs(float(st.shown_soc[0, 0]) - true_soc(loop)))
    assert true_soc(loop) > 0.4  # it charged (2C for 15 minutes)
    e = np.array(errs)
    assert float(np.sqrt(np.mean(e * e))) <= 0.02 and float(e.max()) <= 0.03, (
        float(np.sqrt(np.mean(e * e))), float(e.max()))  # fmt: skip
    assert max(caps) <= 1.05 * q_true and min(caps) >= 0.95 * q_true, (min(caps), max(caps))


def test_the_ocv_over_the_soc_spread_is_the_point_ocv_where_straight_and_averages_a_knee() -> None:
    """``ocv_over_spread``: on a straight stretch it is the point value and slope with no extra
    variance; across a knee it is still the point value, with the chord's slope and the mean
    square of the linearisation's residual over the three Gauss-Hermite points (what the point
    linearisation would have over-trusted)."""
    from packpilot.control.soc import observer as ob

    ocv_soc = np.array([0.0, 0.1, 1.0])
    ocv_v = np.array([3.0, 3.5, 4.2])  # steep foot, then flat: a knee at 10 %
    du_t, du_tab = np.array([0.0, 1.0]), np.zeros(6)
    args = (ocv_soc, ocv_v, du_t, du_tab, math.nan)
    m, s, v = ob.ocv_over_spread(*args, 0.5, 0.01**2, 25.0)
    f0, s0 = ob.ocv_at(ocv_soc, ocv_v, 0.5)
    assert m == pytest.approx(f0, abs=1e-12) and s == pytest.approx(s0) and v < 1e-15
    h = math.sqrt(3.0) * 0.05
    m, s, v = ob.ocv_over_spread(*args, 0.1, 0.05**2, 25.0)
    fm, fp = ob.ocv_at(ocv_soc, ocv_v, 0.1 - h)[0], ob.ocv_at(ocv_soc, ocv_v, 0.1 + h)[0]
    # the point value (not the mean), the chord, and the mean square of the linearisation's
    # residual OCV(x) - OCV(soc) - slope (x - soc) over the three points
    assert m == pytest.approx(3.5) and s == pytest.approx((fp - fm) / (2.0 * h))
    res = [fm - 3.5 + s * h, 0.0, fp - 3.5 - s * h]
    var = (res[0] ** 2 + res[2] ** 2) / 6.0
    assert v == pytest.approx(var) and v > 1e-4
    mean = (fm + 4.0 * 3.5 + fp) / 6.0
    assert v >= (mean - 3.5) ** 2 > 1e-4  # the curvature's bias is counted as noise
    assert ob.ocv_over_spread(*args, 0.05, 0.0, 25.0) == pytest.approx((3.25, 5.0, 0.0))


# ------------------------------------------------------------------------ issue #28, h28cold2


def test_a_known_soc_on_the_ocvs_curve_stays_put_and_the_source_voltage_follows_a_step() -> None:
    """What sequencing's zero-load prediction reads from the observer (docs/parallel_discharge.md
    rule 8a): R0, and through the model the source voltage ``EMF - v_rc`` (= ``V + I R0``), the
    voltage the battery shows the instant its current stops. One battery rests 20 s at 96 %
    SOC (the OCV's curved top; the observer starts at the right SOC with its 15 % prior, so
    the spread linearisation is active, checked below), then takes 30 A.

    * At rest, a filter whose state is right sees no innovation: the SOC stays within 0.05 %,
      the polarisation within 0.5 mV per cell of zero, the source voltage within 5 mV of the
      plant's. Broken by predicting the spread's mean OCV instead of the point value (h28cold's
      first version, mutant ``ocv-spread-mean``): the curvature's bias read as an innovation
      moved the right SOC by 2.4 % at the first reading and put 11 mV per cell into the
      polarisation at rest (source voltage 48 mV off), and ``r_scale`` learned 1 % differently
      at the step; in ``bench_zero_load``
      seed 230 that shifted rule 8b/8c's hand-over cycle by a second and the load loss met a
      just-closed battery at 1.128x its charge limit.
    * Through the step: R0 within 2 % of the plant's ohmic resistance from the first
      corrected period, and the polarisation tracks the step: the source-voltage error (the
      one-RC model against the plant's two time constants: ~38 mV right after the step) falls
      back below 20 mV within 20 s and stays there."""
    from packpilot.control.soc import observer as ob
    from packpilot.model import loads

    data = read_toml(EXAMPLES / "soc_observer_sensors.toml")
    data["pack"]["batteries"][0].update(soc0=0.96, cell_soc_spread=0.0, cell_capacity_spread=0.0)
    data.pop("sensors")
    data["load"] = {"kind": "current", "value": 1.0}
    data["sim"] = {"dt_s": 0.5, "duration_s": 80.0}
    loop = ClosedLoop.of(parse_config(data, "load_step"), 1)
    rest_s, amps = 20.0, 30.0
    loop.profile = loads.LoadProfile(kind="current", t_s=np.array([0.0, rest_s, 1e6]),
                                     value=np.array([0.0, amps, amps]))  # fmt: skip
    part = next(x for x in loop.core.compiled if x.method.name == "soc")
    st, prm = part.st, part.prm
    slots = {ch.name: s for s, ch, _ in loop.core.status_channels()}
    pack = loop.plant.pack
    lin_var0 = math.nan
    rows = []
    for k in range(160):
        if k == 1:  # the spread linearisation is active here: the OCV is curved over the prior
            _, _, lin_var0 = ob.ocv_over_spread(
                prm.ocv_soc, prm.ocv_v, prm.du_t, prm.du_tab, prm.t_ref_c,
                float(st.x[0, 0, ob.X_SOC]), float(st.cov[0, 0, ob.X_SOC, ob.X_SOC]), 20.0,
            )  # fmt: skip
        t0 = loop.plant.t_s
        loop.step(k, 0.5)
        s = loop.core.status[0][0]
        src_err = s[slots["soc_emf_v"]] - s[slots["soc_v_rc_v"]] - float(np.sum(pack.e_cell[0]))
        r0_err = s[slots["soc_r0_ohm"]] / float(np.sum(pack.r_cell[0])) - 1.0
        soc_err = float(st.x[0, 0, ob.X_SOC]) - true_soc(loop)
        rows.append((t0, src_err, r0_err, soc_err, float(st.x[0, 0, ob.X_V1])))
    assert lin_var0 > (0.005 / 6) ** 2, lin_var0  # more than the cell's voltage noise
    a = np.array(rows)
    rest = a[(a[:, 0] >= 0.5) & (a[:, 0] < rest_s)]  # from the observer's first correction
    assert np.max(np.abs(rest[:, 3])) <= 0.0005, np.max(np.abs(rest[:, 3]))
    assert np.max(np.abs(rest[:, 4])) <= 0.0005, np.max(np.abs(rest[:, 4]))
    assert np.max(np.abs(rest[:, 1])) <= 0.005, np.max(np.abs(rest[:, 1]))
    step = a[a[:, 0] >= rest_s + 0.5]  # from the first period corrected under the load
    assert np.max(np.abs(step[:, 2])) <= 0.02, np.max(np.abs(step[:, 2]))
    settled = a[a[:, 0] >= rest_s + 20.0]
    assert np.max(np.abs(settled[:, 1])) <= 0.020, np.max(np.abs(settled[:, 1]))
