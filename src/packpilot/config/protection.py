"""``[protection]``: condition-dependent discharge protection (US10868343B2;
``spec/discharge_protection.md``): the protection parameters, the N-dimensional range table
that selects one from the battery's status, and the options of the accumulation.

Validation only (pydantic); the compiled rules are in :mod:`packpilot.control.protection`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from itertools import product
from typing import Any, Literal

from pydantic import (
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_serializer,
    model_validator,
)

from packpilot.config.base import (
    DETECT_MAX_A,
    MAX_CURRENT_A,
    Strict,
    load_section_model,
)

MAX_T_MAX_S = 86_400.0
"""Longest t_max: a day at the cut-off is already 'never trips' (1e308 s overflowed in ms)."""
MIN_T_MAX_S = 0.001
"""Shortest t_max: one millisecond, the unit of the exact accumulation (``t_max_s = 1e-12``
rounded to 0 ms and divided by zero when the table was compiled)."""
MAX_PARAMETERS = 256
MAX_ROWS = 256
"""Most parameters and table rows a protection section may hold (the spec's grid has 9;
``packpilot calibrate protection`` writes one parameter per corner of its grid, 121 by default)."""
MAX_COVERAGE_CELLS = 200_000
"""Most (cell of the axis grid x row) pairs the exact coverage check may visit: the grid
grows as the product of the breakpoints of every axis; beyond this the check (and the table
an engineer can review) is too large, and the file is refused before the check runs."""
HYSTERESIS_MAX: Mapping[str, float] = {
    "current_a": 100.0,
    "temp_c": 20.0,
    "soh": 0.5,
    "resistance_ohm": 1.0,
    "cycle_count": 1000.0,
}
"""Widest hysteresis band per axis: a wider one keeps a row active over most of its axis'
physical range, so the protection never moves to a stricter parameter."""
MAX_TAU_S = 3600.0
"""Longest filter / prediction time constant: an hour already ignores every flight."""
MAX_M_MS = 2**53
"""Largest m = LCM(t_max in ms): the accumulated sums stay exact integers in float64."""
CUTOFF_MIN_V = 2.0
CUTOFF_MAX_V = 4.5
"""Allowed cut-off range: the values are cell-level Li-ion voltages (spec §3)."""

AXES: tuple[str, ...] = ("current_a", "temp_c", "soh", "resistance_ohm", "cycle_count")
"""Status parameters a table may use as axes, in their stable order; an axis' index here is
its code in the compiled rules (``control/protection/rules.py`` reads the value of each code:
current_a and temp_c as measured, soh = full_capacity_ah / nominal capacity, NaN without a
nominal capacity; resistance_ohm = the cell-level internal resistance estimated online from
current steps (unknown until the first step); cycle_count as the battery reports it)."""

_INTERVAL_RE = re.compile(r"^\s*([\[(])\s*([^,\s]+)\s*,\s*([^,\s]+)\s*([\])])\s*$")


def _fmt(x: float) -> str:
    if math.isinf(x):
        return "inf" if x > 0 else "-inf"
    return f"{x:g}"


class AxisRange(Strict):
    """An interval of one status parameter with explicit open/closed edges.

    In TOML write it in interval notation, e.g. ``"(15, 25]"`` (15 excluded, 25 included) or
    ``"[5, inf)"``; or as a table ``{lo = 15, hi = 25, lo_closed = false, hi_closed = true}``.
    Edges default to *open*, so an edge value is only covered when a row says so explicitly.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    lo: float = Field(default=-math.inf, description="Lower edge (-inf = unbounded).")
    hi: float = Field(default=math.inf, description="Upper edge (inf = unbounded).")
    lo_closed: bool = Field(default=False, description="True: the lower edge value is inside.")
    hi_closed: bool = Field(default=False, description="True: the upper edge value is inside.")

    @model_validator(mode="before")
    @classmethod
    def _parse_interval(cls, data: object) -> object:
        if not isinstance(data, str):
            return data
        m = _INTERVAL_RE.match(data)
        if m is None:
            raise ValueError(
                f"range {data!r}: expected interval notation such as '(15, 25]' or '[5, inf)'"
            )
        lo_b, lo_s, hi_s, hi_b = m.groups()
        try:
            lo, hi = float(lo_s), float(hi_s)
        except ValueError:
            raise ValueError(f"range {data!r}: edges must be numbers or inf/-inf") from None
        return {"lo": lo, "hi": hi, "lo_closed": lo_b == "[", "hi_closed": hi_b == "]"}

    @model_validator(mode="after")
    def _check(self) -> AxisRange:
        if math.isnan(self.lo) or math.isnan(self.hi):
            raise ValueError("range edges must not be NaN")
        if (self.lo_closed and math.isinf(self.lo)) or (self.hi_closed and math.isinf(self.hi)):
            raise ValueError(f"range {self}: an infinite edge must be open, use '(' or ')'")
        if self.lo > self.hi or (self.lo == self.hi and not (self.lo_closed and self.hi_closed)):
            raise ValueError(f"range {self} is empty")
        return self

    @model_serializer(mode="plain")
    def _as_interval(self) -> str:
        """Dumped in the interval notation a TOML file uses, exactly (``repr`` of each edge):
        it reads back as the same range, and JSON, which has no infinity, can hold it."""
        lo, hi = (repr(x) if math.isfinite(x) else _fmt(x) for x in (self.lo, self.hi))
        return f"{'[' if self.lo_closed else '('}{lo}, {hi}{']' if self.hi_closed else ')'}"

    def contains(self, x: float, band: float = 0.0) -> bool:
        """True when ``x`` lies in the range widened by ``band`` on both sides."""
        lo, hi = self.lo - band, self.hi + band
        if x < lo or (x == lo and not self.lo_closed):
            return False
        return not (x > hi or (x == hi and not self.hi_closed))

    def __str__(self) -> str:
        return (
            f"{'[' if self.lo_closed else '('}{_fmt(self.lo)}, "
            f"{_fmt(self.hi)}{']' if self.hi_closed else ')'}"
        )


_ALL = AxisRange()


class ProtectionParameter(Strict):
    """One discharge protection parameter: a cut-off voltage and how long it may be held."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(description="Identifier used by table rows and telemetry, e.g. 'P1'.")
    cutoff_v: float = Field(
        description=f"Cell-level cut-off voltage, {CUTOFF_MIN_V}..{CUTOFF_MAX_V} V."
    )
    t_max_s: float = Field(
        description="Longest sustainable time at or below the cut-off (> 0, whole milliseconds "
        "so that the LCM m and the weights are exact)."
    )

    @model_validator(mode="after")
    def _check(self) -> ProtectionParameter:
        who = f"parameter {self.name!r}"
        if not self.name.strip():
            raise ValueError("parameter name: must not be empty")
        if not (math.isfinite(self.cutoff_v) and CUTOFF_MIN_V <= self.cutoff_v <= CUTOFF_MAX_V):
            raise ValueError(
                f"{who}: cutoff_v must be between {CUTOFF_MIN_V} and {CUTOFF_MAX_V} V "
                f"(cell level), got {self.cutoff_v}"
            )
        if not (math.isfinite(self.t_max_s) and MIN_T_MAX_S <= self.t_max_s <= MAX_T_MAX_S):
            raise ValueError(
                f"{who}: t_max_s must be a positive duration of {MIN_T_MAX_S:g} to "
                f"{MAX_T_MAX_S:g} s, "
                f"got {self.t_max_s}"
            )
        ms = self.t_max_s * 1000.0
        if abs(ms - round(ms)) > 1e-6 * max(1.0, ms):
            raise ValueError(
                f"{who}: t_max_s must be a whole number of milliseconds, got {self.t_max_s}"
            )
        return self

    @property
    def t_max_ms(self) -> int:
        return round(self.t_max_s * 1000.0)


class TableRow(Strict):
    """Status-parameter ranges (one per axis; a missing axis = any value) -> a parameter."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    param: str = Field(description="Name of the protection parameter this row selects.")
    ranges: dict[str, AxisRange] = Field(
        default_factory=dict,
        description="Axis name (current_a, temp_c, soh) -> interval, e.g. '(15, 25]'.",
    )


def _row(param: str, current_a: str, temp_c: str) -> TableRow:
    return TableRow.model_validate(
        {"param": param, "ranges": {"current_a": current_a, "temp_c": temp_c}}
    )


DEFAULT_PARAMETERS: tuple[ProtectionParameter, ...] = (
    ProtectionParameter(name="P1", cutoff_v=2.8, t_max_s=15.0),
    ProtectionParameter(name="P2", cutoff_v=3.0, t_max_s=10.0),
    ProtectionParameter(name="P3", cutoff_v=3.2, t_max_s=5.0),
)

_I_LOW, _I_MID, _I_HIGH = "(-inf, 15]", "(15, 25]", "(25, inf)"
_T_COLD, _T_COOL, _T_WARM = "(-inf, 5)", "[5, 15)", "[15, inf)"
DEFAULT_TABLE: tuple[TableRow, ...] = (
    # spec §4 grid, boundaries per §10.1: I <= 15 low, 15 < I <= 25 mid, I > 25 high;
    # T < 5 cold, 5 <= T < 15 cool, T >= 15 warm.
    _row("P1", _I_LOW, _T_COLD),
    _row("P2", _I_LOW, _T_COOL),
    _row("P3", _I_LOW, _T_WARM),
    _row("P1", _I_MID, _T_COLD),
    _row("P2", _I_MID, _T_COOL),
    _row("P2", _I_MID, _T_WARM),
    _row("P1", _I_HIGH, _T_COLD),
    _row("P1", _I_HIGH, _T_COOL),
    _row("P1", _I_HIGH, _T_WARM),
)


@dataclass(frozen=True)
class _Atom:
    """An elementary piece of one axis between breakpoints: a point or an open interval."""

    rep: float
    text: str


def _axis_atoms(axis: str, rows: Sequence[TableRow]) -> list[_Atom]:
    pts = sorted(
        {
            x
            for r in rows
            if axis in r.ranges
            for x in (r.ranges[axis].lo, r.ranges[axis].hi)
            if math.isfinite(x)
        }
    )
    if not pts:
        return [_Atom(0.0, f"{axis} any")]
    atoms = [_Atom(pts[0] - 1.0, f"{axis} in (-inf, {_fmt(pts[0])})")]
    for a, b in zip(pts, [*pts[1:], math.inf], strict=True):
        atoms.append(_Atom(a, f"{axis} = {_fmt(a)}"))
        rep = a + 1.0 if math.isinf(b) else (a + b) / 2.0
        atoms.append(_Atom(rep, f"{axis} in ({_fmt(a)}, {_fmt(b)})"))
    return atoms


def check_coverage(rows: Sequence[TableRow], axes: Sequence[str]) -> None:
    """Raise ValueError unless every point of the status space is covered by exactly one row.

    Exact: between consecutive breakpoints every row either contains a whole open interval or
    none of it, so checking one representative per breakpoint and per open interval suffices.
    """
    per_axis = [_axis_atoms(a, rows) for a in axes]
    for combo in product(*per_axis):
        hits = [
            k
            for k, r in enumerate(rows)
            if all(
                r.ranges.get(a, _ALL).contains(at.rep) for a, at in zip(axes, combo, strict=True)
            )
        ]
        where = " and ".join(at.text for at in combo)
        if not hits:
            raise ValueError(f"table has a gap: no row covers {where}")
        if len(hits) > 1:
            a, b = hits[0], hits[1]
            raise ValueError(
                f"table rows overlap: table[{a}] ({rows[a].param}) and table[{b}] "
                f"({rows[b].param}) both cover {where}"
            )


class ProtectionConfig(Strict):
    """Condition-dependent discharge protection (spec/discharge_protection.md)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    parameters: tuple[ProtectionParameter, ...] = Field(
        default=DEFAULT_PARAMETERS,
        max_length=MAX_PARAMETERS,
        description="Protection parameters (name, cutoff_v, t_max_s). Only those referenced by "
        "the table enter m = LCM(t_max).",
    )
    table: tuple[TableRow, ...] = Field(
        default=DEFAULT_TABLE,
        max_length=MAX_ROWS,
        description="Range rows -> parameter; must cover the status space exactly once.",
    )
    voltage_comparison: Literal["<=", "<"] = Field(
        default="<=", description="Accumulate when min cell voltage <= (or <) the cut-off."
    )
    trip_comparison: Literal[">=", ">"] = Field(
        default=">=", description="Trip when the weighted sum >= (or >) m (spec §10.2)."
    )
    discharge_threshold_a: float = Field(
        default=0.5, description="Current above which the battery counts as discharging (A)."
    )
    charge_threshold_a: float = Field(
        default=0.5, description="Charging is current below minus this value (A)."
    )
    charge_detect_s: float = Field(
        default=10.0, description="Charging this long starts a new discharge cycle (s)."
    )
    reset_on_recovery: bool = Field(
        default=False,
        description="Reset the sum when the voltage rises above the cut-off (spec §10.4: off).",
    )
    reset_on_reinsert: bool = Field(
        default=True,
        description="A battery re-inserted after being absent starts a new discharge cycle "
        "(it may have been charged elsewhere; a relay battery cannot charge in the pack).",
    )
    hysteresis: dict[str, float] = Field(
        default_factory=dict,
        description="Per-axis band, e.g. {current_a = 0.5, temp_c = 0.5}: keep the active row "
        "until the value leaves it by more than the band. Empty = off.",
    )
    filter_tau_s: dict[str, float] = Field(
        default_factory=dict,
        description="Per-axis first-order low-pass time constant (s) applied before the "
        "lookup. Empty = off.",
    )
    warning_share: float = Field(
        default=0.5,
        description="Share of the allowance (sum of t_k / t_max_k) at which a "
        "ProtectionWarning tells the platform a trip is coming; once per episode, re-armed "
        "when the share falls back below it (a new discharge cycle). In (0, 1].",
    )
    resistance_step_a: float = Field(
        default=2.0,
        description="Smallest change of the battery current between two ticks that updates the "
        "internal-resistance estimate (R = -dV_cell / dI; axis resistance_ohm), A.",
    )
    resistance_gain: float = Field(
        default=0.25,
        description="Weight of a new step's resistance in the estimate (exponential average), "
        "in (0, 1]; 1 = the last step alone.",
    )
    predict_tau_s: float = Field(
        default=5.0,
        description="Time constant (s) of the low-pass filter on the check voltage's slope "
        "that predicts when the voltage reaches the active cut-off (status "
        "protection_time_to_trip_s).",
    )

    @field_validator("discharge_threshold_a", "charge_threshold_a")
    @classmethod
    def _detection(cls, v: float, info: ValidationInfo) -> float:
        name = info.field_name
        if not (math.isfinite(v) and 0.0 <= v <= DETECT_MAX_A):
            raise ValueError(f"{name} must be a current of 0 to {DETECT_MAX_A:g} A, got {v}")
        return v

    @field_validator("charge_detect_s")
    @classmethod
    def _non_negative(cls, v: float, info: ValidationInfo) -> float:
        name = info.field_name
        if not (math.isfinite(v) and 0.0 <= v <= MAX_TAU_S):
            raise ValueError(f"{name} must be a time of 0 to {MAX_TAU_S:g} s, got {v}")
        return v

    @field_validator("warning_share")
    @classmethod
    def _check_share(cls, v: float) -> float:
        if not (math.isfinite(v) and 0.0 < v <= 1.0):
            raise ValueError(f"warning_share must be in (0, 1], got {v}")
        return v

    @field_validator("resistance_step_a")
    @classmethod
    def _check_step(cls, v: float) -> float:
        if not (math.isfinite(v) and 0.0 < v <= MAX_CURRENT_A):
            raise ValueError(
                f"resistance_step_a must be a current > 0 and <= {MAX_CURRENT_A:g} A, got {v}"
            )
        return v

    @field_validator("resistance_gain")
    @classmethod
    def _check_gain(cls, v: float) -> float:
        if not (math.isfinite(v) and 0.0 < v <= 1.0):
            raise ValueError(f"resistance_gain must be in (0, 1], got {v}")
        return v

    @field_validator("predict_tau_s")
    @classmethod
    def _check_tau(cls, v: float) -> float:
        if not (math.isfinite(v) and 0.0 < v <= MAX_TAU_S):
            raise ValueError(f"predict_tau_s must be > 0 and <= {MAX_TAU_S:g} s, got {v}")
        return v

    @field_validator("hysteresis")
    @classmethod
    def _check_hysteresis(cls, v: dict[str, float]) -> dict[str, float]:
        for axis, band in v.items():
            if axis not in AXES:
                raise ValueError(f"hysteresis.{axis}: unknown axis; known: {', '.join(AXES)}")
            most = HYSTERESIS_MAX[axis]
            if not (math.isfinite(band) and 0.0 <= band <= most):
                raise ValueError(f"hysteresis.{axis} must be within 0..{most:g}, got {band}")
        return v

    @field_validator("filter_tau_s")
    @classmethod
    def _check_filter(cls, v: dict[str, float]) -> dict[str, float]:
        for axis, tau in v.items():
            if axis not in AXES:
                raise ValueError(f"filter_tau_s.{axis}: unknown axis; known: {', '.join(AXES)}")
            if not (math.isfinite(tau) and 0.0 < tau <= MAX_TAU_S):
                raise ValueError(
                    f"filter_tau_s.{axis} must be > 0 and <= {MAX_TAU_S:g} s, got {tau}"
                )
        return v

    @model_validator(mode="after")
    def _check_table(self) -> ProtectionConfig:
        names = [p.name for p in self.parameters]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"parameters: duplicate name(s) {', '.join(dup)}")
        if not self.table:
            raise ValueError("table: must have at least one row")
        for k, row in enumerate(self.table):
            if row.param not in names:
                raise ValueError(
                    f"table[{k}].param: unknown parameter {row.param!r}; "
                    f"defined: {', '.join(names)}"
                )
            for axis in row.ranges:
                if axis not in AXES:
                    raise ValueError(
                        f"table[{k}].ranges.{axis}: unknown axis; known: {', '.join(AXES)}"
                    )
        self._check_grid()
        check_coverage(self.table, self.axes)
        self._check_lcm()
        return self

    def _check_grid(self) -> None:
        """Refuse a table whose exact coverage check would visit more than
        :data:`MAX_COVERAGE_CELLS` (grid cell, row) pairs, before it starts."""
        cells = len(self.table)
        for axis in self.axes:
            cells *= len(_axis_atoms(axis, self.table))
            if cells > MAX_COVERAGE_CELLS:
                raise ValueError(
                    f"table: {len(self.table)} rows over axes {', '.join(self.axes)} make a "
                    f"grid too large to check (more than {MAX_COVERAGE_CELLS:,} cell-row pairs)"
                )

    def _check_lcm(self) -> None:
        """m = LCM of the used t_max in ms must stay an exact integer of the accumulation."""
        used = {r.param for r in self.table}
        m_ms = math.lcm(*(p.t_max_ms for p in self.parameters if p.name in used))
        if m_ms > MAX_M_MS:
            raise ValueError(
                f"parameters: m = LCM of t_max = {m_ms / 1000:.4g} s is too large (at most "
                f"{MAX_M_MS / 1000:.4g} s); use t_max_s values with common factors"
            )

    @property
    def axes(self) -> tuple[str, ...]:
        """Axes used by the table, in a stable order."""
        used = {a for r in self.table for a in r.ranges}
        return tuple(a for a in AXES if a in used)

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<protection>") -> ProtectionConfig:
        return load_section_model(cls, data, "protection", source)


__all__ = [
    "AXES",
    "CUTOFF_MAX_V",
    "CUTOFF_MIN_V",
    "DEFAULT_PARAMETERS",
    "DEFAULT_TABLE",
    "AxisRange",
    "ProtectionConfig",
    "ProtectionParameter",
    "TableRow",
    "check_coverage",
]
