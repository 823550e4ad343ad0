"""Issue #28: the core's own SOC observer on a REAL flight log (no SOC truth exists).

The log: ``examples/logs/real/arducopter_dronekit_flight_battery.tlog`` (3S 2650 mAh LiPo,
~3 Hz SYS_STATUS: pack voltage and current only; three flights with rests between; MANIFEST.md).
A log-driven plant port (:class:`LogPort`, the loop's ``PlantPort``: ``measure`` / ``apply``)
stands where the simulator stands: every sample, the core's measurement arena is filled the way
:class:`~packpilot.sim.plant_io.SimulatedPlant` fills it (its own ``sense`` kernel lays out
switches and presence), then the log's values overwrite the electrical ones: battery current,
pack voltage, each cell (and group) at V / 3 (the log has no cells), and an ASSUMED 15 C
temperature (the log has none). ``apply`` ignores the commands: the log is open loop. The core
(:func:`packpilot.sim.loop.control`, supervised, ``[soc]`` with its defaults) steps once per log
sample with dt = the sample's own interval (median 0.345 s; no resampling needed).

Cell set: ``uav_5ah`` at ``capacity_ah = 2.65`` (the configured BATT_CAPACITY), 3S1P.

Figures (all per cell):
1. voltage prediction error under load (|I| > 3.4 A, the fit's flight threshold): the
   observer's one-step-ahead prediction (its state before the sample, propagated over dt by
   its own ``predict`` kernel: what its innovation is made of) and its a-posteriori fit, vs the
   log's noise floor (``noise_floor``) and a naive coulomb counter from the first sample's OCV
   with the cell set's R0 (no RC).
2. SOC at each rest after a flight: observer vs an OCV reading of the rested voltage (the last
   10 samples of the rest), vs the naive counter, vs the autopilot's ``remaining``.
3. the observer's R0 / capacity at the end (compare with ``packpilot fit`` on the same log).

    PYTHONPATH=src NUMBA_DISABLE_JIT=1 python benchmarks/bench_soc_real.py
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from packpilot.arena import Arenas, unpack
from packpilot.config import ScenarioConfig, parse_config
from packpilot.contract.arrays import MeasArrays
from packpilot.control.soc import observer as ob
from packpilot.io.flightlog import read_flight_log
from packpilot.model.fit.profile import noise_floor
from packpilot.replay.fitlogs import profiles_from_logs
from packpilot.sim.loop import ClosedLoop, control
from packpilot.sim.plant_io import SimulatedPlant

LOG = (
    Path(__file__).resolve().parents[1]
    / "examples/logs/real/arducopter_dronekit_flight_battery.tlog"
)
SERIES = 3
CAPACITY_AH = 2.65
TEMP_C = 15.0
"""ASSUMED cell temperature: the log has none (a July morning in Canberra, a small pack)."""
LOAD_A = 3.4
"""Under load: above the fit's rest threshold (10 % of the log's high current, 33.8 A)."""
REST_A = 3.4
REST_MIN_S = 30.0
REST_TAIL = 10
"""Samples at the end of a rest read through the OCV curve (~3.5 s)."""


class LogPort:
    """The loop's plant port fed by a log: one sample per :meth:`measure`."""

    def __init__(self, plant: SimulatedPlant, t_s: Any, pack_v: Any, cur_a: Any) -> None:
        self.plant, self.t_s, self.pack_v, self.cur_a = plant, t_s, pack_v, cur_a
        self.k = 0

    def measure(self, arenas: Arenas, m_row: int) -> None:
        self.plant.measure(arenas, m_row)  # switches, presence, layout as the simulator does
        m = unpack(MeasArrays, *arenas, m_row)
        v, i = float(self.pack_v[self.k]), float(self.cur_a[self.k])
        b = m.bat
        m.t_s[0] = float(self.t_s[self.k])
        b.voltage_v[0, 0] = v
        b.current_a[0, 0] = i
        b.temp_c[0, 0] = b.min_temp_c[0, 0] = TEMP_C
        b.min_cell_v[0, 0] = b.max_cell_v[0, 0] = v / SERIES
        b.group_v[0, 0, :SERIES] = v / SERIES
        b.soc[0, 0] = math.nan  # the battery reports no SOC of its own
        b.remaining_capacity_ah[0, 0] = math.nan
        m.load_current_a[0] = i
        m.bus_v[0] = v

    def apply(self, arenas: Arenas, cmd_row: int) -> None:
        """Open loop: the log's current was drawn whatever the BMS says."""


@dataclass(frozen=True)
class Setup:
    """What the BMS is configured with (the observer's model and tuning)."""

    label: str
    cell: str = "uav_5ah"
    capacity_ah: float | None = CAPACITY_AH
    """None: the cell set's own."""
    resistance_ohm: float | None = None
    """The battery's DC resistance at ``TEMP_C`` (None: the cell set's own R0)."""
    soc: tuple[tuple[str, float], ...] = ()
    """``[soc]`` settings (none: the defaults)."""


def scenario(setup: Setup) -> ScenarioConfig:
    """One 3S1P battery of ``setup``'s cell set, ``[soc]`` on."""
    bat: dict[str, Any] = {"name": "A", "series_groups": SERIES, "cells_per_group": 1, "soc0": 0.9}
    if setup.capacity_ah is not None:
        bat["capacity_ah"] = setup.capacity_ah
    resistance_ohm = setup.resistance_ohm
    if resistance_ohm is not None:
        bat |= {"resistance_ohm": resistance_ohm, "resistance_temp_c": TEMP_C}
    data: dict[str, Any] = {
        "pack": {
            "cell": setup.cell,
            "ambient_c": TEMP_C,
            "batteries": [bat],
        },
        "load": {"kind": "current", "value": 0.0},
        "soc": dict(setup.soc),
        "sim": {"dt_s": 0.345, "duration_s": 1100.0, "progress": False},
    }
    return parse_config(data, "soc_real_tlog")


def _a_priori_v(soc_part: Any, x0: Any, cov0: Any, cur: float, dt: float) -> float:
    """The observer's predicted cell voltage for this sample from its state before it: its own
    ``predict`` kernel over ``dt`` then the measurement model ``correct`` uses."""
    prm, st = soc_part.prm, soc_part.st
    x, cov = x0.copy(), cov0.copy()
    fm, wk = st.fm.copy(), st.wk.copy()
    soc = float(x[0, 0, ob.X_SOC])
    r1 = ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, TEMP_C, soc)
    tau = ob.table2(prm.tau_tab, prm.ax_t, prm.ax_s, TEMP_C, soc)
    ob.predict(x, cov, fm, wk, 0, 0, cur, dt, r1, tau, prm.walk)
    r0 = ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, TEMP_C, float(x[0, 0, ob.X_SOC]))
    ocv, _, _ = ob.ocv_over_spread(
        prm.ocv_soc,
        prm.ocv_v,
        prm.du_t,
        prm.du_tab,
        prm.t_ref_c,
        x[0, 0, ob.X_SOC],
        cov[0, 0, ob.X_SOC, ob.X_SOC],
        TEMP_C,
    )
    ic = cur - x[0, 0, ob.X_OFFSET]
    return float(ocv - x[0, 0, ob.X_RSCALE] * r0 * ic - x[0, 0, ob.X_V1])


def run_core(setup: Setup) -> dict[str, Any]:
    log = read_flight_log(LOG)
    bat = log.batteries[0]
    t, v, i = bat.t_s, bat.voltage_v, bat.current_a
    assert i is not None and bat.soc is not None
    prof = profiles_from_logs([LOG], SERIES, None)[0][0]
    cfg = scenario(setup)
    loop = ClosedLoop.of(cfg, 1)
    core = loop.core
    port = LogPort(loop.plant, t, v, i)
    soc_part = next(x for x in core.compiled if x.method.name == "soc")
    slots = {ch.name: s for s, ch, _ in core.status_channels()}
    names = (
        "soc_est",
        "soc_fallback",
        "soc_emf_v",
        "soc_r0_ohm",
        "soc_v_rc_v",
        "soc_capacity_ah",
        "soc_current_offset_a",
        "soc_nis",
        "soc_observer_ok",
    )
    n = len(t)
    out = {k: np.full(n, np.nan) for k in names}
    prior = np.full(n, np.nan)
    x_soc = np.full(n, np.nan)
    kinds: list[tuple[float, str]] = []
    for k in range(n):
        dt = float(t[k] - t[k - 1]) if k else 0.0
        x0, cov0 = soc_part.st.x.copy(), soc_part.st.cov.copy()
        ok_before = k > 0 and math.isfinite(float(x0[0, 0, ob.X_SOC]))
        port.k = k
        control(core, port, loop.links, float(t[k]), dt)
        if core.ev.n[0]:
            kinds += [(float(t[k]), kind) for kind in core.event_kinds()[0]]
        st = core.status[0]
        for name in names:
            out[name][k] = st[0, slots[name]]
        x_soc[k] = soc_part.st.x[0, 0, ob.X_SOC]
        if ok_before and dt > 0:
            prior[k] = _a_priori_v(soc_part, x0, cov0, float(i[k]), dt)
    return {
        "t": t,
        "v": v,
        "i": i,
        "remaining": bat.soc,
        "prof": prof,
        "out": out,
        "prior": prior,
        "x_soc": x_soc,
        "cap_ah": loop.plant.infos[0].capacity_ah[0],
        "prm": soc_part.prm,
        "kinds": kinds,
    }


def rests(t: Any, i: Any) -> list[tuple[int, int]]:
    """(lo, hi) index ranges where |I| < REST_A for >= REST_MIN_S, after the first flight."""
    quiet = np.abs(i) < REST_A
    out: list[tuple[int, int]] = []
    k = 0
    n = len(t)
    while k < n:
        if quiet[k]:
            j = k
            while j < n and quiet[j]:
                j += 1
            if t[j - 1] - t[k] >= REST_MIN_S:
                out.append((k, j))
            k = j
        else:
            k += 1
    return out


def report(setup: Setup) -> dict[str, float]:
    """Run the core over the log configured as ``setup`` and print the figures; returns the
    headline numbers."""
    from packpilot.control.soc.rules import ocv_t, soc_from_ocv_t

    r = run_core(setup)
    label = setup.label
    t, v, i, out, prm = r["t"], r["v"], r["i"], r["out"], r["prm"]
    vc = v / SERIES
    r_nom = float(prm.r_nom[0])
    # naive: coulomb counter from the first samples' OCV, the configured R0, no RC
    soc0 = soc_from_ocv_t(prm, float(np.median(vc[:10])), TEMP_C)
    drawn = np.concatenate([[0.0], np.cumsum(0.5 * (i[1:] + i[:-1]) * np.diff(t))]) / 3600.0
    naive_soc = soc0 - drawn / r["cap_ah"]
    naive_v = np.array([ocv_t(prm, s, TEMP_C)[0] for s in naive_soc]) - i * r_nom * np.array(
        [ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, TEMP_C, s) for s in naive_soc]
    )
    post_v = (
        out["soc_emf_v"] - out["soc_r0_ohm"] * (i - out["soc_current_offset_a"]) - out["soc_v_rc_v"]
    ) / SERIES
    load = np.abs(i) > LOAD_A
    ok = load & np.isfinite(r["prior"])

    def rms(e: Any) -> float:
        return float(np.sqrt(np.mean(e * e))) * 1e3

    floor = noise_floor(r["prof"]) * 1e3
    res: dict[str, float] = {}
    r0_cfg = r_nom * ob.table2(prm.r0_tab, prm.ax_t, prm.ax_s, TEMP_C, 0.9)
    print(
        f"\n=== {label}: configured R0 {1e3 * r0_cfg:.1f} mOhm/cell at {TEMP_C:g} C, SOC 0.9, "
        f"capacity {r['cap_ah']:.3f} Ah, [soc] {dict(setup.soc) or 'defaults'} ==="
    )
    print(
        f"log {LOG.name}: {len(t)} samples, {t[-1] - t[0]:.0f} s, median dt "
        f"{np.median(np.diff(t)):.3f} s; under load (|I| > {LOAD_A} A): {int(load.sum())}"
    )
    res["prior"] = rms(r["prior"][ok] - vc[ok])
    res["post"] = rms(post_v[load] - vc[load])
    res["naive"] = rms(naive_v[load] - vc[load])
    print("1. cell-voltage error under load (RMS, mV per cell)")
    print(f"  noise floor (noise_floor)                     {floor:6.1f}")
    print(
        f"  observer one-step-ahead (a priori)            {res['prior']:6.1f}"
        f"  (mean {1e3 * np.mean(r['prior'][ok] - vc[ok]):+.1f})"
    )
    print(f"  observer after its correction (a posteriori)  {res['post']:6.1f}")
    print(
        f"  naive counter + configured R0, no RC          {res['naive']:6.1f}"
        f"  (mean {1e3 * np.mean(naive_v[load] - vc[load]):+.1f})"
    )
    print(
        "2. SOC at the end of each rest >= 30 s after a flight (OCV of the last "
        f"{REST_TAIL} samples)"
    )
    print(
        "  rest (s)        len  OCV(rested V)  shown (trusted)  observer state  "
        "counter(naive)  fallback  autopilot"
    )
    for lo, hi in rests(t, i):
        if t[lo] < 400:  # the pre-flight ground rest: no flight before it
            continue
        tail = slice(max(lo, hi - REST_TAIL), hi)
        s_ocv = soc_from_ocv_t(prm, float(np.mean(vc[tail])), TEMP_C)
        k = hi - 1
        trusted = "yes" if out["soc_observer_ok"][k] > 0.5 else "no"
        print(
            f"  {t[lo]:6.0f}-{t[hi - 1]:6.0f} {t[hi - 1] - t[lo]:5.0f}  {s_ocv:13.3f}  "
            f"{out['soc_est'][k]:8.3f} ({trusted:>3})  {r['x_soc'][k]:14.3f}  "
            f"{naive_soc[k]:14.3f}  {out['soc_fallback'][k]:8.3f}  "
            f"{r['remaining'][k]:9.2f}"
        )
    k = len(t) - 1
    tail = slice(k - REST_TAIL + 1, k + 1)
    landed_s = t[k] - t[np.nonzero(load)[0][-1]]
    print(
        f"  log end {t[k]:.0f} s (|I| {i[k]:.2f} A, landed {landed_s:.0f} s before): OCV "
        f"{soc_from_ocv_t(prm, float(np.mean(vc[tail])), TEMP_C):.3f}, observer "
        f"{out['soc_est'][k]:.3f} (state {r['x_soc'][k]:.3f}, trusted "
        f"{out['soc_observer_ok'][k] > 0.5}), naive {naive_soc[k]:.3f}, fallback "
        f"{out['soc_fallback'][k]:.3f}, autopilot {r['remaining'][k]:.2f}"
    )
    _params_and_trust(r, k)
    first_soc = out["soc_est"][np.isfinite(out["soc_est"])][0]
    print(f"  SOC0: naive {soc0:.3f}, observer {first_soc:.3f}")
    res["floor"] = floor
    return res


def _params_and_trust(r: dict[str, Any], k: int) -> None:
    """Figures 3 and 4: the observer's R0 / capacity / offset, and its window test."""
    t, out, prm = r["t"], r["out"], r["prm"]
    print("3. observer's parameters (per cell)")
    first = int(np.argmax(np.isfinite(out["soc_r0_ohm"])))
    for lab, kk in (("start", first), ("end", k)):
        print(
            f"  {lab} ({t[kk]:.0f} s): R0 {1e3 * out['soc_r0_ohm'][kk] / SERIES:.1f} mOhm, "
            f"capacity {out['soc_capacity_ah'][kk]:.3f} Ah, current offset "
            f"{out['soc_current_offset_a'][kk]:+.3f} A"
        )
    mid = [int(np.argmin(np.abs(t - x))) for x in (466.0, 731.0, 854.0)]
    print(
        "  at take-off / rests (R0 mOhm, capacity Ah): "
        + ", ".join(
            f"{t[kk]:.0f} s {1e3 * out['soc_r0_ohm'][kk] / SERIES:.1f} "
            f"{out['soc_capacity_ah'][kk]:.2f}"
            for kk in mid
        )
    )
    okv = out["soc_observer_ok"]
    fin = np.isfinite(okv)
    ev = [(round(tt), kind) for tt, kind in r["kinds"] if kind.startswith("Soc")]
    print(
        f"4. trust: soc_observer_ok true in {int(np.sum(okv[fin] > 0.5))}/{int(fin.sum())} "
        f"samples; NIS average max {np.nanmax(out['soc_nis']):.2f} (limit {prm.nis_limit:g}), "
        f"median {np.nanmedian(out['soc_nis']):.2f}; SOC events {ev}"
    )


FIT_R0_OHM = 0.0456
"""``packpilot fit`` (--validate time) on this log, per cell (45.6 mOhm at the start)."""


def setups(cell_json: str | None, r0_ohm: float = FIT_R0_OHM) -> list[Setup]:
    out = [
        Setup("A: uav_5ah as shipped at 2.65 Ah (R0 of its 5 Ah cell)"),
        Setup(
            "B: A + battery resistance_ohm = 3 x the fit's R0 (in-sample)",
            resistance_ohm=SERIES * r0_ohm,
        ),
        Setup(
            "D: B + ekf_voltage_sigma_v = 2 x the noise floor (sensitivity)",
            resistance_ohm=SERIES * r0_ohm,
            soc=(("ekf_voltage_sigma_v", 0.0364),),
        ),
    ]
    if cell_json is not None:
        out.append(
            Setup(
                f"C: the cell set packpilot fit wrote for this log ({cell_json}; in-sample)",
                cell=cell_json,
                capacity_ah=None,
            )
        )
    return out


def run() -> list[dict[str, Any]]:
    """``make bench``: fit the log with ``packpilot fit`` (the user's command, default time
    split) into a temporary cell set, then setups A, B and C; one row of figures each."""
    import subprocess
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        cell = str(Path(tmp) / "tlog_set.json")
        subprocess.run(
            [sys.executable, "-m", "packpilot.cli", "fit", str(LOG), "--cells", str(SERIES),
             "--out", cell],
            check=True, capture_output=True,
        )  # fmt: skip
        rows: list[dict[str, Any]] = []
        for setup in setups(cell)[:2] + setups(cell)[3:]:
            res = report(setup)
            rows.append({"setup": setup.label.split(":")[0], **{
                f"{k}_mV": round(v, 1) for k, v in res.items()
            }})  # fmt: skip
        return rows


def main() -> int:
    """``--cell PATH``: also run the set ``packpilot fit LOG --cells 3 --out PATH`` wrote;
    ``--r0-mohm X``: the per-cell R0 setups B and D are told (default the fit's 45.6)."""
    args = sys.argv[1:]
    cell = args[args.index("--cell") + 1] if "--cell" in args else None
    r0 = float(args[args.index("--r0-mohm") + 1]) / 1e3 if "--r0-mohm" in args else FIT_R0_OHM
    for setup in setups(cell, r0):
        report(setup)
    return 0


if __name__ == "__main__":
    sys.exit(main())
