"""Absolute safety limits: warn / derate / trip tiers with debounce, delay, hysteresis and latch.

The tiers follow foxBMS's safe-operating-area layers: a *warn* row is the maximum operating
limit (MOL, an event only), a *derate* row the recommended safety limit (RSL, the published
current limit of that path drops to ``derate_fraction``), a *trip* row the maximum safety limit
(MSL, the path is opened and stays open until its reset condition). Every row is data
(:class:`LimitRow`), so a pack's limits are a table in the TOML file, not code.

A row is violated while its quantity is strictly beyond ``threshold``. It becomes active once
``debounce`` consecutive samples violated it *and* the violation then persisted ``delay_s``
more seconds (the debounce rejects single-sample glitches, the delay sets the time scale).
It clears when the quantity is back at or past ``reset`` (hysteresis) and it has been active
for at least ``latch_s``; ``latch_s = None`` means only :meth:`LimitsController.reset_trips`
(an operator or supervisor decision) clears it. A non-finite value neither counts nor clears
(sensor plausibility is :mod:`packpilot.control.plausibility`'s job); this layer holds its state.

The published current limits (charge and discharge, per battery and for the pack) are the
minimum of three piecewise-linear C-rate tables over cell voltage, temperature and SOC, scaled
by the battery's capacity. For parallel batteries the pack limit is N x the smallest limit of
the N batteries that can conduct in that direction (current shares roughly equally, so the
weakest battery sets everyone's share).

Defaults are for a Li-ion NMC / LiPo pouch cell (4.2 V full); see ``docs/safety.md``.
"""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from packpilot.config.base import load_section_model
from packpilot.control.types import (
    CHARGER_OFF,
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
    PackInfo,
    SwitchKind,
)

Quantity = Literal[
    "cell_v_max", "cell_v_min", "chg_c_rate", "dsg_c_rate", "temp_max_c", "temp_min_c"
]
Tier = Literal["warn", "derate", "trip"]
Path = Literal["charge", "discharge"]
Context = Literal["always", "charging", "discharging"]

TIER_RANK: Mapping[str, int] = {"warn": 0, "derate": 1, "trip": 2}
TIER_EVENT: Mapping[str, str] = {
    "warn": "LimitWarning",
    "derate": "LimitDerate",
    "trip": "LimitTripped",
}
QUANTITY_DIRECTION: Mapping[str, Literal["above", "below"]] = {
    "cell_v_max": "above",
    "cell_v_min": "below",
    "chg_c_rate": "above",
    "dsg_c_rate": "above",
    "temp_max_c": "above",
    "temp_min_c": "below",
}
"""The only meaningful direction of each quantity (a 'max cell voltage below' row is a typo)."""

EPS = 1e-9
"""Time comparisons tolerate float round-off of summed ``dt_s`` (10 x 0.1 s = 0.9999999)."""

_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")

M = TypeVar("M", bound=BaseModel)


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


# --------------------------------------------------------------------------------- the table


class LimitRow(BaseModel):
    """One tier of one limit: when it fires, what it opens, and how it clears."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    limit: str = Field(
        description="Name of the limit this tier belongs to (e.g. 'over_voltage'); rows with the "
        "same name form a ladder and must share quantity, direction, path and context."
    )
    quantity: Quantity = Field(
        description="cell_v_max / cell_v_min (V), chg_c_rate / dsg_c_rate (charge / discharge "
        "current divided by the battery capacity, 1/h), temp_max_c / temp_min_c (degC)."
    )
    direction: Literal["above", "below"] = Field(
        description="Violated when the quantity is strictly above / below the threshold."
    )
    path: Path = Field(
        description="Switch path a trip opens and current limit a derate reduces: charge or "
        "discharge. A relay opens for either (it cannot block one direction)."
    )
    when: Context = Field(
        default="always",
        description="Evaluated always, or only while charging (docked or charge current) / "
        "discharging; outside its context the row counts nothing and may clear.",
    )
    tier: Tier = Field(description="warn (MOL, event), derate (RSL), trip (MSL, opens path).")
    threshold: float = Field(description="Limit value in the quantity's unit.")
    reset: float = Field(
        description="Hysteresis: the row clears only when the quantity is back at or past this "
        "value, which must lie on the safe side of the threshold."
    )
    debounce: int = Field(default=1, description="Consecutive violating samples needed (>= 1).")
    delay_s: float = Field(
        default=0.0, description="Seconds the violation must persist after the debounce (>= 0)."
    )
    latch_s: float | None = Field(
        default=0.0,
        description="Minimum time the row stays active (>= 0); None = cleared only by an "
        "explicit reset_trips() once the quantity is past the reset value.",
    )

    @model_validator(mode="after")
    def _check(self) -> LimitRow:
        who = f"{self.limit}/{self.tier}"
        if not _NAME_RE.match(self.limit):
            raise ValueError(
                f"limit {self.limit!r}: use lower-case letters, digits and '_' (it names a "
                "status channel)"
            )
        want = QUANTITY_DIRECTION[self.quantity]
        if self.direction != want:
            raise ValueError(f"{who}: quantity {self.quantity} is only limited {want!r}")
        if not _finite(self.threshold):
            raise ValueError(f"{who}: threshold must be a finite number, got {self.threshold}")
        if not _finite(self.reset):
            raise ValueError(f"{who}: reset must be a finite number, got {self.reset}")
        if self.direction == "above" and not self.reset < self.threshold:
            raise ValueError(
                f"{who}: reset {self.reset} must be below threshold {self.threshold} "
                "(the safe side of an upper limit)"
            )
        if self.direction == "below" and not self.reset > self.threshold:
            raise ValueError(
                f"{who}: reset {self.reset} must be above threshold {self.threshold} "
                "(the safe side of a lower limit)"
            )
        if self.debounce < 1:
            raise ValueError(
                f"{who}: debounce must be >= 1 consecutive samples, got {self.debounce}"
            )
        if not (_finite(self.delay_s) and self.delay_s >= 0.0):
            raise ValueError(f"{who}: delay_s must be a finite time >= 0 s, got {self.delay_s}")
        if self.latch_s is not None and not (_finite(self.latch_s) and self.latch_s >= 0.0):
            raise ValueError(
                f"{who}: latch_s must be a finite time >= 0 s or omitted for a manual reset, "
                f"got {self.latch_s}"
            )
        return self

    def violated(self, value: float) -> bool:
        return value > self.threshold if self.direction == "above" else value < self.threshold

    def cleared(self, value: float) -> bool:
        return value <= self.reset if self.direction == "above" else value >= self.reset


def _r(
    limit: str,
    quantity: Quantity,
    path: Path,
    tier: Tier,
    threshold: float,
    reset: float,
    debounce: int,
    delay_s: float,
    latch_s: float | None = 0.0,
    when: Context = "always",
) -> LimitRow:
    return LimitRow(
        limit=limit,
        quantity=quantity,
        direction=QUANTITY_DIRECTION[quantity],
        path=path,
        when=when,
        tier=tier,
        threshold=threshold,
        reset=reset,
        debounce=debounce,
        delay_s=delay_s,
        latch_s=latch_s,
    )


DEFAULT_ROWS: tuple[LimitRow, ...] = (
    # Cell over-voltage (NMC/LiPo charge to 4.20 V; > 4.25 V risks Li plating / oxidation).
    _r("over_voltage", "cell_v_max", "charge", "warn", 4.20, 4.15, 3, 0.0),
    _r("over_voltage", "cell_v_max", "charge", "derate", 4.22, 4.17, 3, 0.0),
    _r("over_voltage", "cell_v_max", "charge", "trip", 4.25, 4.15, 3, 0.0, latch_s=None),
    # Cell under-voltage (under load; below 2.7 V copper dissolution starts on rest).
    _r("under_voltage", "cell_v_min", "discharge", "warn", 2.9, 3.1, 3, 0.5),
    _r("under_voltage", "cell_v_min", "discharge", "derate", 2.8, 3.0, 3, 1.0),
    _r("under_voltage", "cell_v_min", "discharge", "trip", 2.7, 3.0, 3, 2.0, latch_s=None),
    # Over-current, in C (charge 2C continuous for a UAV pouch cell, discharge 15C).
    _r("over_current_charge", "chg_c_rate", "charge", "warn", 2.0, 1.8, 3, 2.0),
    _r("over_current_charge", "chg_c_rate", "charge", "derate", 2.5, 2.0, 3, 1.0),
    _r("over_current_charge", "chg_c_rate", "charge", "trip", 3.0, 1.0, 3, 0.5, latch_s=30.0),
    _r("over_current_discharge", "dsg_c_rate", "discharge", "warn", 15.0, 12.0, 3, 2.0),
    _r("over_current_discharge", "dsg_c_rate", "discharge", "derate", 18.0, 15.0, 3, 1.0),
    _r("over_current_discharge", "dsg_c_rate", "discharge", "trip", 20.0, 10.0, 3, 0.5, 30.0),
    # Over-temperature: charging is limited tighter (45 degC) than discharging (60 degC).
    _r("over_temp_charge", "temp_max_c", "charge", "warn", 40.0, 38.0, 3, 1.0, when="charging"),
    _r("over_temp_charge", "temp_max_c", "charge", "derate", 43.0, 40.0, 3, 1.0, when="charging"),
    _r("over_temp_charge", "temp_max_c", "charge", "trip", 45.0, 40.0, 3, 1.0, 60.0, "charging"),
    _r("over_temp_discharge", "temp_max_c", "discharge", "warn", 50.0, 47.0, 3, 1.0),
    _r("over_temp_discharge", "temp_max_c", "discharge", "derate", 55.0, 52.0, 3, 1.0),
    _r("over_temp_discharge", "temp_max_c", "discharge", "trip", 60.0, 50.0, 3, 1.0, 60.0),
    # Under-temperature: no charging below 0 degC (lithium plating); discharge down to -20 degC.
    _r("under_temp_charge", "temp_min_c", "charge", "warn", 5.0, 7.0, 3, 1.0, when="charging"),
    _r("under_temp_charge", "temp_min_c", "charge", "derate", 2.0, 5.0, 3, 1.0, when="charging"),
    _r("under_temp_charge", "temp_min_c", "charge", "trip", 0.0, 3.0, 3, 1.0, 60.0, "charging"),
    _r("under_temp_discharge", "temp_min_c", "discharge", "warn", -15.0, -13.0, 3, 1.0),
    _r("under_temp_discharge", "temp_min_c", "discharge", "derate", -18.0, -15.0, 3, 1.0),
    _r("under_temp_discharge", "temp_min_c", "discharge", "trip", -20.0, -17.0, 3, 1.0, 60.0),
)


# ------------------------------------------------------------------------------ derating


class CurveTable(BaseModel):
    """A piecewise-linear C-rate limit over one input, held constant beyond its end points."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    x: tuple[float, ...] = Field(description="Input points, strictly increasing.")
    c_rate: tuple[float, ...] = Field(description="Allowed current at each point, C (>= 0).")

    @model_validator(mode="after")
    def _check(self) -> CurveTable:
        if not self.x:
            raise ValueError("x: needs at least one point")
        if len(self.x) != len(self.c_rate):
            raise ValueError(
                f"x has {len(self.x)} points but c_rate has {len(self.c_rate)}; give one each"
            )
        if not all(_finite(v) for v in self.x):
            raise ValueError(f"x: values must be finite numbers, got {self.x}")
        if any(b <= a for a, b in pairwise(self.x)):
            raise ValueError(f"x: must be strictly increasing, got {self.x}")
        if not all(_finite(v) and v >= 0.0 for v in self.c_rate):
            raise ValueError(f"c_rate: values must be finite and >= 0, got {self.c_rate}")
        return self

    def at(self, x: float) -> float:
        """Interpolated limit; a non-finite input gets the table's smallest (safest) value."""
        if not _finite(x):
            return min(self.c_rate)
        xs, ys = self.x, self.c_rate
        if x <= xs[0]:
            return ys[0]
        if x >= xs[-1]:
            return ys[-1]
        k = bisect.bisect_right(xs, x)
        x0, x1, y0, y1 = xs[k - 1], xs[k], ys[k - 1], ys[k]
        return y0 + (y1 - y0) * (x - x0) / (x1 - x0)


def _curve(points: Sequence[tuple[float, float]]) -> CurveTable:
    return CurveTable(x=tuple(p[0] for p in points), c_rate=tuple(p[1] for p in points))


class DeratingConfig(BaseModel):
    """Current-limit tables in C (multiplied by the battery capacity). Defaults: NMC/LiPo UAV cell
    with 2C continuous charge and 15C continuous discharge at room temperature."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    charge_vs_cell_v: CurveTable = Field(
        default=_curve([(2.5, 0.1), (3.0, 0.1), (3.2, 2.0), (4.15, 2.0), (4.22, 0.2), (4.25, 0.0)]),
        description="Charge limit over the highest cell voltage: trickle below 3.0 V, taper "
        "above 4.15 V.",
    )
    charge_vs_temp_c: CurveTable = Field(
        default=_curve(
            [(0.0, 0.0), (2.0, 0.2), (10.0, 1.0), (15.0, 2.0), (40.0, 2.0), (45.0, 0.0)]
        ),
        description="Charge limit over cell temperature (hottest and coldest both apply).",
    )
    charge_vs_soc: CurveTable = Field(
        default=_curve([(0.0, 2.0), (0.85, 2.0), (1.0, 0.5)]),
        description="Charge limit over SOC (0..1).",
    )
    discharge_vs_cell_v: CurveTable = Field(
        default=_curve([(2.7, 0.0), (3.0, 5.0), (3.3, 15.0)]),
        description="Discharge limit over the lowest cell voltage.",
    )
    discharge_vs_temp_c: CurveTable = Field(
        default=_curve(
            [(-20.0, 0.0), (-10.0, 2.0), (0.0, 8.0), (10.0, 15.0), (50.0, 15.0), (60.0, 0.0)]
        ),
        description="Discharge limit over cell temperature (hottest and coldest both apply).",
    )
    discharge_vs_soc: CurveTable = Field(
        default=_curve([(0.0, 3.0), (0.1, 10.0), (0.2, 15.0), (1.0, 15.0)]),
        description="Discharge limit over SOC (0..1).",
    )

    def charge_c(self, bm: BatteryMeasurement) -> float:
        return min(
            self.charge_vs_cell_v.at(bm.max_cell_v),
            _temp_lookup(self.charge_vs_temp_c, bm),
            self.charge_vs_soc.at(bm.soc),
        )

    def discharge_c(self, bm: BatteryMeasurement) -> float:
        return min(
            self.discharge_vs_cell_v.at(bm.min_cell_v),
            _temp_lookup(self.discharge_vs_temp_c, bm),
            self.discharge_vs_soc.at(bm.soc),
        )


def _temp_lookup(table: CurveTable, bm: BatteryMeasurement) -> float:
    """Hottest and coldest cell both limit (a table is low at both ends)."""
    hot = table.at(bm.temp_c)
    return min(hot, table.at(bm.min_temp_c)) if _finite(bm.min_temp_c) else hot


# ---------------------------------------------------------------------------------- config


class LimitsConfig(BaseModel):
    """Absolute safety limits (warn / derate / trip rows) and the current-derating tables."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rows: tuple[LimitRow, ...] = Field(
        default=DEFAULT_ROWS, description="The limit table; see docs/safety.md for the defaults."
    )
    derating: DeratingConfig = Field(default_factory=DeratingConfig)
    derate_fraction: float = Field(
        default=0.5,
        description="Share of the table limit a path keeps while one of its derate rows is "
        "active (0..1).",
    )
    context_current_c: float = Field(
        default=0.05,
        description="A battery counts as charging (discharging) when its current is beyond this "
        "C-rate in that direction; a docked pack always counts as charging.",
    )

    @model_validator(mode="after")
    def _check(self) -> LimitsConfig:
        if not (_finite(self.derate_fraction) and 0.0 <= self.derate_fraction <= 1.0):
            raise ValueError(f"derate_fraction must be within 0..1, got {self.derate_fraction}")
        if not (_finite(self.context_current_c) and self.context_current_c >= 0.0):
            raise ValueError(f"context_current_c must be >= 0, got {self.context_current_c}")
        ladders: dict[str, list[int]] = {}
        for k, row in enumerate(self.rows):
            ladders.setdefault(row.limit, []).append(k)
        for name, idx in ladders.items():
            first = self.rows[idx[0]]
            seen: dict[str, int] = {}
            for k in idx:
                row = self.rows[k]
                who = f"rows[{k}] ({name}/{row.tier})"
                for attr in ("quantity", "direction", "path", "when"):
                    if getattr(row, attr) != getattr(first, attr):
                        raise ValueError(
                            f"{who}: {attr} {getattr(row, attr)!r} differs from rows[{idx[0]}] "
                            f"({getattr(first, attr)!r}); one limit has one {attr}"
                        )
                if row.tier in seen:
                    raise ValueError(f"{who}: tier {row.tier!r} repeats rows[{seen[row.tier]}]")
                seen[row.tier] = k
            ordered = sorted(seen.items(), key=lambda kv: TIER_RANK[kv[0]])
            for (t_lo, k_lo), (t_hi, k_hi) in pairwise(ordered):
                lo, hi = self.rows[k_lo].threshold, self.rows[k_hi].threshold
                ok = hi > lo if first.direction == "above" else hi < lo
                if not ok:
                    rel = "above" if first.direction == "above" else "below"
                    raise ValueError(
                        f"rows[{k_hi}] ({name}/{t_hi}): threshold {hi} must lie {rel} the "
                        f"{t_lo} threshold {lo} of rows[{k_lo}] (warn before derate before trip)"
                    )
        return self

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<limits>") -> LimitsConfig:
        """Validate a ``[limits]`` table; errors are a one-line ConfigError naming the row."""
        return load_section_model(cls, data, "limits", source)


# ------------------------------------------------------------------------------ controller


@dataclass(slots=True)
class _RowState:
    count: int = 0
    held_s: float = 0.0
    active: bool = False
    active_s: float = 0.0
    clear_ok: bool = False
    value: float = math.nan


def capacity_ah(pack: PackInfo, i: int, bm: BatteryMeasurement | None) -> float:
    """Nominal capacity from the pack facts, else the battery's reported full capacity, else NaN."""
    if i < len(pack.capacity_ah) and _finite(pack.capacity_ah[i]) and pack.capacity_ah[i] > 0:
        return float(pack.capacity_ah[i])
    if bm is not None and _finite(bm.full_capacity_ah) and bm.full_capacity_ah > 0:
        return float(bm.full_capacity_ah)
    return math.nan


def conducts(pack: PackInfo, i: int, bm: BatteryMeasurement, path: Path) -> bool:
    """Switch feedback says the battery can carry current in ``path``'s direction.

    A relay conducts both ways only when closed; a MOSFET pair conducts discharge while its
    discharge FET is on (the charge FET's body diode passes it) and charge while its charge FET
    is on.
    """
    sw = bm.switch
    kind = pack.switch_kind[i] if i < len(pack.switch_kind) else SwitchKind.RELAY
    if kind == SwitchKind.RELAY:
        return sw.relay_closed
    return sw.chg_on if path == "charge" else sw.dsg_on


def _num(x: float) -> float | None:
    return float(x) if _finite(x) else None


class LimitsController:
    """Evaluates every limit row for every battery each tick; see the module docstring.

    Commands: ``chg_on=False`` while a charge-path trip is active, ``dsg_on=False`` while a
    discharge-path trip is active, otherwise ``None`` (no opinion: after a trip clears, the path
    closes again only when a method controller commands it, e.g. after voltage matching), and
    ``charger=CHARGER_OFF`` while docked with any charge-path trip active.
    """

    def __init__(self, config: LimitsConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.rows = config.rows
        self.ladders: dict[str, tuple[int, ...]] = {}
        for k, row in enumerate(self.rows):
            self.ladders[row.limit] = (*self.ladders.get(row.limit, ()), k)
        n = pack.n_batteries
        self._state = [[_RowState() for _ in self.rows] for _ in range(n)]
        self._pending: list[Event] = []
        self._limit_chg_a: list[float] = [0.0] * n
        self._limit_dsg_a: list[float] = [0.0] * n
        self._pack_chg_a = 0.0
        self._pack_dsg_a = 0.0
        self._t_s = math.nan

    # -- queries --------------------------------------------------------------------------

    def is_active(self, battery: int, row: int) -> bool:
        return self._state[battery][row].active

    def active_tier(self, battery: int, limit: str) -> str:
        """Highest active tier of one limit for one battery: 'ok', 'warn', 'derate' or 'trip'."""
        best = "ok"
        for k in self.ladders.get(limit, ()):
            tier = self.rows[k].tier
            if self._state[battery][k].active and (
                best == "ok" or TIER_RANK[tier] > TIER_RANK[best]
            ):
                best = tier
        return best

    def tripped(self, battery: int, path: Path) -> bool:
        return any(
            st.active and row.tier == "trip" and row.path == path
            for row, st in zip(self.rows, self._state[battery], strict=True)
        )

    @property
    def limit_chg_a(self) -> tuple[float, ...]:
        """Per-battery charge current limit (A) from the last tick."""
        return tuple(self._limit_chg_a)

    @property
    def limit_dsg_a(self) -> tuple[float, ...]:
        return tuple(self._limit_dsg_a)

    @property
    def pack_limit_chg_a(self) -> float:
        """N x the smallest charge limit of the N batteries that can take charge now (A)."""
        return self._pack_chg_a

    @property
    def pack_limit_dsg_a(self) -> float:
        return self._pack_dsg_a

    def reset_trips(self, battery: int | None = None) -> int:
        """Explicit reset: clear active rows (any latch) whose quantity is past its reset value.

        Returns how many rows cleared; their ``LimitReset`` events come with the next tick.
        """
        n = 0
        targets = range(len(self._state)) if battery is None else (battery,)
        for i in targets:
            if not 0 <= i < len(self._state):
                continue
            for k, st in enumerate(self._state[i]):
                if st.active and st.clear_ok:
                    self._deactivate(
                        i, k, st, math.nan, manual=True, events=self._pending, t_s=self._t_s
                    )
                    n += 1
        return n

    # -- the tick -------------------------------------------------------------------------

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        dt = float(dt_s) if _finite(dt_s) and dt_s > 0.0 else 0.0
        self._t_s = meas.t_s
        events, self._pending = self._pending, []
        fresh: list[Event] = []
        n = self.pack.n_batteries
        docked = bool(meas.docked)
        bms: list[BatteryMeasurement | None] = [
            meas.batteries[i] if i < len(meas.batteries) else None for i in range(n)
        ]
        for i in range(n):
            self._step_battery(i, bms[i], docked, meas.t_s, dt, fresh)
        self._update_limits(bms)
        for ev in fresh:
            data = dict(ev.data)
            data["pack_limit_chg_a"] = _num(self._pack_chg_a)
            data["pack_limit_dsg_a"] = _num(self._pack_dsg_a)
            events.append(Event(ev.t_s, ev.kind, ev.battery, ev.message, data))
        chg: list[bool | None] = [False if self.tripped(i, "charge") else None for i in range(n)]
        dsg: list[bool | None] = [False if self.tripped(i, "discharge") else None for i in range(n)]
        charger = CHARGER_OFF if docked and any(c is False for c in chg) else None
        status: dict[str, Sequence[float | int | str | bool | None]] = {
            f"lim_{name}": [self.active_tier(i, name) for i in range(n)] for name in self.ladders
        }
        status["limit_chg_a"] = list(self._limit_chg_a)
        status["limit_dsg_a"] = list(self._limit_dsg_a)
        status["pack_limit_chg_a"] = [self._pack_chg_a] * n
        status["pack_limit_dsg_a"] = [self._pack_dsg_a] * n
        return ControlOutput(
            commands=Commands(chg_on=tuple(chg), dsg_on=tuple(dsg), charger=charger),
            events=tuple(events),
            status=status,
        )

    # -- internals ------------------------------------------------------------------------

    def _values(self, i: int, bm: BatteryMeasurement | None) -> dict[str, float]:
        if bm is None or not bm.present:
            return dict.fromkeys(QUANTITY_DIRECTION, math.nan)
        cap = capacity_ah(self.pack, i, bm)
        cur = bm.current_a
        coldest = bm.min_temp_c if _finite(bm.min_temp_c) else bm.temp_c
        return {
            "cell_v_max": bm.max_cell_v,
            "cell_v_min": bm.min_cell_v,
            "chg_c_rate": max(0.0, -cur) / cap if _finite(cur) else math.nan,
            "dsg_c_rate": max(0.0, cur) / cap if _finite(cur) else math.nan,
            "temp_max_c": bm.temp_c,
            "temp_min_c": coldest,
        }

    def _contexts(self, i: int, bm: BatteryMeasurement | None, docked: bool) -> dict[str, bool]:
        if bm is None or not bm.present:
            return {"always": True, "charging": docked, "discharging": False}
        cap = capacity_ah(self.pack, i, bm)
        band = self.config.context_current_c * cap if _finite(cap) else 0.0
        cur = bm.current_a
        return {
            "always": True,
            "charging": docked or (_finite(cur) and cur < -band),
            "discharging": _finite(cur) and cur > band and not docked,
        }

    def _step_battery(
        self,
        i: int,
        bm: BatteryMeasurement | None,
        docked: bool,
        t_s: float,
        dt: float,
        events: list[Event],
    ) -> None:
        values = self._values(i, bm)
        ctx = self._contexts(i, bm, docked)
        for k, row in enumerate(self.rows):
            st = self._state[i][k]
            v = values[row.quantity]
            st.value = v
            violating = False
            if not ctx[row.when]:
                st.count, st.held_s = 0, 0.0
                st.clear_ok = True
            elif not _finite(v):
                st.clear_ok = False  # unknown: hold counters and the active state
            else:
                violating = row.violated(v)
                st.clear_ok = row.cleared(v)
                if violating:
                    if st.count >= row.debounce:
                        st.held_s += dt
                    else:
                        st.count += 1
                        st.held_s = 0.0
                else:
                    st.count, st.held_s = 0, 0.0
            if st.active:
                st.active_s += dt
                latch = row.latch_s
                if st.clear_ok and latch is not None and st.active_s >= latch - EPS:
                    self._deactivate(i, k, st, v, manual=False, events=events, t_s=t_s)
            elif violating and st.count >= row.debounce and st.held_s >= row.delay_s - EPS:
                st.active, st.active_s = True, 0.0
                events.append(
                    Event(
                        t_s=t_s,
                        kind=TIER_EVENT[row.tier],
                        battery=i,
                        message=f"{row.limit} {row.tier}: {row.quantity} {v:g} "
                        f"{'>' if row.direction == 'above' else '<'} {row.threshold:g}",
                        data=self._row_data(k, v),
                    )
                )

    def _row_data(self, k: int, value: float) -> dict[str, float | int | str | bool | None]:
        row = self.rows[k]
        return {
            "row": k,
            "limit": row.limit,
            "tier": row.tier,
            "quantity": row.quantity,
            "path": row.path,
            "value": _num(value),
            "threshold": row.threshold,
            "reset": row.reset,
        }

    def _deactivate(
        self,
        i: int,
        k: int,
        st: _RowState,
        value: float,
        *,
        manual: bool,
        events: list[Event],
        t_s: float = math.nan,
    ) -> None:
        st.active, st.active_s, st.count, st.held_s = False, 0.0, 0, 0.0
        row = self.rows[k]
        data = self._row_data(k, st.value if not _finite(value) else value)
        data["manual"] = manual
        events.append(
            Event(
                t_s=t_s,
                kind="LimitReset",
                battery=i,
                message=f"{row.limit} {row.tier} cleared" + (" (explicit reset)" if manual else ""),
                data=data,
            )
        )

    def _update_limits(self, bms: Sequence[BatteryMeasurement | None]) -> None:
        der = self.config.derating
        frac = self.config.derate_fraction
        n = self.pack.n_batteries
        chg_ok: list[int] = []
        dsg_ok: list[int] = []
        for i in range(n):
            bm = bms[i]
            if bm is None or not bm.present:
                self._limit_chg_a[i] = self._limit_dsg_a[i] = 0.0
                continue
            cap = capacity_ah(self.pack, i, bm)
            lim = {"charge": der.charge_c(bm) * cap, "discharge": der.discharge_c(bm) * cap}
            for path in ("charge", "discharge"):
                tiers = {
                    row.tier
                    for row, st in zip(self.rows, self._state[i], strict=True)
                    if st.active and row.path == path
                }
                if "trip" in tiers:
                    lim[path] = 0.0
                elif "derate" in tiers:
                    lim[path] *= frac  # once per path, however many derate rows are active
            self._limit_chg_a[i] = lim["charge"]
            self._limit_dsg_a[i] = lim["discharge"]
            if not self.tripped(i, "charge") and conducts(self.pack, i, bm, "charge"):
                chg_ok.append(i)
            if not self.tripped(i, "discharge") and conducts(self.pack, i, bm, "discharge"):
                dsg_ok.append(i)
        self._pack_chg_a = _pack_limit([self._limit_chg_a[i] for i in chg_ok])
        self._pack_dsg_a = _pack_limit([self._limit_dsg_a[i] for i in dsg_ok])


def _pack_limit(limits: Sequence[float]) -> float:
    """N x the smallest of N parallel batteries' limits (NaN if any of them is unknown)."""
    if not limits:
        return 0.0
    if not all(_finite(x) for x in limits):
        return math.nan
    return len(limits) * min(limits)


__all__ = [
    "DEFAULT_ROWS",
    "CurveTable",
    "DeratingConfig",
    "LimitRow",
    "LimitsConfig",
    "LimitsController",
    "capacity_ah",
    "conducts",
    "load_section_model",
]
