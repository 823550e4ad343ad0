"""Did the run go wrong? A verdict and an alarms table, from the events and from physics.

Events say what the BMS *noticed*; a run with no controller notices nothing, yet its cells can
still be drained below empty, one battery can still push 40 A into another, and the load can
still lose power. So the verdict has two sources, both computed here, once, for every view
(``simulate``'s summary and ``--fail-on``, the HTML report, the live dashboard):

* **events**: every event kind has a severity in one table (:mod:`packpilot.contract.severity`);
  warnings, alarms and faults become rows of the alarms table, one per kind, battery and
  cause, with the first time, the count and whether the condition was cleared;
* **physics checks** on the recorded plant truth (the trace: what really happened, not what the
  sensors reported): over-discharge (a cell below its cell set's minimum voltage: alarm; SOC
  below 0 %: warning), cross-charge (battery-to-battery current into a traction battery above
  its charge limit, whatever the charger does: alarm), cross-discharge (a traction battery
  giving more than 2 A to other batteries for more than 10 s while the dock charges: alarm)
  and load loss (the load got less than it asked for: alarm). The battery-to-battery share of
  a battery's current is :func:`packpilot.sim.metrics.cross_current`'s, per battery.

The checks are streaming (:class:`PhysicsWatch` takes the trace in chunks of any length), so
the dashboard feeds it as samples arrive and a finished run feeds its whole trace at once, with
the same code. Nothing here changes a run: severities and verdicts are presentation.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config.limits import LimitsConfig
from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Result, StepSample
from packpilot.contract.severity import MATCH_FIELDS, VERDICTS, Severity, row_of
from packpilot.contract.topology import Topology
from packpilot.sim.fit_range import FitWatch

F64 = NDArray[np.float64]
B1 = NDArray[np.bool_]

CATEGORIES: tuple[str, ...] = (
    "fault", "trip", "unsupplied", "overdischarge", "crosscharge", "limit", "refused",
    "crosscurrent", "reserve", "extrapolated", "unknown",
)  # fmt: skip
"""Every category an alarm can have: what ``simulate --fail-on`` accepts."""

DEFAULT_CHARGE_C = 2.0
"""Charge limit (1/h) when neither the scenario nor the default limits table names one."""
LOAD_LOSS_REL = 0.01
LOAD_LOSS_ABS_A = 0.05
"""The load counts as unsupplied when it got less than its demand by more than 1 % and 50 mA
(the bus solve is exact; this only keeps rounding out)."""
CHARGER_IDLE_A = 0.01
"""A charger delivering at most this is not charging."""
CROSS_DISCHARGE_A = 2.0
CROSS_DISCHARGE_S = 10.0
"""A traction battery that gives more than 2 A to other batteries for more than 10 s while
the dock charges is discharging into its siblings: what staged charging exists to avoid
(issue #24 item 3's acceptance bound)."""

_CH = {name: k for k, name in enumerate(BATTERY_CHANNELS)}


@dataclass(frozen=True)
class Alarm:
    """One row of the alarms table."""

    t_s: float
    """First time the condition was seen."""
    battery: str | None
    """Display name; None for the whole pack."""
    kind: str
    """The event kind, or the physics check (``OverDischarge``, ``CrossCharge``, ``LoadLoss``)."""
    category: str
    severity: Severity
    cause: str
    cleared_t_s: float | None = None
    """When the condition last ended; None while it stands (or for a one-off)."""
    count: int = 1
    """Episodes (physics) or events (event kinds) of this row."""
    source: str = "event"
    """``event`` (what the BMS reported) or ``physics`` (what the trace shows)."""

    @property
    def cleared(self) -> bool:
        return self.cleared_t_s is not None

    def as_dict(self) -> dict[str, Any]:
        return {
            "t_s": self.t_s,
            "battery": self.battery,
            "kind": self.kind,
            "category": self.category,
            "severity": self.severity.label,
            "cause": self.cause,
            "cleared": self.cleared,
            "cleared_t_s": self.cleared_t_s,
            "count": self.count,
            "source": self.source,
        }


@dataclass(frozen=True)
class Verdict:
    """A run's verdict: its highest severity and the alarms behind it."""

    severity: Severity
    alarms: tuple[Alarm, ...]

    @property
    def word(self) -> str:
        """``OK``, ``WARNING``, ``ALARM`` or ``FAULT``."""
        return VERDICTS[self.severity]

    @property
    def categories(self) -> frozenset[str]:
        return frozenset(a.category for a in self.alarms)

    def as_dict(self) -> dict[str, Any]:
        return {
            "verdict": self.word,
            "severity": self.severity.label,
            "alarms": [a.as_dict() for a in self.alarms],
        }


def verdict_of(alarms: Iterable[Alarm]) -> Verdict:
    """The verdict of a set of alarms: the worst first, then by time."""
    rows = sorted(alarms, key=lambda a: (-a.severity, a.t_s))
    worst = max((a.severity for a in rows), default=Severity.INFO)
    return Verdict(worst, tuple(rows))


# --------------------------------------------------------------------------- events


def _match_key(e: Event) -> tuple[tuple[str, Any], ...]:
    return tuple((k, e.data[k]) for k in (*MATCH_FIELDS, "reason") if k in e.data)


def _clears(opened: Event, clearing: Event) -> bool:
    """``clearing`` ends ``opened``: same battery, same values where both name a match field."""
    if clearing.battery != opened.battery:
        return False
    return all(
        opened.data[k] == clearing.data[k]
        for k in MATCH_FIELDS
        if k in opened.data and k in clearing.data
    )


@dataclass
class EventAlarms:
    """Warnings, alarms and faults among the events, as alarms-table rows (fed in order)."""

    topology: Topology
    _rows: dict[tuple[Any, ...], Alarm] = field(default_factory=dict)
    _open: dict[tuple[Any, ...], Event] = field(default_factory=dict)

    def feed(self, events: Iterable[Event]) -> None:
        for e in events:
            self._clear_by(e)
            row = row_of(e.kind)
            if row.severity > Severity.INFO:
                self._note(e, row.category, row.severity)

    def _note(self, e: Event, category: str, severity: Severity) -> None:
        key = (e.kind, e.battery, _match_key(e))
        old = self._rows.get(key)
        if old is None:
            name = self.topology.battery_name(e.battery)
            self._rows[key] = Alarm(e.t_s, name, e.kind, category, severity, e.message)
        else:
            self._rows[key] = replace(old, count=old.count + 1, cleared_t_s=None)
        if row_of(e.kind).cleared_by is not None:
            self._open[key] = e

    def _clear_by(self, e: Event) -> None:
        for key, opened in list(self._open.items()):
            if row_of(opened.kind).cleared_by == e.kind and _clears(opened, e):
                self._rows[key] = replace(self._rows[key], cleared_t_s=e.t_s)
                del self._open[key]

    def alarms(self) -> list[Alarm]:
        return list(self._rows.values())


# --------------------------------------------------------------------------- physics


@functools.cache
def _cell_v_min(cell: str) -> float:
    """Minimum voltage of a cell set (NaN when it cannot be loaded: the check is skipped)."""
    from packpilot.errors import PackPilotError
    from packpilot.model.cell import load_parameter_file, load_parameter_set

    try:
        if cell.endswith((".json", ".toml", ".npz")) or "/" in cell:
            from pathlib import Path

            return float(load_parameter_file(Path(cell)).v_min_v)
        return float(load_parameter_set(cell).v_min_v)
    except (PackPilotError, OSError, ValueError):
        return math.nan


def _charge_c(config: Mapping[str, Any]) -> float:
    """The lowest charge C-rate any row of the scenario's limits table (else the default
    table, the project's written-down datasheet figure) treats as too much."""
    raw = config.get("limits")
    try:
        limits = LimitsConfig.model_validate(raw) if isinstance(raw, Mapping) else LimitsConfig()
    except ValueError:
        limits = LimitsConfig()
    rates = [r.threshold for r in limits.rows if r.quantity == "chg_c_rate"]
    return min(rates, default=DEFAULT_CHARGE_C)


@dataclass(frozen=True)
class PhysicsLimits:
    """What the physics checks compare against, per string (trace battery)."""

    names: tuple[str, ...]
    traction: tuple[bool, ...]
    cell_v_min: tuple[float, ...]
    charge_c: float
    """Charge limit as a C-rate: limit (A) = charge_c × the battery's full capacity (Ah)."""

    @classmethod
    def of_config(cls, config: Mapping[str, Any] | None, names: Sequence[str]) -> PhysicsLimits:
        """From a run's recorded config (``cfg.model_dump(mode="json")``); without one the
        cells are unknown and the cell-voltage check is skipped."""
        cfg = config or {}
        pack = cfg.get("pack")
        pack = pack if isinstance(pack, Mapping) else {}
        by_name = {
            b.get("name"): b for b in pack.get("batteries") or () if isinstance(b, Mapping)
        }
        default_cell = str(pack.get("cell") or "uav_5ah")
        v_min = tuple(
            _cell_v_min(str((by_name.get(n) or {}).get("cell") or default_cell))
            if config is not None
            else math.nan
            for n in names
        )
        topo = Topology.of_config(cfg, names)
        traction = tuple(r != "aux" for r in topo.roles)
        return cls(tuple(names), traction, v_min, _charge_c(cfg))


@dataclass
class _Check:
    """One physics condition on one column (a string, or the pack): its alarm row and state."""

    kind: str
    category: str
    severity: Severity
    battery: str | None
    on: bool = False
    first_t_s: float = math.nan
    cleared_t_s: float | None = None
    count: int = 0
    worst: float = math.nan
    duration_s: float = 0.0
    limit: float = math.nan
    """The threshold at the first occurrence (the cross-charge limit in A)."""


class PhysicsWatch:
    """Over-discharge, cross-charge and load loss on the plant's trace, fed in chunks."""

    def __init__(self, limits: PhysicsLimits) -> None:
        self.limits = limits
        n = len(limits.names)
        self._v_min = np.array(limits.cell_v_min, dtype=np.float64)
        self._traction = np.array(limits.traction, dtype=np.bool_)
        self._checks: dict[tuple[str, int], _Check] = {}
        over, alarm, warning = "overdischarge", Severity.ALARM, Severity.WARNING
        for s, name in enumerate(limits.names):
            self._checks[("cell", s)] = _Check("OverDischarge", over, alarm, name)
            self._checks[("soc", s)] = _Check("OverDischarge", over, warning, name)
            self._checks[("cross", s)] = _Check("CrossCharge", "crosscharge", alarm, name)
            self._checks[("xdsg", s)] = _Check("CrossDischarge", "crosscharge", alarm, name)
        self._xdsg_run_s = np.zeros(n)
        """Per string: how long its cross-discharge has lasted at the end of the last chunk."""
        self._checks[("load", n)] = _Check("LoadLoss", "unsupplied", Severity.ALARM, None)
        self._last_t_s = math.nan
        self.fit: Any = None
        """A ``sim.fit_range.FitWatch`` fed the same chunks (set by :class:`RunWatch`)."""

    def feed_samples(self, samples: Sequence[StepSample]) -> None:
        """A chunk of the dashboard's samples."""
        if not samples:
            return
        self.feed(
            np.array([s.t_s for s in samples]),
            np.stack([s.battery for s in samples]),
            np.array([s.load_demand_a for s in samples]),
            np.array([s.load_a for s in samples]),
            np.array([s.charger_a for s in samples]),
        )

    def feed(self, t_s: F64, battery: F64, demand_a: F64, load_a: F64, charger_a: F64) -> None:
        """A chunk of the trace: ``battery`` shaped (steps, strings, BATTERY_CHANNELS)."""
        if t_s.size == 0:
            return
        if self.fit is not None:
            self.fit.feed(t_s, battery)
        dt = np.diff(t_s, prepend=t_s[0] if math.isnan(self._last_t_s) else self._last_t_s)
        dt = np.where(dt > 0, dt, np.median(dt) if dt.size > 1 else 0.0)
        with np.errstate(invalid="ignore"):
            cell_v = battery[:, :, _CH["min_cell_v"]]
            soc = battery[:, :, _CH["soc"]]
            limit_a = self.limits.charge_c * battery[:, :, _CH["full_ah"]]
            into_s, out_s = _battery_to_battery(
                battery[:, :, _CH["current_a"]], self._traction, charger_a
            )
            charging = (charger_a > CHARGER_IDLE_A)[:, None] & self._traction[None, :]
            short_a = demand_a - load_a
            lost = short_a > np.maximum(LOAD_LOSS_REL * demand_a, LOAD_LOSS_ABS_A)
        for s in range(len(self.limits.names)):
            self._column(("cell", s), t_s, dt, cell_v[:, s] < self._v_min[s], -cell_v[:, s])
            self._column(("soc", s), t_s, dt, soc[:, s] < 0.0, -soc[:, s])
            over = self._traction[s] & (into_s[:, s] > limit_a[:, s])
            self._column(("cross", s), t_s, dt, over, into_s[:, s], limit_a[:, s])
            raw = charging[:, s] & (out_s[:, s] > CROSS_DISCHARGE_A)
            run_s = _run_lengths(raw, dt, self._xdsg_run_s[s])
            self._xdsg_run_s[s] = run_s[-1]
            lasting = raw & (run_s > CROSS_DISCHARGE_S)
            self._column(("xdsg", s), t_s, dt, lasting, out_s[:, s])
        self._column(("load", len(self.limits.names)), t_s, dt, lost, short_a)
        self._last_t_s = float(t_s[-1])

    def _column(
        self, key: tuple[str, int], t_s: F64, dt: F64, cond: B1, badness: F64,
        limit: F64 | None = None,
    ) -> None:  # fmt: skip
        """Fold one condition's chunk into its row: episodes, first time, worst value."""
        c = self._checks[key]
        if cond.any():
            idx = np.flatnonzero(cond)
            if c.count == 0:
                c.first_t_s = float(t_s[idx[0]])
                c.limit = math.nan if limit is None else float(limit[idx[0]])
            worst = float(np.nanmax(badness[idx]))
            c.worst = worst if math.isnan(c.worst) else max(c.worst, worst)
            c.duration_s += float(dt[idx].sum())
        prev = np.concatenate(([c.on], cond[:-1]))
        rises = cond & ~prev
        falls = ~cond & prev
        c.count += int(rises.sum())
        if falls.any():
            c.cleared_t_s = float(t_s[np.flatnonzero(falls)[-1]])
        if cond[-1]:
            c.cleared_t_s = None
        c.on = bool(cond[-1])

    def alarms(self) -> list[Alarm]:
        out = []
        for (what, s), c in self._checks.items():
            if c.count == 0:
                continue
            out.append(
                Alarm(
                    c.first_t_s, c.battery, c.kind, c.category, c.severity,
                    self._cause(what, s, c), c.cleared_t_s, c.count, "physics",
                )
            )  # fmt: skip
        return out

    def _cause(self, what: str, s: int, c: _Check) -> str:
        lim = self.limits
        if what == "cell":
            return f"cell below its minimum {lim.cell_v_min[s]:g} V (lowest {-c.worst:.3f} V)"
        if what == "soc":
            return f"SOC below 0 % (lowest {-100.0 * c.worst:.1f} %)"
        if what == "cross":
            return (
                f"cross-charge {c.worst:.1f} A from another battery, above its charge limit"
                f" {c.limit:.1f} A ({lim.charge_c:g}C)"
            )
        if what == "xdsg":
            return (
                f"discharged up to {c.worst:.1f} A into other batteries while the dock charged"
                f" (more than {CROSS_DISCHARGE_A:g} A for more than {CROSS_DISCHARGE_S:g} s)"
            )
        return f"load short of its demand by up to {c.worst:.1f} A for {c.duration_s:.1f} s"


def _battery_to_battery(current_a: F64, traction: B1, charger_a: F64) -> tuple[F64, F64]:
    """(steps, strings) battery-to-battery current into and out of each traction battery,
    as :func:`packpilot.sim.metrics.cross_current` shares it (0 for the aux battery)."""
    cur = np.where(traction[None, :], current_a, 0.0)
    chg = np.maximum(-cur, 0.0)
    dsg = np.maximum(cur, 0.0)
    big_c = chg.sum(axis=1)
    big_d = dsg.sum(axis=1)
    flow = np.maximum(big_c - np.maximum(charger_a, 0.0), 0.0)
    into = chg * (flow / np.where(big_c > 0.0, big_c, 1.0))[:, None]
    out = dsg * (flow / np.where(big_d > 0.0, big_d, 1.0))[:, None]
    return into, out


def _run_lengths(cond: B1, dt: F64, carry_s: float) -> F64:
    """How long ``cond`` has held at each sample (s; 0 where it does not), continuing a run of
    ``carry_s`` from the previous chunk."""
    held = np.where(cond, dt, 0.0)
    total = np.cumsum(held)
    start = np.maximum.accumulate(np.where(cond, 0.0, total))
    run = total - start
    first_break = int(np.argmin(cond)) if not cond.all() else cond.size
    run[:first_break] += carry_s
    return np.where(cond, run, 0.0)


class BatchPhysics:
    """The physics checks of :class:`PhysicsWatch` for P packs stepped together (a campaign
    batch), folded step by step without a trace: per pack, which conditions were ever seen and
    which still stand after its last step. Same conditions and thresholds as
    :class:`PhysicsWatch`, so a campaign run's verdict matches the run's own (``simulate``)."""

    def __init__(self, limits: PhysicsLimits, n_packs: int, starts: NDArray[np.int64]) -> None:
        self.limits = limits
        self.starts = starts
        S = len(limits.names)
        self._v_min = np.array(limits.cell_v_min, dtype=np.float64)
        self._traction = np.array(limits.traction, dtype=np.bool_)
        shape = (n_packs, S)
        # seen / standing, per check: cell below minimum, SOC below 0, cross-charge, load loss
        self.seen = {k: np.zeros(shape, np.bool_) for k in ("cell", "soc", "cross", "xdsg")}
        self.on = {k: np.zeros(shape, np.bool_) for k in ("cell", "soc", "cross", "xdsg")}
        self._xdsg_run_s = np.zeros(shape)
        """Per pack and string: how long its cross-discharge has lasted (as PhysicsWatch)."""
        self.seen["load"] = np.zeros((n_packs, 1), np.bool_)
        self.on["load"] = np.zeros((n_packs, 1), np.bool_)

    def feed(
        self, live: B1, cell_v: F64, soc: F64, cap_ah: F64, string_a: F64, demand_a: F64,
        load_a: F64, charger_a: F64, dt_s: float,
    ) -> None:  # fmt: skip
        """One step of every pack (cells ``(P, C)``, strings ``(P, S)``); stopped packs
        (``live`` false) keep what they had."""
        st = self.starts
        with np.errstate(invalid="ignore", divide="ignore"):
            cell_min = np.minimum.reduceat(cell_v, st, axis=1)
            full = np.minimum.reduceat(cap_ah, st, axis=1)
            soc_s = np.minimum.reduceat(soc * cap_ah, st, axis=1) / full
            # the same battery-to-battery split and thresholds as PhysicsWatch.feed, with the
            # packs as rows: current into a battery above its charge limit whatever the charger
            # does; a battery feeding its siblings while the charger delivers, for long
            into_s, out_s = _battery_to_battery(string_a, self._traction, charger_a)
            cross = self._traction[None, :] & (into_s > self.limits.charge_c * full)
            charging = (charger_a > CHARGER_IDLE_A)[:, None] & self._traction[None, :]
            raw = charging & (out_s > CROSS_DISCHARGE_A) & live[:, None]
            self._xdsg_run_s = np.where(raw, self._xdsg_run_s + dt_s, 0.0)
            short = demand_a - load_a
            lost = short > np.maximum(LOAD_LOSS_REL * demand_a, LOAD_LOSS_ABS_A)
        now = {
            "cell": cell_min < self._v_min[None, :],
            "soc": soc_s < 0.0,
            "cross": cross,
            "xdsg": raw & (self._xdsg_run_s > CROSS_DISCHARGE_S),
            "load": lost[:, None],
        }
        for k, cond in now.items():
            cond = cond & live[:, None]
            self.seen[k] |= cond
            self.on[k] = np.where(live[:, None], cond, self.on[k])

    def of(self, p: int) -> tuple[list[tuple[str, Severity]], bool]:
        """Pack ``p``'s physics alarms as (category, severity), and whether it ended the run
        over-discharged (a cell below its minimum or a battery below 0 % SOC at its last step)."""
        out: list[tuple[str, Severity]] = []
        if self.seen["cell"][p].any():
            out.append(("overdischarge", Severity.ALARM))
        elif self.seen["soc"][p].any():
            out.append(("overdischarge", Severity.WARNING))
        if self.seen["cross"][p].any() or self.seen["xdsg"][p].any():
            out.append(("crosscharge", Severity.ALARM))
        if self.seen["load"][p].any():
            out.append(("unsupplied", Severity.ALARM))
        ended = bool(self.on["cell"][p].any() or self.on["soc"][p].any())
        return out, ended


def counted_verdict(
    event_counts: Mapping[str, int], physics: Iterable[tuple[str, Severity]]
) -> tuple[str, list[str]]:
    """A run's verdict word and alarm categories from its event counts by kind and its physics
    alarms: what a campaign row keeps of a run (no trace, no event times)."""
    worst = Severity.INFO
    cats: set[str] = set()
    for kind, n in event_counts.items():
        row = row_of(kind)
        if n and row.severity > Severity.INFO:
            worst = max(worst, row.severity)
            cats.add(row.category or "unknown")
    for cat, sev in physics:
        worst = max(worst, sev)
        cats.add(cat)
    return VERDICTS[worst], sorted(cats)


# --------------------------------------------------------------------------- a run


class RunWatch:
    """Events and physics of one run, streaming: what every view of a run asks for (the CLI's
    verdict, the report's, the live dashboard's): the events' alarms, the physics checks and,
    on a fitted cell set, the range it was fitted on (``OutsideFit``, #27 §4)."""

    def __init__(self, config: Mapping[str, Any] | None, names: Sequence[str]) -> None:
        self.events = EventAlarms(Topology.of_config(config, names))
        self.physics = PhysicsWatch(PhysicsLimits.of_config(config, names))
        self.fit = FitWatch(config, names)
        if self.fit.watch:
            self.physics.fit = self.fit

    def verdict(self) -> Verdict:
        return verdict_of([*self.events.alarms(), *self.physics.alarms(),
                           *_outside_fit(self.fit.found())])  # fmt: skip


def run_verdict(result: Result, config: Mapping[str, Any] | None) -> Verdict:
    """The verdict of a finished (or recorded) run."""
    watch = RunWatch(config, result.battery_names)
    tr = result.trace
    if len(tr.t_s):
        watch.physics.feed(tr.t_s, tr.battery, tr.load_demand_a, tr.load_a, tr.charger_a)
    watch.events.feed(result.events)
    return watch.verdict()


def _outside_fit(found: Mapping[str, Sequence[tuple[float, str]]]) -> list[Alarm]:
    """A warning per battery on a fitted cell set that the run took beyond the range the set
    was fitted on (:mod:`packpilot.sim.fit_range`): the answer there is extrapolated."""
    return [
        Alarm(
            t_s=rows[0][0], battery=name, kind="OutsideFit", category="extrapolated",
            severity=Severity.WARNING, source="physics", count=len(rows),
            cause="outside the fitted range: " + "; ".join(
                f"{what} (from {t:.1f} s)" for t, what in rows
            ),
        )
        for name, rows in found.items()
    ]  # fmt: skip


def fail_on(verdict: Verdict, categories: Iterable[str]) -> list[str]:
    """The listed categories this run's alarms fall in (``simulate --fail-on``)."""
    wanted = set(categories)
    return sorted(wanted & verdict.categories)


def parse_fail_on(text: str) -> list[str]:
    """``"trip,fault"`` -> ``["trip", "fault"]``; an unknown category is an error naming the
    allowed ones."""
    from packpilot.errors import ConfigError

    items = [x.strip() for x in text.split(",") if x.strip()]
    bad = [x for x in items if x not in CATEGORIES]
    if bad or not items:
        raise ConfigError(
            f"--fail-on {text!r}: unknown category {', '.join(bad) or '(none given)'};"
            f" choose from {', '.join(CATEGORIES)}"
        )
    return items


__all__ = [
    "CATEGORIES",
    "Alarm",
    "BatchPhysics",
    "EventAlarms",
    "PhysicsLimits",
    "PhysicsWatch",
    "RunWatch",
    "Verdict",
    "counted_verdict",
    "fail_on",
    "parse_fail_on",
    "run_verdict",
    "verdict_of",
]
