"""Make the sample flight logs shipped in examples/logs/ from PackPilot simulations.

    PYTHONPATH=src python scripts/make_sample_logs.py [--out examples/logs]

Two flights, each flown WITHOUT PackPilot's controllers (the logs a user would bring: what the
aircraft did on its own), written the way the flight controllers log battery data:

* one battery: ``protection_cold_heavy`` (6S 5 Ah at -10 degC, 30 A with 60 A bursts) with
  its six cells as six series groups so each cell's voltage is known, flown to 600 s with no
  protection. ``px4_one_battery.ulg``: a smart battery on PX4 (``battery_status`` with
  temperature and real ``voltage_cell_v``); ``ardupilot_one_battery.bin``: ArduPilot with an
  analog monitor plus per-cell ``BCL`` (``BAT.Temp`` 0: no temperature sensor).
  ``flight_log.csv`` is ``packpilot import px4_one_battery.ulg`` (the README's example).
* two batteries: ``uav_dual_parallel`` (two 6S packs 2 V apart in parallel, no sequencing:
  the ~50 A cross-charge at connection), 600 s. ``px4_two_batteries.ulg``: two analog
  monitors (temperature NaN, ``voltage_cell_v`` filled with V / 6 as PX4 does, instances 0
  and 1); ``ardupilot_two_batteries.bin`` and ``.log`` (text): ``BAT`` instances 0 and 1, no
  temperature sensor, no cell voltages.

Logged at 1 Hz to keep the files small; the values
are the simulation's plant truth at those instants (float32 in the logs, as on the aircraft).
The ULog and DataFlash bytes come from the minimal writers in ``packpilot.io.flightlog``;
tests read every file with pyulog / pymavlink.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.record import BATTERY_CHANNELS, Result
from packpilot.io.flightlog import read_flight_log
from packpilot.io.flightlog.dataflash import write_bin, write_text
from packpilot.io.flightlog.ulog import write_ulog
from packpilot.sim.runner import Runner

ROOT = Path(__file__).resolve().parents[1]
CH = {c: k for k, c in enumerate(BATTERY_CHANNELS)}
N_CELL_FIELD = 14


def _without_controllers(cfg: ScenarioConfig, **sim: Any) -> ScenarioConfig:
    data = cfg.model_dump()
    data["controller"] = []
    data["sim"] = {**data["sim"], **sim}
    return ScenarioConfig.model_validate(data)


def one_battery_run() -> Result:
    cfg = load_config(ROOT / "examples" / "protection_cold_heavy.toml")
    data = cfg.model_dump()
    bat = data["pack"]["batteries"][0]
    bat["series_groups"], bat["cells_per_group"] = 6, 1
    cfg = ScenarioConfig.model_validate(data)
    return Runner(_without_controllers(cfg, duration_s=600.0), progress=False).run()


def two_battery_run() -> Result:
    cfg = load_config(ROOT / "examples" / "uav_dual_parallel.toml")
    return Runner(_without_controllers(cfg, duration_s=600.0), progress=False).run()


def _rows(result: Result, every_s: float) -> Iterator[int]:
    t = result.trace.t_s
    step = max(1, round(every_s / float(t[1] - t[0])))
    yield from range(0, len(t), step)


def _cells(result: Result, k: int, b: int) -> list[float]:
    g = result.trace.group_v[k, b]
    return [float(x) for x in g if math.isfinite(x)]


def _px4(result: Result, every_s: float, smart: bool) -> list[list[dict[str, Any]]]:
    tr = result.trace
    out: list[list[dict[str, Any]]] = []
    for b in range(len(result.battery_names)):
        samples = []
        used_mah = 0.0
        prev_t = None
        for k in _rows(result, every_s):
            row = tr.battery[k, b]
            t, v, i = float(tr.t_s[k]), float(row[CH["voltage_v"]]), float(row[CH["current_a"]])
            used_mah += 0.0 if prev_t is None else i * (t - prev_t) / 3.6
            prev_t = t
            cells = _cells(result, k, b) if smart else [v / 6.0] * 6
            samples.append(
                {
                    "timestamp": round(t * 1e6),
                    "voltage_v": v,
                    "current_a": i,
                    "current_average_a": i,
                    "discharged_mah": used_mah,
                    "remaining": float(np.clip(row[CH["soc"]], 0.0, 1.0)),
                    "temperature": float(row[CH["temp_c"]]) if smart else math.nan,
                    "voltage_cell_v": cells + [0.0] * (N_CELL_FIELD - len(cells)),
                    "cell_count": len(cells),
                    "connected": True,
                    "id": b,
                    "warning": 0,
                }
            )
        out.append(samples)
    return out


def _ardupilot(result: Result, every_s: float, cells: bool) -> list[tuple[str, list[float]]]:
    tr = result.trace
    msgs: list[tuple[str, list[float]]] = []
    used = [0.0] * len(result.battery_names)
    prev_t: float | None = None
    for k in _rows(result, every_s):
        t = float(tr.t_s[k])
        for b in range(len(result.battery_names)):
            row = tr.battery[k, b]
            v, i = float(row[CH["voltage_v"]]), float(row[CH["current_a"]])
            used[b] += 0.0 if prev_t is None else i * (t - prev_t) / 3600.0
            t_us = float(round(t * 1e6))
            rem = float(np.clip(row[CH["soc"]], 0.0, 1.0)) * 100.0
            # TimeUS,Inst,Volt,VoltR,Curr,CurrTot(Ah),EnrgTot,Temp(0: no sensor),Res,RemPct,H
            msgs.append(("BAT", [t_us, b, v, v, i, used[b], 0.0, 0.0, 0.0, round(rem), 1]))
            if cells:
                mv = [round(c * 1000.0) for c in _cells(result, k, b)]
                msgs.append(("BCL", [t_us, b, v, *mv, *[65535] * (12 - len(mv))]))
        prev_t = t
    return msgs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "examples" / "logs")
    out = ap.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    one = one_battery_run()
    write_ulog(out / "px4_one_battery.ulg", _px4(one, 1.0, smart=True), start_us=0)
    write_bin(out / "ardupilot_one_battery.bin", _ardupilot(one, 1.0, cells=True))
    two = two_battery_run()
    write_ulog(out / "px4_two_batteries.ulg", _px4(two, 1.0, smart=False), start_us=0)
    write_bin(out / "ardupilot_two_batteries.bin", _ardupilot(two, 1.0, cells=False))
    write_text(out / "ardupilot_two_batteries.log", _ardupilot(two, 1.0, cells=False))
    table = read_flight_log(out / "px4_one_battery.ulg").table()
    table.write_csv(out / "flight_log.csv")
    for p in sorted(out.iterdir()):
        print(f"{p.name}: {p.stat().st_size / 1000:.0f} kB")


if __name__ == "__main__":
    main()
