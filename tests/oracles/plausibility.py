"""ORACLE: the scalar plausibility monitor as it was before the compiled core (tests only;
deleted once the golden and equivalence tests pass).

Sensor and switch plausibility: detect lying measurements and failed switches, fail safe.

Limits and method controllers trust the numbers they get; this monitor decides whether those
numbers (and the switches) can be trusted. Per battery it detects

- ``nonfinite``: NaN / inf in a field a controller relies on;
- ``out_of_range``: a value outside its physical range (cell, group and battery voltage,
  temperature, current in C, SOC), or min cell above max cell;
- ``stuck``: a voltage (or temperature) that has not changed *at all* for a configured time
  while the battery carries current (a frozen ADC or a dead CAN source repeating its last
  frame); ``stale``: a per-battery ``sample_age_s`` above a limit, read from any measurement
  that carries the attribute (the simulator's ``sensor_dropout`` frames do);
- ``voltage_sum``: battery voltage disagreeing with the sum of its group voltages;
  ``group_count``: a group-voltage tuple of the wrong length;
- switch feedback disagreeing with the last command for longer than a delay: a welded or
  stuck-open relay, a shorted or stuck-open charge / discharge FET.

Each detection latches one ``Fault`` event (data: battery, kind, field, value, reaction) and a
fail-safe reaction expressed as commands; see ``docs/safety.md`` for the table. Sensor faults
clear by themselves after ``clear_after_s`` of plausible data; switch faults only through
:meth:`PlausibilityMonitor.clear_faults` (a service action). The monitor never raises.

The last command is learnt through :meth:`PlausibilityMonitor.note_commands`, which the
supervisor calls with the *merged* commands after every tick (a plain method rather than a
callback keeps the monitor a closed state machine that a log replay can feed as well).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from packpilot.config.plausibility import PlausibilityConfig
from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
    SwitchKind,
)
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo

EPS = 1e-9

SENSOR_KINDS: tuple[str, ...] = (
    "nonfinite",
    "out_of_range",
    "stuck",
    "stale",
    "voltage_sum",
    "group_count",
)
SWITCH_KINDS: tuple[str, ...] = (
    "relay_welded",
    "relay_stuck_open",
    "chg_fet_shorted",
    "dsg_fet_shorted",
    "chg_fet_stuck_open",
    "dsg_fet_stuck_open",
)
KINDS = SENSOR_KINDS + SWITCH_KINDS

Value = float | int | str | bool | None


def _finite(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


def capacity_ah(pack: PackInfo, i: int, bm: BatteryMeasurement | None) -> float:
    """Nominal capacity from the pack facts, else the battery's reported full capacity, else NaN.
    (Was ``packpilot.control.limits.capacity_ah``; copied so the oracle stands alone.)"""

    def fin(x: float) -> bool:  # limits' _finite (a bool counts as a number there)
        return isinstance(x, int | float) and math.isfinite(x)

    if i < len(pack.capacity_ah) and fin(pack.capacity_ah[i]) and pack.capacity_ah[i] > 0:
        return float(pack.capacity_ah[i])
    if bm is not None and fin(bm.full_capacity_ah) and bm.full_capacity_ah > 0:
        return float(bm.full_capacity_ah)
    return math.nan


def conducts(
    pack: PackInfo, i: int, bm: BatteryMeasurement, path: Literal["charge", "discharge"]
) -> bool:
    """Switch feedback says the battery can carry current in ``path``'s direction.
    (Was ``packpilot.control.limits.conducts``; copied so the oracle stands alone.)"""
    sw = bm.switch
    kind = pack.switch_kind[i] if i < len(pack.switch_kind) else SwitchKind.RELAY
    if kind == SwitchKind.RELAY:
        return sw.relay_closed
    return sw.chg_on if path == "charge" else sw.dsg_on


def _show(x: object) -> Value:
    """A JSON-safe event value: finite numbers as numbers, NaN / inf as text."""
    if isinstance(x, bool | str) or x is None:
        return x
    if isinstance(x, int | float):
        return float(x) if math.isfinite(x) else str(x)
    return str(x)


@dataclass(slots=True)
class _Detector:
    """Persistence timer and latch of one (battery, kind)."""

    bad_s: float = 0.0
    was_bad: bool = False
    ok_s: float = 0.0
    latched: bool = False
    field: str = ""
    value: Value = None


@dataclass(slots=True)
class _Track:
    last: float = math.nan
    unchanged_s: float = 0.0


@dataclass(slots=True)
class _BatteryState:
    det: dict[str, _Detector] = field(default_factory=lambda: {k: _Detector() for k in KINDS})
    tracks: dict[str, _Track] = field(default_factory=dict)
    cmd_chg: bool | None = None
    cmd_dsg: bool | None = None


Finding = tuple[bool, str, Value] | None
"""(bad, field, value); None = cannot be judged this tick (hold the timers)."""


class PlausibilityMonitor:
    """Detects implausible measurements and switch failures; see the module docstring."""

    def __init__(self, config: PlausibilityConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        n = pack.n_batteries
        self._bat = [_BatteryState() for _ in range(n)]
        self._pack_det = _Detector()
        self._pending: list[Event] = []
        self._t_s = math.nan
        self._isolated = [False] * n

    # -- supervisor interface -------------------------------------------------------------

    def note_commands(self, commands: Commands) -> None:
        """Record the merged commands that were applied (``None`` keeps the previous state,
        as the hardware does)."""
        for i, st in enumerate(self._bat):
            c = commands.chg_on[i] if i < len(commands.chg_on) else None
            d = commands.dsg_on[i] if i < len(commands.dsg_on) else None
            if c is not None:
                st.cmd_chg = bool(c)
            if d is not None:
                st.cmd_dsg = bool(d)

    def clear_faults(self, battery: int | None = None, kinds: Iterable[str] | None = None) -> int:
        """Service reset: unlatch faults of one battery (or all) and of the given kinds (or all).

        The only way to clear a switch fault. A condition still present re-latches after its
        delay. Returns how many faults were cleared; ``FaultCleared`` events come with the next
        tick.
        """
        wanted = set(KINDS if kinds is None else kinds)
        n = 0
        targets = range(len(self._bat)) if battery is None else (battery,)
        for i in targets:
            if not 0 <= i < len(self._bat):
                continue
            for kind, det in self._bat[i].det.items():
                if kind in wanted and det.latched:
                    self._unlatch(i, kind, det, manual=True, events=self._pending)
                    n += 1
        if battery is None and "nonfinite" in wanted and self._pack_det.latched:
            self._unlatch(None, "nonfinite", self._pack_det, manual=True, events=self._pending)
            n += 1
        return n

    def faults(self, battery: int) -> frozenset[str]:
        """Latched fault kinds of one battery."""
        return frozenset(k for k, d in self._bat[battery].det.items() if d.latched)

    @property
    def pack_fault(self) -> bool:
        """A pack-level measurement (bus voltage, load current) is not finite."""
        return self._pack_det.latched

    @property
    def welded(self) -> tuple[bool, ...]:
        """Relays known to be welded: never rely on them to isolate their battery."""
        return tuple(b.det["relay_welded"].latched for b in self._bat)

    # -- the tick -------------------------------------------------------------------------

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        cfg = self.config
        dt = float(dt_s) if _finite(dt_s) and dt_s > 0.0 else 0.0
        self._t_s = meas.t_s
        events, self._pending = self._pending, []
        n = self.pack.n_batteries
        docked = bool(meas.docked)
        bms: list[BatteryMeasurement | None] = [
            meas.batteries[i] if i < len(meas.batteries) else None for i in range(n)
        ]
        for i, st in enumerate(self._bat):
            bm = bms[i]
            present = bm is not None and bm.present
            findings: dict[str, tuple[Finding, float, bool]] = {}
            if present:
                assert bm is not None
                cap = capacity_ah(self.pack, i, bm)
                findings["nonfinite"] = (self._nonfinite(bm), cfg.nonfinite_delay_s, True)
                findings["out_of_range"] = (self._range(i, bm, cap), cfg.range_delay_s, True)
                findings["stuck"] = (self._stuck(st, bm, cap, dt), 0.0, True)
                findings["stale"] = (self._stale(bm), 0.0, True)
                findings["voltage_sum"] = (self._sum(i, bm), cfg.sum_delay_s, True)
                findings["group_count"] = (self._group_count(i, bm), 0.0, True)
                for kind, finding in self._switch(i, st, bm).items():
                    findings[kind] = (finding, cfg.switch_delay_s, False)
            for kind, det in st.det.items():
                finding, delay, auto_clear = findings.get(kind, (None, 0.0, False))
                self._advance(i, kind, det, finding, delay, auto_clear, dt, docked, bms, events)
        pack_finding: Finding = (False, "", None)
        for name in ("bus_v", "load_current_a"):
            x = getattr(meas, name)
            if not _finite(x):
                pack_finding = (True, name, _show(x))
                break
        self._advance(
            None,
            "nonfinite",
            self._pack_det,
            pack_finding,
            cfg.nonfinite_delay_s,
            True,
            dt,
            docked,
            bms,
            events,
        )
        return self._output(bms, docked, events)

    # -- detections -----------------------------------------------------------------------

    @staticmethod
    def _nonfinite(bm: BatteryMeasurement) -> Finding:
        for name in ("voltage_v", "current_a", "temp_c", "min_cell_v", "max_cell_v", "soc"):
            x = getattr(bm, name)
            if not _finite(x):
                return (True, name, _show(x))
        if isinstance(bm.min_temp_c, float) and math.isinf(bm.min_temp_c):
            return (True, "min_temp_c", _show(bm.min_temp_c))  # NaN = not measured
        for g, x in enumerate(bm.group_voltages_v):
            if not _finite(x):
                return (True, f"group_voltages_v[{g}]", _show(x))
        return (False, "", None)

    def _series(self, i: int) -> tuple[int, int]:
        """(groups, cells per group) of battery ``i``; 0 when the pack facts do not say."""
        g = self.pack.groups_per_battery[i] if i < len(self.pack.groups_per_battery) else 0
        c = self.pack.cells_per_group[i] if i < len(self.pack.cells_per_group) else 0
        return g, c

    def _range(self, i: int, bm: BatteryMeasurement, cap: float) -> Finding:
        cfg = self.config
        lo_v, hi_v = cfg.cell_v_range
        groups, per_group = self._series(i)
        checks: list[tuple[str, float, float, float]] = [
            ("min_cell_v", bm.min_cell_v, lo_v, hi_v),
            ("max_cell_v", bm.max_cell_v, lo_v, hi_v),
            ("temp_c", bm.temp_c, *cfg.temp_range_c),
            ("min_temp_c", bm.min_temp_c, *cfg.temp_range_c),
            ("soc", bm.soc, *cfg.soc_range),
        ]
        if groups and per_group:
            s = groups * per_group
            checks.append(("voltage_v", bm.voltage_v, lo_v * s, hi_v * s))
            checks.extend(
                (f"group_voltages_v[{g}]", x, lo_v * per_group, hi_v * per_group)
                for g, x in enumerate(bm.group_voltages_v)
            )
        if _finite(cap) and _finite(bm.current_a):
            lo_c, hi_c = cfg.current_range_c
            checks.append(("current_a", bm.current_a / cap, lo_c, hi_c))
        for name, x, lo, hi in checks:
            if _finite(x) and not lo <= x <= hi:
                return (True, name, _show(x))
        if _finite(bm.min_cell_v) and _finite(bm.max_cell_v) and bm.min_cell_v > bm.max_cell_v:
            return (True, "min_cell_v>max_cell_v", _show(bm.min_cell_v - bm.max_cell_v))
        return (False, "", None)

    def _stuck(self, st: _BatteryState, bm: BatteryMeasurement, cap: float, dt: float) -> Finding:
        cfg = self.config
        scale = cap if _finite(cap) else 1.0
        loaded = _finite(bm.current_a) and abs(bm.current_a) >= cfg.stuck_current_c * scale
        fields: list[tuple[str, float, float | None]] = [
            ("voltage_v", bm.voltage_v, cfg.stuck_time_s),
            ("min_cell_v", bm.min_cell_v, cfg.stuck_time_s),
            ("max_cell_v", bm.max_cell_v, cfg.stuck_time_s),
            ("temp_c", bm.temp_c, cfg.stuck_temp_time_s),
        ]
        fields.extend(
            (f"group_voltages_v[{g}]", x, cfg.stuck_time_s)
            for g, x in enumerate(bm.group_voltages_v)
        )
        hit: Finding = (False, "", None)
        for name, x, limit in fields:
            if limit is None:
                continue
            tr = st.tracks.setdefault(name, _Track())
            if x != tr.last:  # a change (or NaN) proves nothing is frozen
                tr.last, tr.unchanged_s = x, 0.0
            elif loaded:
                tr.unchanged_s += dt
            if hit is not None and not hit[0] and tr.unchanged_s >= limit - EPS:
                hit = (True, name, _show(x))
        return hit

    def _stale(self, bm: BatteryMeasurement) -> Finding:
        age = getattr(bm, "sample_age_s", None)
        if age is None or (isinstance(age, float) and math.isnan(age)):
            return None  # not reported (a NaN default would mean "unknown", not "stale")
        if not _finite(age) or age > self.config.max_sample_age_s:
            return (True, "sample_age_s", _show(age))
        return (False, "", None)

    def _group_count(self, i: int, bm: BatteryMeasurement) -> Finding:
        groups, _ = self._series(i)
        k = len(bm.group_voltages_v)
        if groups and k not in (0, groups):
            return (True, "group_voltages_v", k)
        return (False, "", None)

    def _sum(self, i: int, bm: BatteryMeasurement) -> Finding:
        groups, _ = self._series(i)
        g = bm.group_voltages_v
        if not groups or len(g) != groups:
            return None
        if not (_finite(bm.voltage_v) and all(_finite(x) for x in g)):
            return None
        diff = bm.voltage_v - sum(g)
        if abs(diff) > self.config.sum_tolerance_v_per_group * groups:
            return (True, "voltage_v-sum(group_voltages_v)", diff)
        return (False, "", None)

    def _switch(self, i: int, st: _BatteryState, bm: BatteryMeasurement) -> dict[str, Finding]:
        fb = bm.switch
        kind = self.pack.switch_kind[i] if i < len(self.pack.switch_kind) else SwitchKind.RELAY
        out: dict[str, Finding] = {}
        if kind == SwitchKind.RELAY:
            if st.cmd_chg is None or st.cmd_dsg is None:
                return out
            want = st.cmd_chg and st.cmd_dsg
            out["relay_welded"] = (not want and fb.relay_closed, "switch", fb.relay_closed)
            out["relay_stuck_open"] = (want and not fb.relay_closed, "switch", fb.relay_closed)
            return out
        for path, cmd, got in (("chg", st.cmd_chg, fb.chg_on), ("dsg", st.cmd_dsg, fb.dsg_on)):
            if cmd is None:
                continue
            out[f"{path}_fet_shorted"] = (not cmd and got, f"switch.{path}_on", got)
            out[f"{path}_fet_stuck_open"] = (cmd and not got, f"switch.{path}_on", got)
        return out

    # -- latching -------------------------------------------------------------------------

    def _advance(
        self,
        i: int | None,
        kind: str,
        det: _Detector,
        finding: Finding,
        delay: float,
        auto_clear: bool,
        dt: float,
        docked: bool,
        bms: Sequence[BatteryMeasurement | None],
        events: list[Event],
    ) -> None:
        if finding is None:
            return  # not judgeable now: hold every timer
        bad, name, value = finding
        if bad:
            det.bad_s = det.bad_s + dt if det.was_bad else 0.0
            det.was_bad, det.ok_s = True, 0.0
            if not det.latched and det.bad_s >= delay - EPS:
                det.latched, det.field, det.value = True, name, value
                reaction = self._reaction(i, kind, docked, bms)
                events.append(
                    Event(
                        t_s=self._t_s,
                        kind="Fault",
                        battery=i,
                        message=f"{kind}: {name} = {value} -> {reaction}",
                        data={
                            "battery": i,
                            "kind": kind,
                            "field": name,
                            "value": value,
                            "reaction": reaction,
                        },
                    )
                )
            return
        det.ok_s = det.ok_s + dt if not det.was_bad else 0.0
        det.was_bad, det.bad_s = False, 0.0
        if det.latched and auto_clear and det.ok_s >= self.config.clear_after_s - EPS:
            self._unlatch(i, kind, det, manual=False, events=events)

    def _unlatch(
        self, i: int | None, kind: str, det: _Detector, *, manual: bool, events: list[Event]
    ) -> None:
        events.append(
            Event(
                t_s=self._t_s,
                kind="FaultCleared",
                battery=i,
                message=f"{kind} cleared" + (" (service reset)" if manual else ""),
                data={"battery": i, "kind": kind, "field": det.field, "manual": manual},
            )
        )
        det.latched, det.bad_s, det.ok_s, det.was_bad = False, 0.0, 0.0, False
        det.field, det.value = "", None

    # -- reactions ------------------------------------------------------------------------

    def _sensor_bad(self, i: int) -> bool:
        return any(self._bat[i].det[k].latched for k in SENSOR_KINDS)

    def _is_relay(self, i: int) -> bool:
        kinds = self.pack.switch_kind
        return (kinds[i] if i < len(kinds) else SwitchKind.RELAY) == SwitchKind.RELAY

    def _other_source(self, i: int, bms: Sequence[BatteryMeasurement | None]) -> bool:
        """Another battery with trusted sensors can carry the load now (switch feedback)."""
        for j, bm in enumerate(bms):
            if j == i or bm is None or not bm.present or self._sensor_bad(j):
                continue
            if conducts(self.pack, j, bm, "discharge"):
                return True
        return False

    def _reaction(
        self, i: int | None, kind: str, docked: bool, bms: Sequence[BatteryMeasurement | None]
    ) -> str:
        """What the commands will do about a new fault (for the event; see ``_output``)."""
        if i is None:
            return "charger_off"
        if kind in SENSOR_KINDS:
            if self._bat[i].det["relay_welded"].latched:
                return "charger_off (welded relay: cannot isolate)"
            if docked or self._other_source(i, bms):
                return "isolate" + (" + charger_off until open" if docked else "")
            if self._is_relay(i):
                return "keep_supplying (last source in flight)"
            return "open_charge_path, keep_supplying (last source in flight)"
        return {
            "relay_welded": "charger_off; relay never used to isolate",
            "relay_stuck_open": "command_open",
            "chg_fet_shorted": "charger_off",
            "dsg_fet_shorted": "flag_only (discharge cannot be interrupted)",
            "chg_fet_stuck_open": "command_chg_off",
            "dsg_fet_stuck_open": "command_dsg_off",
        }[kind]

    def _output(
        self, bms: Sequence[BatteryMeasurement | None], docked: bool, events: list[Event]
    ) -> ControlOutput:
        n = self.pack.n_batteries
        chg: list[bool | None] = [None] * n
        dsg: list[bool | None] = [None] * n
        charger_off = self._pack_det.latched
        for i, st in enumerate(self._bat):
            det = st.det
            bm = bms[i]
            welded = det["relay_welded"].latched
            self._isolated[i] = False
            if det["relay_stuck_open"].latched:
                chg[i] = dsg[i] = False
            if det["chg_fet_stuck_open"].latched:
                chg[i] = False
            if det["dsg_fet_stuck_open"].latched:
                dsg[i] = False
            sensor_bad = self._sensor_bad(i)
            if sensor_bad and not welded:
                if docked or self._other_source(i, bms):
                    chg[i] = dsg[i] = False
                    self._isolated[i] = True
                elif not self._is_relay(i):
                    chg[i] = False  # discharge still flows through the charge FET's body diode
            can_take_charge = bm is not None and bm.present and conducts(self.pack, i, bm, "charge")
            if (sensor_bad or welded or det["chg_fet_shorted"].latched) and can_take_charge:
                charger_off = True  # never charge into a battery we cannot see or cannot block
        status: dict[str, Sequence[float | int | str | bool | None]] = {
            "plaus_faults": [",".join(sorted(self.faults(i))) for i in range(n)],
            "plaus_isolated": list(self._isolated),
        }
        return ControlOutput(
            commands=Commands(
                chg_on=tuple(chg),
                dsg_on=tuple(dsg),
                charger=CHARGER_OFF if charger_off else None,
            ),
            events=tuple(events),
            status=status,
        )


__all__ = ["KINDS", "SENSOR_KINDS", "SWITCH_KINDS", "PlausibilityConfig", "PlausibilityMonitor"]
