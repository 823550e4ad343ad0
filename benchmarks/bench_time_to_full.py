"""Issue #28 item 2 (h28ttf): the observer's time to full against the plant over whole CC/CV
charges.

The shipped example ``soc_observer_sensors`` (one 6S 5 Ah battery, its sensor errors: cell
voltage noise 5 mV, current gain +1 % and offset +0.2 A, 0.1 s late) is charged by a CC/CV
charger (``--amps`` A, 4.2 V per cell, its 10 mOhm output slope) from each start SOC until the
plant's charge current has tapered to the end current the core uses (``full_current_a``,
default C/20): that time is the truth. Every 10 s the prediction (``soc_time_to_full_s``) and
the first version's rule (the missing charge at the recent average current to 100 %, computed
from the same state) are compared with the time the plant still took. Printed per start SOC:
the end, the worst and median error over windows (from 2 and from 10 minutes in, until 5
minutes before the end), and the worst error in seconds over the last 5 minutes.

    PYTHONPATH=src python benchmarks/bench_time_to_full.py [--soc0 0.1 0.3 0.6] [--amps 5]
        [--no-offset]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.config import ScenarioConfig, parse_config, read_toml
from packpilot.control.soc import observer as ob
from packpilot.sim.loop import ClosedLoop

ROOT = Path(__file__).resolve().parents[1]
DT_S = 0.5


def charge_config(soc0: float, amps: float, offset: bool) -> ScenarioConfig:
    data = read_toml(ROOT / "examples" / "soc_observer_sensors.toml")
    data["pack"]["batteries"][0]["soc0"] = soc0
    data["load"] = {"kind": "none"}
    data["charger"] = {"present": True, "rated_v": 60.0, "rated_a": 20.0, "voltage_v": 25.2,
                       "current_a": amps, "enable": True}  # fmt: skip
    if not offset:
        data["sensors"]["current"]["offset"] = 0.0
    data["sim"] = {"dt_s": DT_S, "duration_s": 20000.0}
    return parse_config(data, "time_to_full")


def run(soc0: float, amps: float, offset: bool) -> dict[str, Any]:
    loop = ClosedLoop.of(charge_config(soc0, amps, offset), 1)
    soc = next(x for x in loop.core.compiled if x.method.name == "soc")
    st, end_a = soc.st, float(soc.prm.full_current_a[0])
    rows: list[tuple[float, float, float]] = []
    k = 0
    while loop.plant.t_s < 200.0 or -float(loop.plant.pack.string_a[0, 0]) > end_a:
        loop.step(k, DT_S)
        k += 1
        if k % round(10.0 / DT_S) == 0:
            avg = float(st.load_avg_a[0, 0])
            old = (1.0 - st.shown_soc[0, 0]) * st.x[0, 0, ob.X_CAP] * 3600.0 / -avg
            rows.append((loop.plant.t_s, float(st.time_to_full_s[0, 0]),
                         float(old) if avg < 0.0 else math.nan))  # fmt: skip
        if k > 200000:
            raise SystemExit("the charge never ended")
    t_end = loop.plant.t_s
    arr = np.array(rows)
    left = t_end - arr[:, 0]
    out: dict[str, Any] = {"soc0": soc0, "t_end": t_end}
    for col, name in ((1, "new"), (2, "old")):
        rel = (arr[:, col] - left) / left
        for t0 in (120.0, 600.0):
            sel = (arr[:, 0] >= t0) & (left >= 300.0)
            out[f"{name}_max_{t0:.0f}"] = float(np.max(np.abs(rel[sel])) * 100)
            out[f"{name}_med_{t0:.0f}"] = float(np.median(np.abs(rel[sel])) * 100)
        tail = left < 300.0
        out[f"{name}_tail_s"] = float(np.max(np.abs(arr[tail, col] - left[tail])))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--soc0", type=float, nargs="*", default=[0.1, 0.3, 0.6])
    ap.add_argument("--amps", type=float, default=5.0)
    ap.add_argument("--no-offset", action="store_true", help="current offset 0 (gain kept)")
    args = ap.parse_args(argv)
    print(f"charge {args.amps:g} A CC / 25.2 V CV, end at C/20, current offset "
          f"{'0' if args.no_offset else '+0.2 A'}; |error| % of the time left (max / median)"
          " over [t0, end - 300 s], and the worst s over the last 300 s")  # fmt: skip
    print("soc0  end s | new: from 120 s  from 600 s  last 300 s | old: from 120 s  "
          "from 600 s  last 300 s")
    for soc0 in args.soc0:
        r = run(soc0, args.amps, not args.no_offset)
        cells = []
        for name in ("new", "old"):
            cells.append(f"{r[f'{name}_max_120']:5.1f}/{r[f'{name}_med_120']:4.1f}  "
                         f"{r[f'{name}_max_600']:5.1f}/{r[f'{name}_med_600']:4.1f}  "
                         f"{r[f'{name}_tail_s']:6.0f} s")  # fmt: skip
        print(f"{soc0:4.2f} {r['t_end']:6.0f} | " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
