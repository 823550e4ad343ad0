"""The pack as one battery: what the inverter and the aircraft are told, once a second.

Everything here is read from the core after its step — the measurements it saw, the limits
layer's pack limits (which already follow derating, trips and the batteries actually
connected: ``n_conducting × weakest``), the limits ladders' tiers, the supervisor's mode and the
protection's platform interface. Nothing is decided here: a trip in the core is a 0 A limit
here because the limits layer says 0 A, and a supervisor in ``fault`` or ``shutdown`` zeroes
both limits because that mode opens every path.

The state of power (``control/power``, ``docs/power.md``) is the core's prediction from the
same state: the Pylontech CCL/DCL are the smaller of the limits layer's and the 30 s state of
power (an inverter holds them continuously), and the ``StateOfPower`` frame (0x231) and
DroneCAN ``BatteryPeriodic`` carry the 2 / 10 / 30 s figures. The prediction is
``sim/power_view.py:state_of_power_now``, the one the dashboard and the report show.

Interpreted (a first run on a machine, ``coldstart.py``) the state of power costs about half
a second of CPU (thousands of sub-steps of its bisections as plain Python) against ~1 µs
compiled; computed inline once a second it stalled the BMS period by up to 0.75 s every
second (``step_p99_ms`` 747, 5 overruns in 66 periods, 2026-11-28). There it runs on one
worker thread from a snapshot of the inputs taken at the publication (:class:`PowerWorker`):
each publication carries the figure of the previous snapshot (about 1 s old, or NaN =
unknown before the first), and the BMS period keeps its time (the worker yields the GIL every
5 ms). Compiled it stays inline, as before: same figures, same frames.

The SOC every frame carries (Pylontech 0x355, DroneCAN ``BatteryInfo`` of the pack and of each
battery, the ``StateOfCharge`` frame 0x232) is the SOC the core uses
(``contract/soc_source.py``): the observer's estimate where it is trusted, its fallback (the
coulomb counter) otherwise, the battery's own report only without a ``[soc]`` estimator; 0x232
says which, and DroneCAN's ``state_of_charge_pct_stdev`` carries the observer's deviation
(a best guess elsewhere, :data:`FALLBACK_STDEV_PCT`). Before, every frame carried the
batteries' own reported SOC, which the core does not act on.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor

import can
import numba
import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.contract import soc_source
from packpilot.contract.events import value as field_value
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core
from packpilot.control.power import PowerInputs, PowerOut, PowerParams, state_of_power
from packpilot.control.supervisor.rules import MODES
from packpilot.io.can import dronecan_io as dc
from packpilot.io.can import pylon
from packpilot.io.can.battery import (
    ProtectionReport,
    SocReport,
    encode_power,
    encode_protection,
    encode_soc,
)
from packpilot.sim.power import inputs_from_core, params_of
from packpilot.sim.power_view import TRIPPED_MODES, CoreView, sop_inputs

HORIZON_CCL = 2
"""Index of the 30 s horizon in ``control.power.HORIZONS_S``: what CCL/DCL carry."""

PERIOD_S = 1.0

PYLON_BITS: dict[str, int] = {
    "cell_v_max": pylon.OVER_VOLTAGE,
    "cell_v_min": pylon.UNDER_VOLTAGE,
    "temp_max_c": pylon.OVER_TEMP,
    "temp_min_c": pylon.UNDER_TEMP,
    "dsg_c_rate": pylon.DISCHARGE_OVER_CURRENT,
    "chg_c_rate": pylon.CHARGE_OVER_CURRENT,
}
"""Limits quantity → the 0x359 bit its ladder raises (warn / derate: warning; trip:
protection)."""


class Channels:
    """Raw status numbers of a core by channel name (slot lookups done once)."""

    def __init__(self, core: Core) -> None:
        self.core = core
        self.slot = {ch.name: slot for slot, ch, _ in core.status_channels()}
        self.labels = {ch.name: labels for _, ch, labels in core.status_channels()}
        self.kind = {ch.name: ch.kind for _, ch, _ in core.status_channels()}

    def value(self, name: str, i: int = 0) -> float:
        s = self.slot.get(name)
        return math.nan if s is None else float(self.core.status[0, i, s])

    def label(self, name: str, i: int = 0) -> str | None:
        """The label of a label channel (``l:<set>``), None if absent or unset."""
        s = self.slot.get(name)
        if s is None:
            return None
        value = field_value(self.value(name, i), self.kind[name], self.labels[name])
        return value if isinstance(value, str) else None


def mode(ch: Channels) -> str | None:
    x = ch.value("mode")
    return MODES[int(x)] if math.isfinite(x) and 0 <= int(x) < len(MODES) else None


def _voltage_limits(cfg: ScenarioConfig, groups: Sequence[int]) -> tuple[float, float]:
    """(charge voltage limit, discharge voltage limit) of the pack: the charging method's
    saturation voltage, else the limits table's cell thresholds × series groups."""
    n = max(groups, default=0)
    cvl = dvl = math.nan
    if cfg.limits is not None:
        rows = cfg.limits.rows
        hi = [r.threshold for r in rows if r.quantity == "cell_v_max"]
        lo = [r.threshold for r in rows if r.quantity == "cell_v_min"]
        cvl = min(hi) * n if hi else math.nan
        dvl = max(lo) * n if lo else math.nan
    ch = cfg.charging
    if ch is not None:
        cvl = ch.v_sat_v * (n if ch.voltage_basis == "cell" else 1)
    return cvl, dvl


def pack_limits(prm: PowerParams, inp: PowerInputs) -> PowerOut:
    """The state of power the runtime publishes: the pack's limits only (what the frames
    carry); each battery's own are left NaN, 80 % of the searches at 4 batteries. One place,
    so the worker, the inline call and the warm-up compile and run the same call."""
    return state_of_power(prm, inp, alone=False)


class PowerWorker:
    """The state of power off the BMS period's thread (interpreted runs; see the module's
    docstring): one computation at a time, from the snapshot given at its submission;
    :meth:`latest` hands back the last finished result and starts the next one."""

    def __init__(self) -> None:
        self._pool = ThreadPoolExecutor(1, thread_name_prefix="packpilot-state-of-power")
        self._running: Future[PowerOut] | None = None
        self.result: PowerOut | None = None
        self.computed = 0
        """Computations finished (their results published or superseded)."""

    def latest(self, prm: PowerParams, inp: PowerInputs | None) -> PowerOut | None:
        """The last finished result (None before the first); submits ``inp`` unless a
        computation is still running (then this snapshot is skipped: the next one is newer)."""
        if self._running is not None and self._running.done():
            self.result = self._running.result()
            self._running = None
            self.computed += 1
        if inp is None:
            self.result = None  # nothing to predict now: say unknown, not an old figure
        elif self._running is None:
            self._running = self._pool.submit(pack_limits, prm, inp)
        return self.result

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


class Publisher:
    """Pylontech frames, the protection state and DroneCAN BatteryInfo, every second."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        core: Core,
        info: PackInfo,
        bus: can.BusABC,
        node_id: int = 100,
        name: str = pylon.DEFAULT_NAME,
    ) -> None:
        self.cfg, self.core, self.info, self.bus = cfg, core, info, bus
        self.ch = Channels(core)
        self.node_id = node_id
        self.name = name
        self.next_s: float | None = None
        self.transfer_id = 0
        self.sent = 0
        self.send_errors = 0
        self.cvl_v, self.dvl_v = _voltage_limits(cfg, info.groups_per_battery)
        self.quantity = {r.limit: r.quantity for r in cfg.limits.rows} if cfg.limits else {}
        self.last: pylon.PackAsBattery | None = None
        self.power_prm = params_of(cfg)
        self.sop: PowerOut | None = None
        """The state of power of the last publication."""
        self.worker = PowerWorker() if numba.config.DISABLE_JIT else None  # type: ignore[attr-defined]
        """Interpreted runs compute the state of power on a worker thread (module docstring)."""

    def due(self, t: float) -> bool:
        return self.next_s is None or t >= self.next_s - 1e-9

    def maybe_publish(self, t: float) -> list[can.Message]:
        """Send every frame when a second has passed; returns what went out."""
        if not self.due(t):
            return []
        self.next_s = (t if self.next_s is None else max(self.next_s, t - PERIOD_S)) + PERIOD_S
        out = self.frames(t)
        for msg in out:
            try:
                self.bus.send(msg)
                self.sent += 1
            except can.CanError:
                self.send_errors += 1
        return out

    def frames(self, t: float) -> list[can.Message]:
        out: list[can.Message] = []
        if self.worker is None:
            self.sop = self.state_of_power()
        else:
            self.sop = self.worker.latest(self.power_prm, self.power_inputs())
        if self.cfg.limits is not None:
            self.last = self.pack_as_battery()
            out += pylon.encode_all(self.last, t)
        out.append(encode_protection(self.protection(), t))
        out.append(self.power_frame(t))
        out.append(self.soc_frame(t))
        for info in self.battery_infos():
            out += dc.encode(info, self.node_id, self.transfer_id, t=t)
        out += dc.encode_periodic(self.periodic(), self.node_id, self.transfer_id, t=t)
        self.transfer_id = (self.transfer_id + 1) & 0x1F
        return out

    # ------------------------------------------------------------------ the one battery
    def _present(self) -> np.ndarray:
        m = self.core.m
        return np.asarray(m.bat.reported[0] & m.bat.present[0])

    def pack_as_battery(self) -> pylon.PackAsBattery:
        m, ch = self.core.m, self.ch
        here = self._present()
        tripped = mode(ch) in TRIPPED_MODES
        ccl = 0.0 if tripped else _finite0(ch.value("pack_limit_chg_a"))
        dcl = 0.0 if tripped else _finite0(ch.value("pack_limit_dsg_a"))
        if self.sop is not None:
            ccl = min(ccl, float(self.sop.pack_chg_a[0, HORIZON_CCL]))
            dcl = min(dcl, float(self.sop.pack_dsg_a[0, HORIZON_CCL]))
        soc = 100.0 * self.pack_soc()[0]
        full = np.where(here & np.isfinite(m.bat.full_capacity_ah[0]), m.bat.full_capacity_ah[0],
                        0.0)  # fmt: skip
        nominal = np.where(here, np.asarray(self.info.capacity_ah), 0.0)
        soh = 100.0 * _ratio(float(np.nansum(full)), float(np.nansum(nominal)))
        prot, warn = self._alarms(tripped)
        return pylon.PackAsBattery(
            charge_voltage_v=_finite0(self.cvl_v),
            charge_current_a=ccl,
            discharge_current_a=dcl,
            discharge_voltage_v=_finite0(self.dvl_v),
            soc_pct=soc,
            soh_pct=min(soh, 100.0),
            voltage_v=self._voltage(here),
            current_a=float(np.nansum(np.where(here, m.bat.current_a[0], 0.0))),
            temp_c=_nanmax(m.bat.temp_c[0][here]),
            protection=prot,
            warning=warn,
            modules=int(here.sum()),
            name=self.name,
        )

    # ------------------------------------------------------------------ SOC
    def battery_soc(self) -> tuple[NDArray[np.float64], list[str]]:
        """The SOC the core uses per battery (0..1) and its source
        (``contract/soc_source.py``): the observer's estimate where trusted, the coulomb
        counter as its fallback, the battery's own report only without an estimator."""
        return self.view().soc()

    def pack_soc(self) -> tuple[float, float, str, int, int]:
        """(SOC 0..1, its standard deviation, source, batteries on the observer, on the
        fallback) of the pack as one battery: the core's SOC of each present battery weighted
        by its full capacity as it reports it (a battery without both counts nothing: a NaN
        would read as empty and drag the pack's SOC down). The deviation is the observer's
        (independent batteries, weighted the same way), NaN unless every battery counted is on
        the observer; the source is the observer only when every battery counted is, else the
        first of fallback, counter, battery's own that any battery counted is on."""
        m = self.core.m
        soc, sources = self.battery_soc()
        full = np.asarray(m.bat.full_capacity_ah[0], np.float64)
        known = self._present() & np.isfinite(full) & (full > 0) & np.isfinite(soc)
        total = float(full[known].sum())
        if total <= 0.0:
            return math.nan, math.nan, soc_source.BATTERY, 0, 0
        w = np.where(known, full / total, 0.0)
        value = float(np.sum(w * np.where(known, soc, 0.0)))
        used = [sources[i] for i in range(len(sources)) if known[i]]
        n_obs = used.count(soc_source.OBSERVER)
        n_fb = used.count(soc_source.FALLBACK)
        sigma = np.array([self.ch.value("soc_sigma", i) for i in range(len(sources))])
        sd = math.sqrt(float(np.sum((w * np.where(known, sigma, 0.0)) ** 2)))
        if n_obs == len(used):
            return value, sd, soc_source.OBSERVER, n_obs, n_fb
        src = next(s for s in (soc_source.FALLBACK, soc_source.COUNTER, soc_source.BATTERY)
                   if s in used)  # fmt: skip
        return value, math.nan, src, n_obs, n_fb

    def soc_frame(self, t: float) -> can.Message:
        """0x232: the pack's SOC as the core estimates it, with its source and deviation."""
        value, sd, src, n_obs, n_fb = self.pack_soc()
        return encode_soc(SocReport(100.0 * value, 100.0 * sd, soc_source.SOURCES.index(src),
                                    n_obs, n_fb), t)  # fmt: skip

    def _voltage(self, here: np.ndarray) -> float:
        bus = float(self.core.m.bus_v[0])
        if math.isfinite(bus):
            return bus
        v = self.core.m.bat.voltage_v[0][here]
        return float(np.nanmean(v)) if v.size and np.isfinite(v).any() else math.nan

    def _alarms(self, tripped: bool) -> tuple[int, int]:
        prot = pylon.SYSTEM_ERROR if tripped else 0
        warn = 0
        n = self.core.m.bat.reported.shape[1]
        for limit, quantity in self.quantity.items():
            bit = PYLON_BITS.get(quantity, 0)
            for i in range(n):
                tier = self.ch.label(f"lim_{limit}", i)
                if tier == "trip":
                    prot |= bit
                elif tier in ("warn", "derate"):
                    warn |= bit
        return prot, warn

    # ------------------------------------------------------------------ state of power
    def view(self) -> CoreView:
        """What the core knows of the pack now (``sim/power_view.py``): the SOC method's
        estimate and its source, the observer's polarisation and R0, the measurements, the
        switch feedback, the limits layer's per-battery limits, the supervisor's mode."""
        m, ch = self.core.m, self.ch
        n = m.bat.reported.shape[1]

        def per(name: str) -> NDArray[np.float64]:
            return np.array([ch.value(name, i) for i in range(n)], np.float64)

        return CoreView(
            soc_est=per("soc_est"), observer_ok=per("soc_observer_ok") == 1.0,
            soc_sigma=per("soc_sigma"), reported_soc=np.asarray(m.bat.soc[0], np.float64),
            v_rc_v=per("soc_v_rc_v"), r0_ohm=per("soc_r0_ohm"), temp_c=m.bat.temp_c[0],
            current_a=m.bat.current_a[0], voltage_v=m.bat.voltage_v[0],
            min_cell_v=m.bat.min_cell_v[0], max_cell_v=m.bat.max_cell_v[0],
            present=self._present(), chg_on=m.bat.sw_chg[0], dsg_on=m.bat.sw_dsg[0],
            limit_dsg_a=per("limit_dsg_a"), limit_chg_a=per("limit_chg_a"),
            tripped=mode(ch) in TRIPPED_MODES, bus_v=float(m.bus_v[0]),
        )  # fmt: skip

    def state_of_power(self) -> PowerOut | None:
        """The core's state of power now (:meth:`power_inputs`); None when nothing can be
        predicted. :func:`pack_limits`."""
        inp = self.power_inputs()
        return None if inp is None else pack_limits(self.power_prm, inp)

    def power_inputs(self) -> PowerInputs | None:
        """What the state of power is computed from: the state the core has (:meth:`view`),
        through ``sim/power_view.py:sop_inputs``, the one function the dashboard and the
        report use too. A battery not reporting, or with no SOC, counts as absent (the
        others are assumed to carry everything). Fresh arrays."""
        return sop_inputs(self.cfg, self.power_prm, self.view())

    def warm_up(self) -> None:
        """Compile (or load) the state-of-power kernels on a made-up state, before the
        clock starts: the first publication finds no battery reported yet and would
        otherwise compile them inside the loop. Interpreted there is nothing to compile
        (and half a second of CPU to lose before the first period): nothing to do."""
        if self.worker is not None:
            return
        n = self.power_prm.series.shape[0]
        half = np.full(n, 0.5)
        v = float(np.interp(0.5, self.power_prm.ocv_soc, self.power_prm.ocv_v))
        yes = np.ones(n, bool)
        inp = inputs_from_core(
            self.cfg, soc=half, temp_c=np.full(n, 25.0), current_a=np.zeros(n),
            voltage_v=self.power_prm.series * v, min_cell_v=np.full(n, v),
            max_cell_v=np.full(n, v), present=yes, chg_on=yes, dsg_on=yes, prm=self.power_prm,
        )  # fmt: skip
        pack_limits(self.power_prm, inp)

    def power_frame(self, t: float) -> can.Message:
        """0x231: the pack's 2 / 10 / 30 s discharge and 10 s charge limits (NaN: unknown)."""
        sop = self.sop
        if sop is None:
            return encode_power(math.nan, math.nan, math.nan, math.nan, t)
        d = [float(x) for x in sop.pack_dsg_a[0]]
        return encode_power(d[0], d[1], d[2], float(sop.pack_chg_a[0, 1]), t)

    # ------------------------------------------------------------------ the aircraft
    def protection(self) -> ProtectionReport:
        """The most-used battery's protection interface (255 / NaN: no protection)."""
        ch, n = self.ch, self.core.m.bat.reported.shape[1]
        fr = [ch.value("protection_fraction", i) for i in range(n)]
        finite = [i for i in range(n) if math.isfinite(fr[i])]
        m = mode(ch)
        mode_ix = MODES.index(m) if m is not None else 255
        if not finite:
            return ProtectionReport(mode_ix, 255, math.nan, math.nan, math.nan)
        i = max(finite, key=lambda j: fr[j])
        param = ch.value("protection_param", i)
        ttt = [ch.value("protection_time_to_trip_s", j) for j in range(n)]
        tte = [ch.value("protection_time_to_empty_s", j) for j in range(n)]
        return ProtectionReport(
            mode=mode_ix,
            active_param=int(param) if math.isfinite(param) else 255,
            allowance_used=fr[i],
            time_to_trip_s=soonest(ttt),
            time_to_empty_s=latest(tte),
        )

    def battery_infos(self) -> list[dc.BatteryInfo]:
        """BatteryInfo of the pack (battery_id 0) and of each battery (1..B)."""
        m = self.core.m
        here = self._present()
        tripped = mode(self.ch) in TRIPPED_MODES
        out = []
        pack = self.last or self.pack_as_battery()
        v = pack.voltage_v
        flags = self._flags(pack.current_a, bool(np.any(m.bat.sw_dsg[0] & here)), tripped)
        full_wh = float(np.nansum(np.where(here, m.bat.full_capacity_ah[0], 0.0))) * _finite0(v)
        rem_wh = full_wh * pack.soc_pct / 100.0
        _, pack_sd, _, _, _ = self.pack_soc()
        out.append(dc.BatteryInfo(0, v, pack.current_a, pack.temp_c, pack.soc_pct, pack.soh_pct,
                                  rem_wh, full_wh, flags, "PackPilot",
                                  soc_stdev_pct=_stdev_pct(pack_sd)))  # fmt: skip
        soc, sources = self.battery_soc()
        for i in range(m.bat.reported.shape[1]):
            vi, cur = float(m.bat.voltage_v[0, i]), float(m.bat.current_a[0, i])
            full = float(m.bat.full_capacity_ah[0, i])
            fl = self._flags(cur, bool(m.bat.sw_dsg[0, i]), tripped or not here[i])
            sd = self.ch.value("soc_sigma", i) if sources[i] == soc_source.OBSERVER else math.nan
            out.append(dc.BatteryInfo(i + 1, vi, cur, float(m.bat.temp_c[0, i]),
                                      100.0 * float(soc[i]), math.nan,
                                      float(soc[i]) * full * vi, full * vi, fl, f"PackPilot-{i}",
                                      soc_stdev_pct=_stdev_pct(sd)))  # fmt: skip
        return out

    def periodic(self) -> dc.BatteryPeriodic:
        """BatteryPeriodic of the pack: cell voltage limits and the current limits the
        aircraft may hold (continuous: the published DCL/CCL; 30 s burst: the 30 s state of
        power; 0 = not provided)."""
        pack = self.last or self.pack_as_battery()
        prm, sop = self.power_prm, self.sop
        cells = int(max(prm.series)) if prm.series.size else 0
        burst = float(sop.pack_dsg_a[0, HORIZON_CCL]) if sop is not None else 0.0
        if mode(self.ch) in TRIPPED_MODES:
            burst = 0.0
        return dc.BatteryPeriodic(
            name=self.name, design_capacity_ah=float(np.nansum(self.info.capacity_ah)),
            cells_in_series=cells,
            nominal_voltage_v=0.0,
            discharge_minimum_voltage_v=float(max(prm.cell_v_min, default=0.0)),
            charging_maximum_voltage_v=float(min(prm.cell_v_max, default=0.0)),
            charging_maximum_current_a=pack.charge_current_a,
            discharge_maximum_current_a=pack.discharge_current_a,
            discharge_maximum_burst_current_a=burst,
        )  # fmt: skip

    @staticmethod
    def _flags(current_a: float, in_use: bool, bad: bool) -> int:
        f = dc.IN_USE if in_use else 0
        if current_a < 0:
            f |= dc.CHARGING
        if bad:
            f |= dc.BMS_ERROR
        return f


def soonest(times_s: Sequence[float]) -> float:
    """The soonest of per-battery predicted times, over the batteries that have one.

    A battery that stands by (sequencing's STANDBY, or any battery not discharging) predicts
    nothing: NaN. Python's ``min`` keeps a NaN that comes first (every comparison with NaN is
    false), so the aircraft would read "no trip coming" while another battery trips in 2 s;
    the NaNs are dropped before comparing. NaN only when no battery predicts a time."""
    return min((x for x in times_s if math.isfinite(x)), default=math.nan)


def latest(times_s: Sequence[float]) -> float:
    """The latest of per-battery predicted times over the batteries that have one (the time
    to empty of the pack: the last battery to run out), NaN when none has one."""
    return max((x for x in times_s if math.isfinite(x)), default=math.nan)


FALLBACK_STDEV_PCT = 10.0
"""DroneCAN's ``state_of_charge_pct_stdev`` where the SOC is not the observer's (its DSDL: "use
best guess if unknown"): the coulomb counter's RMS error measured under the acceptance's sensor
errors, 2.6-14.8 %, median about 10 % (``benchmarks/RESULTS.md``, issue #28 observer figures,
"today's" column). Sending 0, as before, claimed a perfect SOC."""


def _stdev_pct(sd: float) -> float:
    """The SOC deviation sent (percentage points): the observer's, else the best guess."""
    return 100.0 * sd if math.isfinite(sd) else FALLBACK_STDEV_PCT


def _finite0(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def _ratio(a: float, b: float) -> float:
    return a / b if b > 0 and math.isfinite(a) else math.nan


def _nanmax(x: np.ndarray) -> float:
    return float(np.nanmax(x)) if x.size and np.isfinite(x).any() else math.nan


__all__ = ["PERIOD_S", "PYLON_BITS", "Channels", "Publisher", "latest", "soonest"]
