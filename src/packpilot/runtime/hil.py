"""Hardware in the loop: the simulated pack as CAN nodes.

:class:`Hil` puts one :class:`~packpilot.sim.plant_io.SimulatedPlant` on a bus as the nodes a
real pack has:

* a **battery node** per battery publishing ``packpilot.dbc`` telemetry every period — what
  :meth:`SimulatedPlant.measure` reads (the same ``sense`` kernel the simulator's BMS reads) —
  or DroneCAN BatteryInfo + BatteryInfoAux (``dronecan_ids``);
* a **switch node** per battery reporting what it does (``SwitchState``) and obeying
  ``SwitchCmd`` / ``BalancerCmd`` (and the aux node ``AuxCmd``) through
  :meth:`SimulatedPlant.apply`, with a **command timeout**: a node that has heard no new
  command (a repeated sequence number is not new) for ``timeout_periods`` BMS periods opens
  both paths (balancers 0 A, aux relay open) and stays open until commanded;
* the **platform node**: bus voltage and the dock contact;
* the **charger**: the existing :class:`~packpilot.io.can.emulator.ChargerEmulator` on the
  plant's dock;
* an **inverter** that decodes and logs every Pylontech frame it is told (``pylon.dbc``);
* an **aircraft** (flight controller) that decodes DroneCAN BatteryInfo with ``dronecan`` and
  keeps the protection state frame.

A switch node starts in the state the scenario configures, as the simulated switch does.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from packpilot.arena import Arena
from packpilot.config import ScenarioConfig
from packpilot.contract.arrays import cmd_arrays, meas_arrays
from packpilot.io.can import dronecan_io as dc
from packpilot.io.can import pylon
from packpilot.io.can.battery import (
    BatteryReport,
    decode,
    encode_battery,
    encode_platform,
    encode_switch_state,
)
from packpilot.io.can.bus import FrameLog
from packpilot.io.can.client import FrameCounters, received, transmit
from packpilot.io.can.codec import FrameError
from packpilot.io.can.emulator import ChargerEmulator
from packpilot.io.can.plant import battery_map
from packpilot.model.pack import Interval, Pack
from packpilot.sim.loop import Demand
from packpilot.sim.plant_io import SimulatedPlant

DRONECAN_NODE0 = 10
"""DroneCAN node id of battery 0's node (battery i: 10 + i)."""
PLATFORM = -1
"""The platform node in :attr:`Hil.silent`."""


@dataclass
class SwitchNode:
    """One battery's switch node: the last valid command and when it came."""

    chg: bool
    dsg: bool
    seq: int | None = None
    heard_s: float | None = None
    timed_out: bool = False
    timeouts: int = 0
    balancer_a: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def command(self, chg: bool, dsg: bool, seq: int, t: float) -> bool:
        """A command frame; False (ignored) when its sequence number repeats the last one."""
        if seq == self.seq:
            return False
        self.chg, self.dsg, self.seq, self.heard_s = chg, dsg, seq, t
        self.timed_out = False
        return True

    def check(self, t: float, timeout_s: float, started_s: float, keep_dsg: bool = False) -> None:
        """Open both paths (``keep_dsg``: the charge path only) once nothing new was heard for
        ``timeout_s``."""
        ref = self.heard_s if self.heard_s is not None else started_s
        if not self.timed_out and t - ref > timeout_s + 1e-9:
            self.timed_out = True
            self.timeouts += 1
            self.chg = False
            self.dsg = self.dsg and keep_dsg
            self.balancer_a[:] = 0.0


@dataclass
class InverterLog:
    """What the inverter was told: every Pylontech frame, decoded by cantools."""

    frames: list[tuple[float, str, dict[str, Any]]] = field(default_factory=list)
    last: dict[str, dict[str, Any]] = field(default_factory=dict)
    max_frames: int = 100_000

    def take(self, msg: can.Message, t: float) -> bool:
        if msg.is_extended_id or msg.arbitration_id not in _PYLON_IDS:
            return False
        db = pylon.database()
        try:
            m = db.get_message_by_frame_id(msg.arbitration_id)
            vals: dict[str, Any] = dict(m.decode(bytes(msg.data), decode_choices=False))  # type: ignore[arg-type]
        except Exception:
            return True
        self.last[m.name] = vals
        if len(self.frames) < self.max_frames:
            self.frames.append((t, m.name, vals))
        return True


@dataclass
class AircraftLog:
    """What the flight controller was told: DroneCAN BatteryInfo by ``battery_id``, decoded by
    the ``dronecan`` package once a transfer's last frame arrived."""

    last: dict[int, dc.BatteryInfo] = field(default_factory=dict)
    transfers: int = 0
    periodic: dc.BatteryPeriodic | None = None
    """The last BatteryPeriodic (design facts and the pack's current limits)."""
    assembler: dc.Assembler = field(
        default_factory=lambda: dc.Assembler((dc.BATTERY_INFO_ID, dc.BATTERY_PERIODIC_ID))
    )

    @property
    def errors(self) -> int:
        return self.assembler.errors

    def take(self, msg: can.Message) -> bool:
        if not self.assembler.wants(msg):
            return False
        info = self.assembler.take_any(msg)
        if isinstance(info, dc.BatteryInfo):
            self.last[info.battery_id] = info
            self.transfers += 1
        elif isinstance(info, dc.BatteryPeriodic):
            self.periodic = info
        return True


_PYLON_IDS = frozenset(
    (pylon.LIMITS_ID, pylon.SOC_ID, pylon.MEAS_ID, pylon.ALARMS_ID, pylon.REQUEST_ID,
     pylon.NAME_ID)
)  # fmt: skip


class Hil:
    """The simulated pack of ``cfg`` as CAN nodes on ``bus`` (charger on ``charger_bus``)."""

    protection: dict[str, float]
    """The last ProtectionState frame (0x230) the platform decoded ..."""
    power: dict[str, float]
    """... the last StateOfPower frame (0x231) ..."""
    soc: dict[str, float]
    """... and the last StateOfCharge frame (0x232)."""

    def __init__(
        self,
        cfg: ScenarioConfig,
        bus: can.BusABC,
        *,
        charger_bus: can.BusABC | None = None,
        bms_period_s: float | None = None,
        timeout_periods: int = 5,
        timeout_keeps_discharge: bool = False,
        log: FrameLog | None = None,
        dronecan_ids: dict[int, int] | None = None,
    ) -> None:
        """``dronecan_ids``: CAN index → DroneCAN ``battery_id`` of the batteries that
        publish BatteryInfo + BatteryInfoAux instead of the PackPilot frames."""
        self.cfg = cfg
        self.dronecan_ids = dict(dronecan_ids or {})
        self.keep_dsg = timeout_keeps_discharge
        self.bus = bus
        self.log = log
        self.plant = SimulatedPlant(cfg, 1)
        self.demand = Demand(cfg)
        self.bms_period_s = bms_period_s or cfg.sim.dt_s
        self.timeout_s = timeout_periods * self.bms_period_s
        topo = self.plant.topology
        bats = cfg.pack.batteries
        self.map = battery_map(topo.names, topo.roles, [b.series_groups for b in bats])
        self.nominal_v = [nominal_voltage(self.plant.pack, i) for i in range(len(bats))]
        """Each battery's nominal voltage (BatteryInfoAux: its Wh ↔ Ah conversion)."""
        info = self.plant.infos[0]
        g = max((b.series_groups for b in bats), default=1)
        ar = Arena()
        ar.add(meas_arrays(1, info.n_batteries, g))
        ar.add(cmd_arrays(1, info.n_batteries, g))
        self.arenas, views, rows = ar.seal()
        self.m, self.cmd = views
        self.m_row, self.cmd_row = rows
        pack = self.plant.pack
        self.switch = [
            SwitchNode(bool(pack.chg_on[0, s]), bool(pack.dsg_on[0, s]),
                       balancer_a=np.zeros(bats[s].series_groups))
            for s in topo.traction
        ]  # fmt: skip
        a = topo.aux
        self.aux = None if a is None else SwitchNode(bool(pack.chg_on[0, a]), True)
        self.aux_charge_a = 0.0
        self.charger: ChargerEmulator | None = None
        if cfg.charger.present and charger_bus is not None:
            self.charger = ChargerEmulator(
                charger_bus, pack.charger.view(0),
                heartbeat_timeout_s=cfg.charger.heartbeat_timeout_s,
            )  # fmt: skip
        self.inverter = InverterLog()
        self.aircraft = AircraftLog()
        self.protection, self.power, self.soc = {}, {}, {}
        """The last ProtectionState frame the platform was sent."""
        self.counters = FrameCounters()
        self.commands = 0
        """Command frames (switch, balancer, aux) heard, valid or repeated."""
        self.counter = 0
        self.started_s = pack.t_s
        self.hooks: list[Callable[[Hil, float], None]] = []
        """Called with (hil, t) after each period's telemetry went out: fault injection (an
        intruder's frames, silencing a node from the next period on)."""
        self.proxies: list[Callable[[Hil, list[can.Message], float], list[can.Message]]] = []
        """Called with (hil, frames, t) before a period's telemetry goes out; returns the
        frames to send instead: fault injection between the nodes and the bus (frozen,
        replayed, altered or duplicated frames), as a proxy on the wire would."""
        self.silent: set[int] = set()
        """CAN indices of battery nodes that do not publish (telemetry loss); :data:`PLATFORM`
        silences the platform node."""
        self.last_iv: Interval | None = None
        self.deaf = False
        """Fault injection: every frame sent to the twin is lost (switch commands, balancer,
        aux, the charger's requests excepted: that is its own bus) while True."""
        self.lost = 0

    @property
    def t_s(self) -> float:
        return self.plant.t_s

    # ------------------------------------------------------------------ telemetry out
    def publish(self) -> None:
        """Every battery's telemetry and the platform frame, as the plant is now."""
        t = self.t_s
        self.plant.measure(self.arenas, self.m_row)
        m = self.m
        out: list[can.Message] = []
        for k, i in enumerate(self.map.traction):
            if i not in self.silent:
                out += self._battery_frames(i, report(m.bat, k), t)
            node = self.switch[k]
            out.append(encode_switch_state(i, bool(m.bat.sw_chg[0, k]), bool(m.bat.sw_dsg[0, k]),
                                           node.timed_out, node.seq or 0, t))  # fmt: skip
        if self.map.aux is not None and self.map.aux not in self.silent:
            out += self._battery_frames(self.map.aux, report(m.aux, 0), t)
        if PLATFORM not in self.silent:
            out.append(encode_platform(float(m.bus_v[0]), bool(m.docked[0]), self.counter, t))
        self.counter = (self.counter + 1) & 0xFF
        for proxy in self.proxies:
            out = proxy(self, out, t)
        for msg in out:
            self.send(msg, t)
        for hook in self.hooks:
            hook(self, t)

    def _battery_frames(self, i: int, r: BatteryReport, t: float) -> list[can.Message]:
        """Battery ``i``'s telemetry: PackPilot frames, or DroneCAN BatteryInfo and
        BatteryInfoAux (cell voltages) when it is one of :attr:`dronecan_ids`."""
        bid = self.dronecan_ids.get(i)
        if bid is None:
            return encode_battery(i, r, self.counter, t)
        tid = self.counter & 0x1F
        vn = self.nominal_v[i]
        info = dc.BatteryInfo(bid, r.voltage_v, r.current_a, r.temp_c, 100.0 * r.soc,
                              full_wh=r.full_ah * vn, remaining_wh=r.remaining_ah * vn)  # fmt: skip
        cells = dc.BatteryCells(bid, r.group_v, nominal_voltage_v=vn)
        node = DRONECAN_NODE0 + i
        return dc.encode(info, node, tid, t=t) + dc.encode_cells(cells, node, tid, t=t)

    def send(self, msg: can.Message, t: float) -> None:
        transmit(self.bus, self.counters, self.log, msg, t)

    # ------------------------------------------------------------------ commands in, physics
    def advance(self, dt_s: float) -> Interval:
        """Obey the commands heard, run the charger node, step the plant by ``dt_s``."""
        t = self.t_s
        self.receive(t)
        for node in self.switch:
            node.check(t, self.timeout_s, self.started_s, self.keep_dsg)
        if self.aux is not None:
            self.aux.check(t, self.timeout_s, self.started_s)
            if self.aux.timed_out:
                self.aux_charge_a = 0.0
        self._actuate()
        if self.charger is not None:
            self.charger.poll(t)
        demand = np.full(1, self.demand.at(t))
        self.last_iv = self.plant.step(dt_s, demand, self.demand.profile.kind)
        return self.last_iv

    def _actuate(self) -> None:
        cmd = self.cmd
        for k, node in enumerate(self.switch):
            cmd.chg_on[0, k] = int(node.chg)
            cmd.dsg_on[0, k] = int(node.dsg)
            g = node.balancer_a.size
            cmd.balancer_a[0, k, :] = 0.0
            cmd.balancer_a[0, k, :g] = node.balancer_a
        cmd.balancer_set[0] = True
        if self.aux is not None:
            cmd.aux_relay[0] = int(self.aux.chg)
            cmd.aux_charge_set[0] = True
            cmd.aux_charge_a[0] = self.aux_charge_a
        self.plant.apply(self.arenas, self.cmd_row)

    def receive(self, t: float) -> None:
        for msg in received(self.bus, self.counters, self.log, t):
            if self.deaf:
                self.lost += 1
                continue
            if self.inverter.take(msg, t) or self.aircraft.take(msg):
                continue
            self._command(msg, t)

    def _command(self, msg: can.Message, t: float) -> None:
        try:
            kind, i, vals = decode(msg)
        except FrameError:
            self.counters.unexpected += 1
            return
        self.counters.received += 1
        if kind in ("switch", "balancer", "aux"):
            self.commands += 1
        if kind in ("protection", "power", "soc"):  # the platform keeps the last of each
            setattr(self, kind, vals)
            return
        if kind == "aux" and self.aux is not None:
            if self.aux.command(bool(vals["AuxRelay"]), True, int(vals["Seq"]), t):
                self.aux_charge_a = _finite0(vals["AuxChargeA"])
            return
        k = self.map.traction.index(i) if i in self.map.traction else -1
        if k < 0:
            return
        node = self.switch[k]
        if kind == "switch":
            node.command(bool(vals["ChgOn"]), bool(vals["DsgOn"]), int(vals["Seq"]), t)
        elif kind == "balancer" and not node.timed_out:
            b = int(vals["Block"])
            for j in range(3):
                g = 3 * b + j
                if g < node.balancer_a.size:
                    node.balancer_a[g] = _finite0(vals.get(f"BalancerA{g}", 0.0))

    def gates(self) -> tuple[np.ndarray, np.ndarray]:
        """Effective (charge, discharge) gates of the traction batteries now."""
        chg, dsg = self.plant.pack.effective_gates()
        tr = list(self.plant.topology.traction)
        return chg[0, tr].copy(), dsg[0, tr].copy()


def _finite0(x: float) -> float:
    return x if math.isfinite(x) else 0.0


def nominal_voltage(pack: Pack, i: int) -> float:
    """Battery ``i``'s nominal voltage as its DroneCAN node states it: its cells' open-circuit
    voltage at half charge × series groups, rounded to float16 as on the wire, so the Wh it
    reports (Ah × this) converts back to its Ah with only the Wh's own float16 rounding."""
    first = int(pack.string_cell_starts[i])
    prm = next(b.params for b in pack.banks if np.any(b.idx == first))
    cell_v = float(np.interp(0.5, prm.ocv_soc, prm.ocv_table_v))
    return float(np.float16(cell_v * pack.cfg.pack.batteries[i].series_groups))


def report(bat: Any, k: int) -> BatteryReport:
    """Battery ``k`` of measurement arrays as its node reports it."""
    ng = int(bat.n_groups[0, k])
    return BatteryReport(
        voltage_v=float(bat.voltage_v[0, k]),
        current_a=float(bat.current_a[0, k]),
        min_cell_v=float(bat.min_cell_v[0, k]),
        max_cell_v=float(bat.max_cell_v[0, k]),
        temp_c=float(bat.temp_c[0, k]),
        min_temp_c=float(bat.min_temp_c[0, k]),
        soc=float(bat.soc[0, k]),
        chg_on=bool(bat.sw_chg[0, k]),
        dsg_on=bool(bat.sw_dsg[0, k]),
        present=bool(bat.present[0, k]),
        full_ah=float(bat.full_capacity_ah[0, k]),
        remaining_ah=float(bat.remaining_capacity_ah[0, k]),
        cycle_count=float(bat.cycle_count[0, k]),
        group_v=tuple(float(x) for x in bat.group_v[0, k, :ng]),
    )





def run_realtime(
    hil: Hil,
    dt_s: float,
    duration_s: float | None = None,
    speed: float = 1.0,
    stop: Any = None,
) -> int:
    """Step ``hil`` every ``dt_s`` of simulated time, paced at ``speed`` simulated seconds per
    wall second on the monotonic clock (``speed <= 0``: as fast as possible); returns the
    periods stepped. Telemetry goes out at the start of each period, commands are obeyed
    at its end, as a real pack's nodes do between two BMS periods."""
    import time

    wall_dt = dt_s / speed if speed > 0 else 0.0
    due = time.monotonic()
    k = 0
    while (stop is None or not stop.is_set()) and (duration_s is None or k * dt_s < duration_s):
        if speed > 0:
            now = time.monotonic()
            if now < due:
                time.sleep(due - now)
            elif now > due + wall_dt:
                due = now  # late: restart the cadence, never burst (a burst looks like babbling)
            due += wall_dt
        hil.publish()
        hil.advance(dt_s)
        k += 1
    return k
__all__ = ["PLATFORM", "AircraftLog", "Hil", "InverterLog", "SwitchNode", "report", "run_realtime"]
