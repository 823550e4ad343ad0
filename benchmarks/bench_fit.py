"""Issue #27 acceptance: `packpilot fit` on synthetic logs made by the plant from known
parameters, and on the real flight logs of examples/logs/real.

Synthetic (1 Hz and 10 Hz, 10 mV one-sigma voltage noise, 1 % current gain error, 30 s rest
at the start, 25 min flight, three seeds each): R0 within 5 %, capacity within 3 % when the SOC
swing is >= 30 %, held-out RMSE within 1.5x the injected noise, tau1 < 2 s flagged not
identifiable at 1 Hz.

Real: per log, whether it imports (or the one line it is refused with), the fit's CPU time,
held-out RMSE and max error per cell, the log's noise floor, skill against the straight line,
SOC swing and verdict. Series cell counts come from the logs' resting voltage (ArduPilot 3.x
logs carry none); the autopilot's configured capacity (PARM BATT_CAPACITY) is shown beside the
fitted one.

Validation both ways (``--validate time`` and ``--validate flights``, leave one flight out):
the three-flight plant logs and every real log, per held-out part (PyBOP not rerun).

Standalone: ``python benchmarks/bench_fit.py``; in ``make bench`` through run_all.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
REAL = HERE.parent / "examples" / "logs" / "real"
SEEDS = (1, 2, 3)
NOISE_V = 0.010
SERIES = {
    # log: series cells, from the resting voltage at the log's start
    "ardupilot_3x_mechanical_fail.log": 4,  # 16.9 V at rest (4.23 V/cell)
    "ardupilot_3x_robert_lefebvre_octo_PM.log": 4,  # 15.0 V
    "ardupilot_3x_underpowered.log": 3,  # 12.1 V
    "ardupilot_3x_tradheli_brownout.log": 3,  # 12.0 V
    "ardupilot_3x_nan.log": 4,
    "arducopter_dronekit_flight_battery.tlog": 3,  # 12.28 V (4.09 V/cell)
}


PYBOP = os.environ.get("PACKPILOT_PYBOP_PYTHON")
"""Interpreter with PyBOP installed (its own environment: PyBOP 26.3 needs numpy < 2.4);
unset = the PyBOP columns are left out."""


def _pybop(prof: Any, split: int, uav: Any = None) -> dict[str, Any]:
    """The same split fitted with PyBOP's CMA-ES, started where PackPilot's first start is,
    with the same chemistry's OCV as PackPilot's fit (``uav``; default uav_5ah)."""
    if not PYBOP:
        return {}
    import numpy as np

    from packpilot.model.cell import load_parameter_set
    from packpilot.model.fit.fit import _guess_capacity, _soc_from_ocv

    uav = uav if uav is not None else load_parameter_set("uav_5ah")
    train = prof.window(0, split)
    q0 = _guess_capacity([train], uav.ocv_soc, uav.ocv_table_v)
    s0 = _soc_from_ocv(float(prof.voltage_v[0]), uav.ocv_soc, uav.ocv_table_v)
    with tempfile.TemporaryDirectory() as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.json"
        np.savez(src, t_s=prof.t_s, current_a=prof.current_a, voltage_v=prof.voltage_v,
                 split=split, ocv_soc=uav.ocv_soc, ocv_v=uav.ocv_table_v, soc0=s0,
                 capacity_ah=q0, r0_ohm=0.01, r1_ohm=0.005, tau1_s=20.0)  # fmt: skip
        run = subprocess.run([PYBOP, str(HERE / "pybop_cmaes.py"), str(src), str(dst)],
                             capture_output=True, text=True, timeout=1800)  # fmt: skip
        if run.returncode != 0:
            return {"pybop": f"failed: {run.stderr.strip().splitlines()[-1][:120]}"}
        out = json.loads(dst.read_text())
    return {
        "pybop_heldout_rmse_mV": 1000 * out["heldout_rmse_v"],
        "pybop_heldout_max_mV": 1000 * out["heldout_max_v"],
        "pybop_cpu_s": out["fit_cpu_s"],
        "pybop_r0_mOhm": 1000 * out["fitted"]["R0 [Ohm]"],
    }


def _synthetic() -> list[dict[str, Any]]:
    from packpilot.model.cell import load_parameter_set
    from packpilot.model.fit.fit import fit
    from packpilot.model.fit.synthetic import Truth, synthetic_log
    from packpilot.model.fit.validate import fit_and_validate

    uav = load_parameter_set("uav_5ah")
    rows = []
    truth = Truth()
    for rate in (1.0, 10.0):
        for seed in SEEDS:
            prof = synthetic_log(truth, rate, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=seed)
            t0 = time.process_time()
            v = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v)
            cpu = time.process_time() - t0
            p, c = v.result.params, v.checks[0]
            rows.append({
                "case": f"{rate:g} Hz seed {seed}, tau1 {truth.tau1_s:g} s",
                "r0_err_pct": 100 * (p["r0_ohm"].value / truth.r0_ohm - 1),
                "capacity_err_pct": 100 * (p["capacity_ah"].value / truth.capacity_ah - 1),
                "tau1_s": p["tau1_s"].value,
                "soc_swing_pct": 100 * c.soc_swing,
                "heldout_rmse_over_noise": c.rmse_v / NOISE_V,
                "noise_floor_mV": 1000 * c.noise_floor_v,
                "skill": c.skill,
                "verdict": v.verdict,
                "fit_cpu_s": cpu,
                "heldout_rmse_mV": 1000 * c.rmse_v,
                "ocv": "default" if v.result.ocv_fit is None else "corrected",
            })  # fmt: skip
            if rate == 1.0 and seed == 1:
                rows[-1].update(_pybop(prof, int(len(prof.t_s) * 0.6)))
    rows += _synthetic_ocv(uav)
    for seed in SEEDS:
        short = Truth(tau1_s=1.0)
        prof = synthetic_log(short, 1.0, noise_v=NOISE_V, gain=1.01, seed=seed)
        r = fit([prof], uav.ocv_soc, uav.ocv_table_v)
        tau = r.params["tau1_s"]
        rows.append({
            "case": f"1 Hz seed {seed}, tau1 1 s", "tau1_s": tau.value,
            "tau1_flagged": not tau.identifiable, "flag": tau.reason,
            "r0_err_pct": 100 * (r.params["r0_ohm"].value / short.r0_ohm - 1),
            "r0_flagged": not r.params["r0_ohm"].identifiable,
            "r0_plus_r1_err_pct": 100 * (
                (r.params["r0_ohm"].value + r.params["r1_ohm"].value)
                / (short.r0_ohm + short.r1_ohm) - 1
            ),
            "capacity_err_pct": 100 * (r.params["capacity_ah"].value / short.capacity_ah - 1),
            "fit_cpu_s": r.fit_time_s,
        })  # fmt: skip
    return rows


def _synthetic_ocv(uav: Any) -> list[dict[str, Any]]:
    """A plant-made flight from a cell whose OCV is not the default (an 80 mV bump at 75 %
    SOC): held-out RMSE with the OCV fitted and with the default kept, the same log."""
    from packpilot.model.fit.synthetic import Truth, ocv_bump, ocv_plant_params, synthetic_log
    from packpilot.model.fit.validate import fit_and_validate

    truth = Truth()
    plant = ocv_plant_params(truth, ocv_bump(uav.ocv_soc, 0.08))
    rows = []
    for rate, seed in ((1.0, 1), (1.0, 2), (10.0, 1)):
        prof = synthetic_log(truth, rate, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=seed,
                             plant=plant)  # fmt: skip
        v = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v)
        d = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v, fit_ocv=False)
        o = v.result.ocv_fit
        rows.append({
            "case": f"{rate:g} Hz seed {seed}, OCV +80 mV bump at 75 % SOC",
            "ocv": "default" if o is None else f"corrected {o.window[0]:.2f}..{o.window[1]:.2f}",
            "heldout_rmse_mV": 1000 * v.checks[0].rmse_v,
            "default_ocv_heldout_mV": 1000 * d.checks[0].rmse_v,
            "heldout_rmse_over_noise": v.checks[0].rmse_v / NOISE_V,
            "capacity_err_pct": 100 * (v.result.params["capacity_ah"].value / truth.capacity_ah
                                       - 1),
            "capacity_flag": v.result.params["capacity_ah"].reason[:40],
        })  # fmt: skip
    return rows


def _batt_capacity(path: Path) -> str:
    if path.suffix == ".tlog":
        from packpilot.io.flightlog import read_flight_log

        notes = " ".join(read_flight_log(path).notes)
        t = re.search(r"BATT_CAPACITY parameter: ([0-9]+) mAh", notes)
        return f"{t.group(1)} mAh" if t else ""
    if path.suffix != ".log":
        return ""
    m = re.search(r"^PARM, BATT_CAPACITY, ([0-9.]+)", path.read_text(errors="replace"), re.M)
    return f"{float(m.group(1)):.0f} mAh" if m else ""


def _fit_row(prof: Any, uav: Any) -> dict[str, Any]:
    """One profile fitted and validated (60 / 40), with PyBOP on the same split."""
    from packpilot.model.fit.validate import fit_and_validate

    t1 = time.process_time()
    v = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v)
    cpu = time.process_time() - t1
    c = v.checks[0]
    p = v.result.params
    d = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v, fit_ocv=False).checks[0]
    o = v.result.ocv_fit
    row = {
        "fit_cpu_s": cpu,
        "default_ocv_heldout_mV": 1000 * d.rmse_v,
        "ocv": "default" if o is None else f"corrected {o.window[0]:.2f}..{o.window[1]:.2f}",
        "heldout_rmse_mV": 1000 * c.rmse_v, "heldout_max_mV": 1000 * c.max_err_v,
        "noise_floor_mV": 1000 * c.noise_floor_v,
        "rmse_over_noise": c.rmse_v / max(c.noise_floor_v, 1e-6),
        "line_rmse_mV": 1000 * c.baseline_rmse_v, "skill": c.skill,
        "soc_swing_pct": 100 * c.soc_swing,
        "r0_mOhm": 1000 * p["r0_ohm"].value,
        "capacity_ah": p["capacity_ah"].value,
        "self_heating": "heat_c_j_per_k" in p,
        "verdict": v.verdict,
    }  # fmt: skip
    row.update(_pybop(prof, int(len(prof.t_s) * 0.6), uav))
    return row


def _cycler_row(path: Path) -> dict[str, Any]:
    """A lab cycler export (one cell): imports, fit, PyBOP on the same split."""
    from packpilot.errors import PackPilotError
    from packpilot.model.cell import load_parameter_set
    from packpilot.replay.fitlogs import cycler_profile

    row: dict[str, Any] = {"log": path.name, "battery": "cell"}
    t0 = time.process_time()
    try:
        prof, _ = cycler_profile(path, None)
    except PackPilotError as err:
        row["imports"] = f"refused: {str(err).split(': ', 1)[1]}"
        return row
    row["imports"] = "yes (Maccor text export; lab cycler, 1 cell)"
    row["import_cpu_s"] = time.process_time() - t0
    row.update(_fit_row(prof, load_parameter_set("uav_5ah")))
    return row


def _real() -> list[dict[str, Any]]:
    from packpilot.errors import PackPilotError
    from packpilot.io.cycler import is_cycler_export
    from packpilot.io.flightlog import read_flight_log
    from packpilot.model.cell import load_parameter_set
    from packpilot.replay.fitlogs import battery_profile

    uav = load_parameter_set("uav_5ah")
    rows = []
    for path in sorted(REAL.glob("*")):
        if is_cycler_export(path):
            rows.append(_cycler_row(path))
            continue
        if path.suffix not in (".ulg", ".bin", ".log", ".tlog"):
            continue
        row: dict[str, Any] = {"log": path.name}
        t0 = time.process_time()
        try:
            log = read_flight_log(path)
        except PackPilotError as err:
            row["imports"] = f"refused: {str(err).split(': ', 1)[1]}"
            rows.append(row)
            continue
        row["imports"] = f"yes ({log.autopilot}; {len(log.batteries)} battery)"
        row["import_cpu_s"] = time.process_time() - t0
        for b in log.batteries:
            r = dict(row, battery=b.name)
            try:
                prof, _ = battery_profile(path, b, SERIES.get(path.name))
                r.update(_fit_row(prof, uav))
                r["configured"] = _batt_capacity(path)
            except PackPilotError as err:
                r["fit"] = f"refused: {str(err).split(': ', 1)[-1]}"
            rows.append(r)
    return rows


def _ulog(path: Path, prof: Any) -> None:
    """A synthetic flight as PX4 would log it (one cell: cell_count 1)."""
    from packpilot.io.flightlog.ulog import write_battery_ulog

    write_battery_ulog(path, prof.t_s, prof.voltage_v, prof.current_a, prof.charge_ah)


def _fleet_timing(n: int = 50) -> dict[str, Any]:
    """`fleet add` over n logs (PX4 ULog, 1 Hz, 15 min flights), fits included."""
    from packpilot.model.fit.synthetic import Truth, synthetic_log
    from packpilot.replay.fleet import add_logs

    with tempfile.TemporaryDirectory() as tmp:
        logs = []
        for k in range(n):
            path = Path(tmp) / f"flight{k:02d}.ulg"
            _ulog(path, synthetic_log(Truth(), 1.0, seconds=900, seed=k))
            logs.append(path)
        t0, c0 = time.perf_counter(), time.process_time()
        lines = add_logs(Path(tmp) / "fleet.sqlite", logs, "pack-1", None, None)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    return {"case": f"fleet add, {n} PX4 logs of 15 min at 1 Hz (fits included)",
            "fleet_add_wall_s": wall, "fleet_add_cpu_s": cpu, "records": len(lines)}  # fmt: skip


def _lofo_rows(name: str, prof: Any, uav: Any) -> list[dict[str, Any]]:
    """One log validated both ways: the 60 / 40 time split and, with >= 3 flights, leave one
    flight out (each flight's row; the end flights' marked not judged). PyBOP not rerun."""
    from packpilot.errors import InputError
    from packpilot.model.fit.profile import flights
    from packpilot.model.fit.validate import fit_and_validate

    n = len(flights(prof))
    rows = []
    for mode in ("time", "flights"):
        t0 = time.process_time()
        try:
            v = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v, mode=mode)
        except InputError as err:
            why = (f"{n} flight(s), needs 3" if "at least 3 flights" in str(err)
                   else str(err).split(": ", 2)[-1][:90])  # fmt: skip
            rows.append({"case": f"{name}: --validate {mode}", "flights": n,
                         "verdict": f"refused: {why}"})  # fmt: skip
            continue
        cpu = time.process_time() - t0
        for c in v.checks:
            held = c.test
            rows.append({
                "case": f"{name}: --validate {mode}"
                + ("" if mode == "time" else ", " + " ".join(c.name.rsplit(" ", 2)[-2:])
                   + (" (interior)" if c.interior else " (end: not judged)")),
                "flights": n,
                "held_out_s": f"{c.t_s[held.start]:.0f}..{c.t_s[held.stop - 1]:.0f}",
                "heldout_rmse_mV": 1000 * c.rmse_v, "heldout_max_mV": 1000 * c.max_err_v,
                "noise_floor_mV": 1000 * c.noise_floor_v, "line_rmse_mV": 1000 * c.baseline_rmse_v,
                "skill": c.skill, "verdict": v.verdict, "fit_cpu_s": cpu,
            })  # fmt: skip
    return rows


def _lofo() -> list[dict[str, Any]]:
    """Time split against leave one flight out: three-flight plant logs (1 Hz, 10 mV noise,
    1 % gain error; R0 and capacity errors), then every real log that fits."""
    from packpilot.errors import PackPilotError
    from packpilot.io.cycler import is_cycler_export
    from packpilot.io.flightlog import read_flight_log
    from packpilot.model.cell import load_parameter_set
    from packpilot.model.fit.synthetic import Truth, synthetic_log
    from packpilot.model.fit.validate import fit_and_validate
    from packpilot.replay.fitlogs import battery_profile, cycler_profile

    uav = load_parameter_set("uav_5ah")
    truth = Truth()
    rows = []
    for seed in (1, 2):
        prof = synthetic_log(truth, 1.0, noise_v=NOISE_V, gain=1.01, rest_s=30, seed=seed,
                             flights=3)  # fmt: skip
        v = fit_and_validate([prof], uav.ocv_soc, uav.ocv_table_v, mode="flights")
        p = v.result.params
        rows.append({
            "case": f"3-flight plant log, 1 Hz seed {seed}: --validate flights",
            "r0_err_pct": 100 * (p["r0_ohm"].value / truth.r0_ohm - 1),
            "capacity_err_pct": 100 * (p["capacity_ah"].value / truth.capacity_ah - 1),
            "heldout_rmse_over_noise": max(c.rmse_v for c in v.checks) / NOISE_V,
            "verdict": v.verdict,
        })  # fmt: skip
    for path in sorted(REAL.glob("*")):
        try:
            if is_cycler_export(path):
                prof, _ = cycler_profile(path, None)
            elif path.name in SERIES:
                log = read_flight_log(path)
                prof, _ = battery_profile(path, log.batteries[0], SERIES[path.name])
            else:
                continue
        except PackPilotError:
            continue
        rows += _lofo_rows(path.name, prof, uav)
    return rows


def run() -> list[dict[str, Any]]:
    return [*_synthetic(), _fleet_timing(), *_real(), *_lofo()]


if __name__ == "__main__":
    sys.path.insert(0, str(HERE.parent / "src"))
    from run_all import _table  # type: ignore[import-not-found]

    rows = run()
    synth = [r for r in rows if "case" in r]
    real = [r for r in rows if "log" in r]
    print(_table(synth))
    print()
    print(_table(real))
