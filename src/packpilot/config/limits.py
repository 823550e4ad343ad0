"""``[limits]``: absolute safety limits (warn / derate / trip rows) and the current-derating
tables.

The tiers follow foxBMS's safe-operating-area layers: a *warn* row is the maximum operating
limit (MOL, an event only), a *derate* row the recommended safety limit (RSL, the published
current limit of that path drops to ``derate_fraction``), a *trip* row the maximum safety limit
(MSL, the path is opened and stays open until its reset condition). Every row is data
(:class:`LimitRow`), so a pack's limits are a table in the TOML file, not code. The rules that
evaluate the table are :mod:`packpilot.control.limits`.

Defaults are for a Li-ion NMC / LiPo pouch cell (4.2 V full); see ``docs/safety.md``.
"""

from __future__ import annotations

import bisect
import math
import re
from collections.abc import Mapping, Sequence
from itertools import pairwise
from typing import Any, Literal, Protocol

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import CELL_V_MAX_V, DETECT_DELAY_MAX_S, Strict, load_section_model

MAX_DEBOUNCE = 100
"""Most consecutive violating samples a row may need: 10 s at the shortest usual period
(0.1 s); more keeps a trip from ever firing on a noisy signal."""
MAX_ROWS = 256
MAX_CURVE_POINTS = 64
"""Most limit rows and derating-table points (the defaults use 24 and 6)."""
CURVE_X_RANGE: Mapping[str, tuple[float, float]] = {
    "cell_v": (0.0, CELL_V_MAX_V),
    "temp_c": (-100.0, 300.0),
    "soc": (0.0, 1.0),
}
"""The physical range of each derating table's input (as :data:`QUANTITY_RANGE`)."""
CONTEXT_C_MAX = 10.0
"""Largest C-rate below which a battery still counts as resting (not charging): beyond it a
charge at 10 C would escape the charging-only rows."""

Quantity = Literal[
    "cell_v_max", "cell_v_min", "chg_c_rate", "dsg_c_rate", "temp_max_c", "temp_min_c"
]
Tier = Literal["warn", "derate", "trip"]
Path = Literal["charge", "discharge"]
Context = Literal["always", "charging", "discharging"]

TIER_RANK: Mapping[str, int] = {"warn": 0, "derate": 1, "trip": 2}
QUANTITY_DIRECTION: Mapping[str, Literal["above", "below"]] = {
    "cell_v_max": "above",
    "cell_v_min": "below",
    "chg_c_rate": "above",
    "dsg_c_rate": "above",
    "temp_max_c": "above",
    "temp_min_c": "below",
}
"""The only meaningful direction of each quantity (a 'max cell voltage below' row is a typo)."""

QUANTITY_RANGE: Mapping[str, tuple[float, float]] = {
    "cell_v_max": (0.0, CELL_V_MAX_V),
    "cell_v_min": (0.0, CELL_V_MAX_V),
    "chg_c_rate": (0.0, 1000.0),
    "dsg_c_rate": (0.0, 1000.0),
    "temp_max_c": (-100.0, 300.0),
    "temp_min_c": (-100.0, 300.0),
}
"""Where a threshold or reset of each quantity can physically lie (a cell_v trip at 100 V can
never fire: it is a typo, most likely a battery voltage)."""

QUANTITIES: tuple[str, ...] = tuple(QUANTITY_DIRECTION)
TIERS: tuple[str, ...] = ("warn", "derate", "trip")
"""In rank order (``TIER_RANK``)."""
PATHS: tuple[str, ...] = ("charge", "discharge")
CONTEXTS: tuple[str, ...] = ("always", "charging", "discharging")

_NAME_RE = re.compile(r"^[a-z][a-z0-9_]*$")


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


class Reading(Protocol):
    """What the derating tables read of one battery (a ``BatteryMeasurement``)."""

    @property
    def max_cell_v(self) -> float: ...
    @property
    def min_cell_v(self) -> float: ...
    @property
    def temp_c(self) -> float: ...
    @property
    def min_temp_c(self) -> float: ...
    @property
    def soc(self) -> float: ...


# --------------------------------------------------------------------------------- the table


class LimitRow(Strict):
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
        lo, hi = QUANTITY_RANGE[self.quantity]
        for name in ("threshold", "reset"):
            if not lo <= getattr(self, name) <= hi:
                raise ValueError(
                    f"{who}: {name} {getattr(self, name)} is outside {lo:g}..{hi:g} "
                    f"(the physical range of {self.quantity})"
                )
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
        if not 1 <= self.debounce <= MAX_DEBOUNCE:
            raise ValueError(
                f"{who}: debounce must be >= 1 and <= {MAX_DEBOUNCE} consecutive samples, "
                f"got {self.debounce}"
            )
        if not (_finite(self.delay_s) and 0.0 <= self.delay_s <= DETECT_DELAY_MAX_S):
            raise ValueError(
                f"{who}: delay_s must be a finite time >= 0 and <= {DETECT_DELAY_MAX_S:g} s, "
                f"got {self.delay_s}"
            )
        if self.latch_s is not None and not (_finite(self.latch_s) and self.latch_s >= 0.0):
            raise ValueError(
                f"{who}: latch_s must be a finite time >= 0 s or omitted for a manual reset, "
                f"got {self.latch_s}"
            )
        return self


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


class CurveTable(Strict):
    """A piecewise-linear C-rate limit over one input, held constant beyond its end points."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    x: tuple[float, ...] = Field(
        max_length=MAX_CURVE_POINTS, description="Input points, strictly increasing."
    )
    c_rate: tuple[float, ...] = Field(
        max_length=MAX_CURVE_POINTS,
        description="Allowed current at each point, C (0..1000, the C-rate range of a limit).",
    )

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
        most = QUANTITY_RANGE["chg_c_rate"][1]
        if not all(_finite(v) and 0.0 <= v <= most for v in self.c_rate):
            raise ValueError(
                f"c_rate: values must be finite and >= 0 and <= {most:g} C, got {self.c_rate}"
            )
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


class DeratingConfig(Strict):
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

    @model_validator(mode="after")
    def _x_in_range(self) -> DeratingConfig:
        """Each table's points lie in its input's physical range (a point at 1e300 V is a
        typo that stretches the taper over every voltage a cell can have)."""
        for name in type(self).model_fields:
            lo, hi = CURVE_X_RANGE[name.rsplit("_vs_", 1)[1]]
            xs = getattr(self, name).x
            if not lo <= min(xs) <= max(xs) <= hi:
                raise ValueError(f"{name}.x: points must lie within {lo:g}..{hi:g}, got {xs}")
        return self

    # The scalar form of the tables, for tests and tools; the BMS evaluates them compiled
    # (``packpilot.control.limits.rules``), checked equal by the equivalence test.

    def charge_c(self, bm: Reading) -> float:
        return min(
            self.charge_vs_cell_v.at(bm.max_cell_v),
            _temp_lookup(self.charge_vs_temp_c, bm),
            self.charge_vs_soc.at(bm.soc),
        )

    def discharge_c(self, bm: Reading) -> float:
        return min(
            self.discharge_vs_cell_v.at(bm.min_cell_v),
            _temp_lookup(self.discharge_vs_temp_c, bm),
            self.discharge_vs_soc.at(bm.soc),
        )


def _temp_lookup(table: CurveTable, bm: Reading) -> float:
    """Hottest and coldest cell both limit (a table is low at both ends)."""
    hot = table.at(bm.temp_c)
    return min(hot, table.at(bm.min_temp_c)) if _finite(bm.min_temp_c) else hot


# ---------------------------------------------------------------------------------- config


class LimitsConfig(Strict):
    """Absolute safety limits (warn / derate / trip rows) and the current-derating tables."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rows: tuple[LimitRow, ...] = Field(
        default=DEFAULT_ROWS,
        min_length=1,
        max_length=MAX_ROWS,
        description="The limit table; see docs/safety.md for the defaults.",
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
        if not (_finite(self.context_current_c) and 0.0 <= self.context_current_c <= CONTEXT_C_MAX):
            raise ValueError(
                f"context_current_c must be within 0..{CONTEXT_C_MAX:g} C, "
                f"got {self.context_current_c}"
            )
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


__all__ = [
    "CONTEXTS",
    "DEFAULT_ROWS",
    "PATHS",
    "QUANTITIES",
    "QUANTITY_DIRECTION",
    "TIERS",
    "TIER_RANK",
    "Context",
    "CurveTable",
    "DeratingConfig",
    "LimitRow",
    "LimitsConfig",
    "Path",
    "Quantity",
    "Reading",
    "Tier",
]
