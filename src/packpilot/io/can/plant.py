"""The plant port over CAN: a real pack where the simulator stands.

:class:`CanPlant` is what :func:`packpilot.sim.loop.control` needs of a plant: ``measure``
fills the core's measurements with the latest telemetry each battery sent
(``packpilot.dbc``), ``apply`` sends the switch, balancer and aux commands, every period, not
only on change. The core, its rules and its safety layers do not know which plant they talk to.

Freshness: every battery's ``sample_age_s`` is the age of the oldest frame kind it must send
(meas, cells, state, capacity and, when it has groups, its group blocks). A silent battery keeps its
last values and its age grows, exactly what the fault injector's ``sensor_dropout`` produces:
the plausibility layer's ``stale`` rule (``[plausibility] max_sample_age_s``) treats it as a
dead sensor and the documented safe state follows. A battery never heard from reads NaN with an
infinite age. A battery node that sends any of its identifiers more than ``babble_factor``
times as often as it should per BMS period (once; its group frames once per block; a backlog
after a late period counts the periods that passed) is babbling: its sample is not trusted (age
infinite) while it does. The platform's bus voltage reads NaN once its frame is older than
``platform_timeout_s`` (a pack ``nonfinite`` fault). Once a sample is older than ``stale_s``
(the plausibility layer's ``max_sample_age_s``) its switch feedback reads *open*: what a
silent battery's switches do is unknown, and a path not known to conduct must not count as
connected (the limits layer's pack limits, ``n_conducting × weakest``, would otherwise count
an isolated battery the inverter can no longer draw from); the plausibility layer does not
judge the switches of a stale sample.

Switch commands: a controller with no opinion leaves a switch as it is; the port holds the
state the BMS last asked for, starting from the feedback of the battery's first state frame
(open if it never reported), and sends it every period with a sequence counter.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import can
import numpy as np
from numpy.typing import NDArray

from packpilot.arena import Arenas, unpack
from packpilot.contract.arrays import NO_OPINION, BatteryArrays, CmdArrays, MeasArrays
from packpilot.io.can import dronecan_io as dc
from packpilot.io.can.battery import (
    classify,
    decode,
    encode_aux,
    encode_balancer,
    encode_switch,
)
from packpilot.io.can.bus import FrameLog
from packpilot.io.can.client import FrameCounters, received, transmit
from packpilot.io.can.codec import FrameError
from packpilot.io.can.dbcgen import BATTERY_GROUPS, GROUPS_PER_FRAME, MAX_GROUPS

Array = NDArray[np.float64]

REQUIRED = ("meas", "cells", "state", "capacity")
"""Frame kinds every battery sends each period (plus its group blocks when it has groups)."""
DRONECAN_REQUIRED = ("dronecan", "switch_state")
"""A DroneCAN battery: its BatteryInfo, and its switch node's SwitchState (the feedback)."""
COUNTED = ("meas", "state")
"""Frame kinds that carry the node's alive counter (+1 per period)."""
SUSPECT_PERIODS = 2
"""Periods in a row with a duplicated, frozen or out-of-sequence counter after which a node's
telemetry is not trusted (issue #26: frozen, stale, duplicated or reordered frames are
detected within 2 periods)."""
LATE_PERIODS = 2
LATE_FLOOR_S = 0.2
"""A frame read more than max(2 periods, 0.2 s) after it reached the bus is late (the floor:
host stalls of a few tens of ms at a 10 ms period are not a telemetry fault)."""
RESYNC_PERIODS = 2
"""A counter sequence silent this many periods may be replaced by a new one (node reboot)."""
PRESENT_DEBOUNCE_S = 0.5
"""How long a battery's Present bit must hold a new value before the BMS believes it."""
PRESENT_CURRENT_A = 1.0
"""A battery carrying more than this is present, whatever its Present bit says."""
DOCK_DEBOUNCE_S = 1.0
"""How long the dock contact must read docked before the BMS believes it (in flight)."""
DOCK_MAX_DISCHARGE_C = 0.1
"""Docking is believed only while the pack discharges at most this C-rate (of its summed
capacity): a pack feeding a flight load is not on a dock."""


@dataclass(frozen=True)
class BatteryMap:
    """Which CAN index (``base + index`` identifiers) each configured battery uses."""

    traction: tuple[int, ...]
    """CAN index of traction battery ``k`` (the core's battery order)."""
    groups: tuple[int, ...]
    """Series groups of traction battery ``k``."""
    aux: int | None = None
    aux_groups: int = 0


@dataclass
class Freshness:
    """What the telemetry checks found (run metrics, asserted on in tests)."""

    duplicates: int = 0
    """Counted frames whose alive counter repeated the last one (dropped)."""
    out_of_order: int = 0
    """Counted frames behind or too far ahead of the sequence (dropped): old, reordered or a
    second node on the same identifiers."""
    resyncs: int = 0
    suspect: int = 0
    """Times a node became suspect (not trusted: its sample reads infinitely old)."""
    late: int = 0
    """Frames read more than ``late_s`` after they reached the bus (a receive backlog)."""
    present_glitches: int = 0
    """Present-bit changes not (yet) believed."""
    dock_rejected: int = 0


class FrameAges:
    """How long frames waited between reaching the bus and being read (real time only): a
    histogram of 1 ms bins up to 10 s plus the maximum, so a week-long run keeps 80 kB. The
    latency the BMS sees, backlogs included (issue #26: a flood through the hub)."""

    BIN_S = 1e-3
    BINS = 10_000

    def __init__(self) -> None:
        self.hist = np.zeros(self.BINS + 1, np.int64)
        self.max_s = 0.0

    def add(self, d: float) -> None:
        self.hist[min(int(d / self.BIN_S), self.BINS)] += 1
        self.max_s = max(self.max_s, d)

    def percentile_ms(self, q: float) -> float:
        """The ``q``-th percentile (upper bin edge, ms); NaN with no frame counted."""
        n = int(self.hist.sum())
        if n == 0:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self.hist), math.ceil(q / 100.0 * n)))
        return min((k + 1) * self.BIN_S, self.max_s) * 1e3

    def summary(self) -> dict[str, float]:
        """Empty without a wall clock (lock-step, replay: no frame has an age)."""
        if not self.hist.any():
            return {}
        return {"can_frame_age_p50_ms": self.percentile_ms(50),
                "can_frame_age_p99_ms": self.percentile_ms(99),
                "can_frame_age_max_ms": self.max_s * 1e3}  # fmt: skip


PORT_EVENT_KINDS = (
    "TelemetrySuspect", "TelemetryTrusted", "TelemetryResync", "PresenceConfirmed",
    "DockRejected", "DockConfirmed", "SwitchTimeoutSeen",
)  # fmt: skip
"""The event kinds the port's detections become (``contract/severity.py`` rates them)."""


@dataclass(frozen=True)
class Detection:
    """Something the port detected on the bus, for the runtime's events."""

    t_s: float
    kind: str
    battery: int | None
    message: str


class _Latest:
    """The last decoded values of one battery node and when each frame kind arrived."""

    def __init__(self, n_groups: int, dronecan: bool = False) -> None:
        self.dronecan = dronecan
        """Fed by DroneCAN BatteryInfo (+ BatteryInfoAux) and its switch node's SwitchState,
        instead of the PackPilot battery frames."""
        self.required = DRONECAN_REQUIRED if dronecan else REQUIRED
        self.values: dict[str, float] = {}
        self.group_v = np.full(MAX_GROUPS, np.nan)
        self.n_groups = n_groups
        self.rx_s: dict[str, float] = {}
        self.block_rx_s = np.full(-(-n_groups // GROUPS_PER_FRAME), -math.inf)
        self.babbling = False
        self.seen_this_period: dict[int, int] = {}
        self.new_seq = 0
        self.bad_seq = 0
        """Counted frames judged new / bad (duplicate, out of order) in this period."""
        self.seq = {k: _Sequence() for k in COUNTED}
        """The alive counter of each counted frame kind."""
        self.bad_periods = 0
        """Consecutive periods with a duplicated, frozen or out-of-sequence counted frame."""
        self.suspect = False
        """Its frames conflict or stopped advancing for :data:`SUSPECT_PERIODS` periods:
        not trusted (age infinite) until a clean period."""
        self.present_belief: bool | None = None
        """The Present bit as the BMS believes it (debounced; None: no state frame yet)."""
        self.present_bit_since_s = math.nan
        """Since when the Present bit has disagreed with the belief (NaN: it agrees)."""
        self.sw_timed_out = False
        self.sw_seq: int | None = None
        self.sw_rx_s = -math.inf

    def age(self, t: float) -> float:
        """Age of the oldest required frame (inf: never complete)."""
        oldest = min((self.rx_s.get(k, -math.inf) for k in self.required), default=-math.inf)
        if self.dronecan and "cells" in self.rx_s:  # cells are required once a battery sent them
            oldest = min(oldest, self.rx_s["cells"])
        elif self.block_rx_s.size and not self.dronecan:
            oldest = min(oldest, float(self.block_rx_s.min()))
        return t - oldest if math.isfinite(oldest) else math.inf

    def get(self, name: str) -> float:
        return self.values.get(name, math.nan)


class _Sequence:
    """One frame kind's alive counter: the last one accepted and when."""

    __slots__ = ("last", "rx_s")

    def __init__(self) -> None:
        self.last: int | None = None
        self.rx_s = -math.inf

    def judge(self, counter: int, t: float, period_s: float) -> str:
        """``new`` (accept), ``duplicate`` (the same counter again: a repeated or frozen
        frame), ``out_of_order`` (behind, or further ahead than the periods since the last
        accepted one allow: an old frame, a second source) or ``resync`` (the accepted
        sequence has been silent for :data:`RESYNC_PERIODS` periods: a rebooted node starts
        a new one; accept it)."""
        if self.last is None:
            verdict = "new"
        else:
            d = (counter - self.last) & 0xFF
            if d == 0:
                return "duplicate"
            gap = t - self.rx_s
            allowed = 2 + (max(0, round(gap / period_s)) if period_s > 0 else 0)
            if d <= min(allowed, 127):
                verdict = "new"
            elif period_s > 0 and gap >= RESYNC_PERIODS * period_s - 1e-9:
                verdict = "resync"
            else:
                return "out_of_order"
        self.last, self.rx_s = counter, t
        return verdict


class CanPlant:
    """Per-battery telemetry in, switch commands out, over one python-can bus."""

    def __init__(
        self,
        bus: can.BusABC,
        batteries: BatteryMap,
        *,
        balancers: bool = False,
        log: FrameLog | None = None,
        babble_factor: int = 4,
        platform_timeout_s: float = 1.0,
        period_s: float = 0.1,
        stale_s: float = 2.0,
        dronecan_ids: Mapping[int, int] | None = None,
        capacity_ah: float = math.nan,
        charger: bool = False,
    ) -> None:
        """``period_s``: the BMS period, at which every battery node sends its frames;
        ``stale_s``: the plausibility layer's ``max_sample_age_s``; ``dronecan_ids``:
        DroneCAN ``battery_id`` → CAN index of the batteries read from BatteryInfo;
        ``capacity_ah``: the pack's summed configured capacity (the dock's current check);
        ``charger``: the scenario has a charger (docking then needs it online)."""
        self.bus = bus
        self.capacity_ah = capacity_ah
        self.has_charger = charger
        self.freshness = Freshness()
        self.ages = FrameAges()
        self.wall: Callable[[], float] | None = None
        """The wall clock frames are stamped with (``time.time``), set by a real-time run:
        a frame then counts from when it reached the bus, not from when it was read."""
        self.late_s = max(LATE_PERIODS * period_s, LATE_FLOOR_S)
        """A frame read this long after it reached the bus is late (a bad period)."""
        self.detections: list[Detection] = []
        """What the port detected in this period (read and cleared by the runtime)."""
        self.dock_belief: bool | None = None
        self.dock_since_s = math.nan
        self.dock_rejected = False
        self.stale_s = stale_s
        self.period_s = period_s
        self._last_poll_s: float | None = None
        self.map = batteries
        self.balancers = balancers
        self.log = log
        self.babble_factor = babble_factor
        self.platform_timeout_s = platform_timeout_s
        self.t_s = 0.0
        """Set by the runtime before each period (the time every sample is aged against)."""
        self.counters = FrameCounters()
        self.babbled = 0
        """Periods in which some battery node babbled."""
        self.dronecan_ids = dict(dronecan_ids or {})
        by_dc = set(self.dronecan_ids.values())
        self.node: dict[int, _Latest] = {
            i: _Latest(g, i in by_dc)
            for i, g in zip(batteries.traction, batteries.groups, strict=True)
        }
        if batteries.aux is not None:
            self.node[batteries.aux] = _Latest(batteries.aux_groups, batteries.aux in by_dc)
        self.assembler = dc.Assembler()
        self.platform: dict[str, float] = {}
        self.platform_rx_s = -math.inf
        n = len(batteries.traction)
        self.held_chg = np.zeros(n, np.bool_)
        self.held_dsg = np.zeros(n, np.bool_)
        self._held_known = np.zeros(n, np.bool_)
        self.held_balancer = np.zeros((n, max(max(batteries.groups, default=1), 1)))
        self.held_aux_relay: bool | None = None
        self.held_aux_charge_a = 0.0
        self.seq = 0
        self.sent_seqs: list[int] = []
        """The sequence numbers of the last few command periods (newest last)."""
        self._view_cache: dict[tuple[int, int, type], Any] = {}

    # ------------------------------------------------------------------ receive
    def poll(self) -> None:
        """Drain the bus (at most :data:`MAX_FRAMES_PER_POLL` frames) into the latest values."""
        t = self.t_s
        for node in self.node.values():
            node.seen_this_period.clear()
            node.new_seq = node.bad_seq = 0
        now = self.wall() if self.wall is not None else math.nan
        for msg in received(self.bus, self.counters, self.log, t):
            self._take(msg, t - self._delay(msg, now))
        # A backlog after a stalled period is not babbling: allow for the periods that passed.
        periods = 1
        if self._last_poll_s is not None and self.period_s > 0:
            periods = max(1, math.ceil((t - self._last_poll_s) / self.period_s - 1e-6))
        self._last_poll_s = t
        babbled = False
        for i, node in self.node.items():
            node.babbling = any(
                n > self.babble_factor * _expected(fid, node) * periods
                for fid, n in node.seen_this_period.items()
            )
            babbled |= node.babbling
            self._judge_sequence(i, node, t)
        self.babbled += babbled

    def _judge_sequence(self, i: int, node: _Latest, t: float) -> None:
        """A period with a duplicated, frozen or out-of-sequence counted frame is bad;
        :data:`SUSPECT_PERIODS` bad periods in a row make the node suspect, a clean period
        with a new frame trusts it again."""
        bad = node.bad_seq > 0
        new = node.new_seq > 0
        if bad:
            node.bad_periods += 1
        elif new:
            node.bad_periods = 0
        was = node.suspect
        node.suspect = node.bad_periods >= SUSPECT_PERIODS
        if node.suspect and not was:
            self.freshness.suspect += 1
            self.detections.append(Detection(t, "TelemetrySuspect", i, (
                f"battery node {i}: its alive counter repeated, froze or went out of sequence "
                f"for {SUSPECT_PERIODS} periods: not trusted")))  # fmt: skip
        elif was and not node.suspect:
            self.detections.append(Detection(t, "TelemetryTrusted", i,
                                             f"battery node {i}: counter advancing again"))

    def _delay(self, msg: can.Message, now: float) -> float:
        """How long ``msg`` waited since it reached the bus (its receive timestamp, on the
        wall clock of every python-can interface) before this poll read it: 0 without a wall
        clock (lock-step, replay), or when the timestamp is missing or ahead of the clock."""
        ts = msg.timestamp
        if not (math.isfinite(now) and ts and math.isfinite(ts)):
            return 0.0
        d = now - ts
        if not 0.0 < d < 1e6:
            return 0.0
        self.ages.add(d)
        if d > self.late_s:
            self.freshness.late += 1
        return d

    def _take(self, msg: can.Message, t: float) -> None:
        if self.assembler.wants(msg):
            self._take_dronecan(msg, t)
            return
        try:
            kind, i, vals = decode(msg)
        except FrameError:
            known = not msg.is_extended_id and not msg.is_error_frame and not msg.is_remote_frame
            if known and _is_ours(msg.arbitration_id):
                self.counters.malformed += 1
            else:
                self.counters.unexpected += 1
            return
        if kind == "platform":
            self.counters.received += 1
            self.platform, self.platform_rx_s = vals, t
            return
        node = self.node.get(i)
        if node is None or kind not in (*node.required, "groups", "cells", "switch_state"):
            self.counters.unexpected += 1  # a command echo, another BMS, an unmapped battery
            return
        self.counters.received += 1
        fid = msg.arbitration_id
        node.seen_this_period[fid] = node.seen_this_period.get(fid, 0) + 1
        if kind == "groups":
            self._take_groups(node, vals, t)
            return
        if kind == "switch_state":  # the feedback of a battery that does not report its own;
            timed_out = vals["TimedOut"] == 1.0
            if timed_out and not node.sw_timed_out:
                self.detections.append(Detection(t, "SwitchTimeoutSeen", i, (
                    f"switch node {i} opened on its command timeout (our commands did not "
                    "reach it): not a switch fault")))  # fmt: skip
            node.sw_timed_out = timed_out
            node.sw_seq = int(vals["Seq"])
            node.sw_rx_s = t
            if node.dronecan:  # a PackPilot battery reports its own (BatteryState)
                node.values["ChgOn"], node.values["DsgOn"] = vals["ChgOn"], vals["DsgOn"]
                node.rx_s[kind] = t
            return
        if kind in COUNTED and not self._fresh(i, node, kind, vals, t):
            return
        if kind == "state":
            vals = dict(vals)
            vals["Present"] = self._present(i, node, vals.get("Present", math.nan), t)
        node.values.update(vals)
        node.rx_s[kind] = t

    def _fresh(self, i: int, node: _Latest, kind: str, vals: dict[str, float], t: float) -> bool:
        """Check a counted frame's alive counter; only a new one refreshes the battery."""
        c = vals.get("Counter", math.nan)
        if self.t_s - t > self.late_s:
            node.bad_seq += 1  # late: read well after it came (a backlog); its age counts
        if not math.isfinite(c):
            verdict = "out_of_order"
        else:
            verdict = node.seq[kind].judge(int(c), t, self.period_s)
        if verdict in ("new", "resync"):
            node.new_seq += 1
            if verdict == "resync":
                self.freshness.resyncs += 1
                self.detections.append(Detection(t, "TelemetryResync", i, (
                    f"battery node {i}: {kind} counter restarted at {int(c)} (node reboot?)")))
            return True
        node.bad_seq += 1
        if verdict == "duplicate":
            self.freshness.duplicates += 1
        else:
            self.freshness.out_of_order += 1
        return False

    def _present(self, i: int, node: _Latest, bit: float, t: float) -> float:
        """The debounced Present bit: a new value counts once it held
        :data:`PRESENT_DEBOUNCE_S`; a battery that carries current is present."""
        raw = bit == 1.0 or math.isnan(bit)
        if node.present_belief is None:
            node.present_belief = raw
        elif raw == node.present_belief:
            node.present_bit_since_s = math.nan
        else:
            current = abs(node.get("Current"))
            if not raw and current > PRESENT_CURRENT_A:
                raw_ok = False  # carries current: it is there
            else:
                if math.isnan(node.present_bit_since_s):
                    node.present_bit_since_s = t
                    self.freshness.present_glitches += 1
                raw_ok = t - node.present_bit_since_s >= PRESENT_DEBOUNCE_S - 1e-9
            if raw_ok:
                node.present_belief = raw
                node.present_bit_since_s = math.nan
                word = "inserted" if raw else "removed"
                self.detections.append(Detection(t, "PresenceConfirmed", i, (
                    f"battery node {i}: {word} (Present bit held {PRESENT_DEBOUNCE_S:g} s)")))
            elif not raw and math.isnan(node.present_bit_since_s):
                self.freshness.present_glitches += 1
        return 1.0 if node.present_belief else 0.0

    def _take_dronecan(self, msg: can.Message, t: float) -> None:
        """A frame of a DroneCAN transfer; a complete BatteryInfo / BatteryInfoAux of a mapped
        ``battery_id`` updates its battery."""
        before = self.assembler.errors
        done = self.assembler.take(msg)
        if self.assembler.errors > before:
            self.counters.malformed += 1
        if done is None:
            return
        i = self.dronecan_ids.get(done.battery_id)
        node = self.node.get(i) if i is not None else None
        if node is None or not node.dronecan:
            self.counters.unexpected += 1  # another battery's, or the BMS's own kind
            return
        self.counters.received += 1
        key = -1 - dc.data_type(msg)
        node.seen_this_period[key] = node.seen_this_period.get(key, 0) + 1
        if isinstance(done, dc.BatteryInfo):
            node.values.update({
                "Voltage": done.voltage_v, "Current": done.current_a, "TempMax": done.temp_c,
                "SOC": done.soc_pct / 100.0, "Present": 1.0,
                "FullWh": done.full_wh, "RemainingWh": done.remaining_wh,
            })  # fmt: skip
            node.rx_s["dronecan"] = t
        else:
            cells = done.cell_v
            node.values["MinCellV"] = min(cells, default=math.nan)
            node.values["MaxCellV"] = max(cells, default=math.nan)
            node.values["CycleCount"] = float(done.cycle_count)
            node.values["NominalV"] = done.nominal_voltage_v
            n = min(len(cells), MAX_GROUPS)
            node.group_v[:] = math.nan
            node.group_v[:n] = cells[:n]
            node.values["NGroupsReported"] = float(len(cells))
            node.rx_s["cells"] = t
        # Capacities: BatteryInfo's Wh over BatteryInfoAux's nominal voltage (the two arrive
        # as separate transfers; NaN until both did, or when the battery omits the conversion).
        full = dc.ah_from_wh(node.get("FullWh"), node.get("NominalV"))
        node.values["FullAh"] = full if full > 0.0 else math.nan
        node.values["RemainingAh"] = dc.ah_from_wh(node.get("RemainingWh"), node.get("NominalV"))

    @staticmethod
    def _take_groups(node: _Latest, vals: dict[str, float], t: float) -> None:
        b = int(vals["Block"])
        if not 0 <= b < node.block_rx_s.size:
            return
        for j in range(GROUPS_PER_FRAME):
            g = b * GROUPS_PER_FRAME + j
            if g < MAX_GROUPS:
                node.group_v[g] = vals.get(f"GroupV{g}", math.nan)
        node.values["NGroupsReported"] = vals["NGroups"]
        node.block_rx_s[b] = t

    def complete(self) -> bool:
        """Every battery has sent every frame kind it must (start-up)."""
        return all(math.isfinite(n.age(self.t_s)) for n in self.node.values())

    # ------------------------------------------------------------------ the port
    def measure(self, arenas: Arenas, m_row: int) -> None:
        """Read the bus and fill the measurements at ``m_row`` of a core's arenas (pack 0)."""
        self.poll()
        m: MeasArrays = self._view(MeasArrays, arenas, m_row)
        t = self.t_s
        m.t_s[0] = t
        for k, i in enumerate(self.map.traction):
            self._fill(m.bat, k, self.node[i], t)
            if not self._held_known[k] and "ChgOn" in self.node[i].values:
                self.held_chg[k] = m.bat.sw_chg[0, k]
                self.held_dsg[k] = m.bat.sw_dsg[0, k]
                self._held_known[k] = True
        aux = self.map.aux
        m.has_aux[0] = aux is not None
        if aux is not None:
            self._fill(m.aux, 0, self.node[aux], t)
            if self.held_aux_relay is None and "ChgOn" in self.node[aux].values:
                self.held_aux_relay = bool(m.aux.sw_chg[0, 0] and m.aux.sw_dsg[0, 0])
        fresh = t - self.platform_rx_s <= self.platform_timeout_s
        m.bus_v[0] = self.platform.get("BusV", math.nan) if fresh else math.nan
        currents = m.bat.current_a[0]
        m.load_current_a[0] = float(np.sum(currents)) if currents.size else 0.0
        m.docked[0] = self._docked(m, t)

    def _docked(self, m: MeasArrays, t: float) -> bool:
        """The dock contact as the BMS believes it. Its first value is taken as it is (a pack
        powered up on its dock); later, undocking counts at once (it stops charging), but
        docking only once the contact has read docked for :data:`DOCK_DEBOUNCE_S` and the
        cross-checks hold: the bus voltage is fresh, the charger (if the scenario has one)
        reports online, and the pack is not feeding a load (net discharge at most
        :data:`DOCK_MAX_DISCHARGE_C`). A stuck or glitching contact in flight therefore never
        puts the pack in charge mode (issue #26)."""
        if "Docked" not in self.platform:
            return bool(self.dock_belief)
        bit = self.platform["Docked"] == 1.0
        if self.dock_belief is None or not bit:
            self.dock_belief, self.dock_since_s, self.dock_rejected = bit, math.nan, False
            return bit
        if self.dock_belief:
            return True
        if math.isnan(self.dock_since_s):
            self.dock_since_s = t
        if t - self.dock_since_s < DOCK_DEBOUNCE_S - 1e-9:
            return False
        why = self._dock_doubt(m)
        if why:
            if not self.dock_rejected:
                self.freshness.dock_rejected += 1
                self.detections.append(Detection(t, "DockRejected", None,
                                                 f"dock contact reads docked, but {why}"))
            self.dock_rejected = True
            return False
        self.dock_belief = True
        self.detections.append(Detection(t, "DockConfirmed", None, (
            f"dock contact held {DOCK_DEBOUNCE_S:g} s, bus voltage, charger and current agree")))
        return True

    def _dock_doubt(self, m: MeasArrays) -> str:
        """Why the measurements contradict a docked pack ('' if they do not)."""
        if not math.isfinite(m.bus_v[0]):
            return "the bus voltage is unknown"
        if self.has_charger and not (m.charger.reported[0] and m.charger.online[0]):
            return "the charger is not online"
        i = float(m.load_current_a[0])
        cap = self.capacity_ah
        limit = DOCK_MAX_DISCHARGE_C * cap if math.isfinite(cap) and cap > 0 else 1.0
        if not i <= limit:
            return f"the pack discharges {i:.1f} A (a docked pack feeds at most {limit:.2g} A)"
        return ""

    def _fill(self, bat: BatteryArrays, k: int, node: _Latest, t: float) -> None:
        g = node.get
        bat.voltage_v[0, k] = g("Voltage")
        bat.current_a[0, k] = g("Current")
        bat.min_cell_v[0, k] = g("MinCellV")
        bat.max_cell_v[0, k] = g("MaxCellV")
        bat.temp_c[0, k] = g("TempMax")
        bat.min_temp_c[0, k] = g("TempMin")
        bat.soc[0, k] = g("SOC")
        bat.full_capacity_ah[0, k] = g("FullAh")
        bat.remaining_capacity_ah[0, k] = g("RemainingAh")
        bat.cycle_count[0, k] = g("CycleCount")
        ng = min(node.n_groups, bat.group_v.shape[2])
        bat.group_v[0, k, :] = np.nan
        bat.group_v[0, k, :ng] = node.group_v[:ng]
        reported = g("NGroupsReported")
        bat.n_groups[0, k] = int(reported) if math.isfinite(reported) else 0
        age = math.inf if (node.babbling or node.suspect) else node.age(t)
        known = age <= self.stale_s  # a stale sample's switch feedback is not feedback
        bat.sw_chg[0, k] = known and g("ChgOn") == 1.0
        bat.sw_dsg[0, k] = known and g("DsgOn") == 1.0
        present = g("Present")
        bat.present[0, k] = present == 1.0 or math.isnan(present)  # never heard: judge it
        bat.reported[0, k] = True
        bat.sample_age_s[0, k] = age
        bat.sw_explained[0, k] = self.explained(node, t)

    def explained(self, node: _Latest, t: float) -> bool:
        """The battery's switch node says why its switches may disagree with the commands:
        it opened them on its command timeout, or it has not yet obeyed one of our last
        commands (lost or late command frames). Such a disagreement is the bus's doing, not a
        failed switch, so the plausibility layer does not judge the switch then; a node that
        never sent its state explains nothing (judged as before)."""
        if t - node.sw_rx_s > self.stale_s:
            return False
        if node.sw_timed_out:
            return True
        return bool(self.sent_seqs) and node.sw_seq not in self.sent_seqs

    def apply(self, arenas: Arenas, cmd_row: int) -> None:
        """Hold the commands at ``cmd_row`` (no opinion: unchanged) and send them all."""
        cmd: CmdArrays = self._view(CmdArrays, arenas, cmd_row)
        for k in range(self.held_chg.size):
            if cmd.chg_on[0, k] != NO_OPINION:
                self.held_chg[k] = cmd.chg_on[0, k] == 1
            if cmd.dsg_on[0, k] != NO_OPINION:
                self.held_dsg[k] = cmd.dsg_on[0, k] == 1
        if cmd.balancer_set[0]:
            g = self.held_balancer.shape[1]
            self.held_balancer[:] = np.nan_to_num(cmd.balancer_a[0, :, :g])
        if cmd.aux_relay[0] != NO_OPINION:
            self.held_aux_relay = cmd.aux_relay[0] == 1
        if cmd.aux_charge_set[0]:
            self.held_aux_charge_a = float(np.nan_to_num(cmd.aux_charge_a[0]))
        self.send_commands()

    def send_commands(self) -> None:
        """The held commands, one frame set per period."""
        t, seq = self.t_s, self.seq
        out: list[can.Message] = []
        for k, i in enumerate(self.map.traction):
            out.append(encode_switch(i, bool(self.held_chg[k]), bool(self.held_dsg[k]), seq, t))
            if self.balancers and self.map.groups[k]:
                cur = tuple(float(x) for x in self.held_balancer[k, : self.map.groups[k]])
                out += encode_balancer(i, cur, seq, t)
        if self.map.aux is not None:
            out.append(encode_aux(bool(self.held_aux_relay), self.held_aux_charge_a, seq, t))
        self.sent_seqs = [*self.sent_seqs[-2:], seq]
        self.seq = (seq + 1) & 0xFF
        for msg in out:
            self._send(msg, t)

    def _send(self, msg: can.Message, t: float) -> None:
        transmit(self.bus, self.counters, self.log, msg, t)

    def _view(self, cls: type, arenas: Arenas, row: int) -> Any:
        """The named tuple at ``row`` of a core's arenas, as views (built once)."""
        key = (id(arenas.f), row, cls)
        view = self._view_cache.get(key)
        if view is None:
            view = self._view_cache[key] = unpack(cls, *arenas, row)
        return view


def _expected(frame_id: int, node: _Latest) -> int:
    """Frames of ``frame_id`` a healthy node sends per period: one, or one per group block."""
    return max(1, node.block_rx_s.size) if frame_id & ~0xF == BATTERY_GROUPS else 1


def _is_ours(frame_id: int) -> bool:
    return classify(frame_id) is not None


def battery_map(names: Sequence[str], roles: Sequence[str], groups: Sequence[int]) -> BatteryMap:
    """CAN index = position in ``[[pack.batteries]]``; the aux battery is the one of role aux."""
    traction = tuple(i for i, r in enumerate(roles) if r != "aux")
    aux = next((i for i, r in enumerate(roles) if r == "aux"), None)
    return BatteryMap(
        traction=traction,
        groups=tuple(groups[i] for i in traction),
        aux=aux,
        aux_groups=groups[aux] if aux is not None else 0,
    )


__all__ = [
    "PORT_EVENT_KINDS", "REQUIRED", "BatteryMap", "CanPlant", "Detection", "Freshness",
    "battery_map",
]  # fmt: skip
