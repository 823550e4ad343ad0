"""What every configuration section shares: strict models, number types, and the one error
formatter that turns a validation error into one line naming the file and the field."""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping
from typing import Annotated, Any, TypeVar, get_args, get_origin

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
)

from packpilot.errors import ConfigError


def plus_zero(x: float) -> float:
    """``-0.0`` read as ``0.0``: it passes ``>= 0`` but flips the sign of whatever it scales
    (a spread of -0.0 made NumPy's ``uniform(high, low)`` refuse the draw)."""
    return x + 0.0


Finite = Annotated[float, Field(allow_inf_nan=False)]
PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False), AfterValidator(plus_zero)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False), AfterValidator(plus_zero)]

MAX_TIME_S = 1e9
"""Longest time any setting may name (~32 years): the longest run (10^8 periods of at most
10 s). Larger values are typos, and a time of 1e308 s overflows once it becomes milliseconds."""
CELL_V_MAX_V = 5.0
"""No cell chemistry PackPilot models rests above 5 V: a per-cell voltage beyond it is absurd."""
CELL_V_FULL_MIN_V = 2.0
"""Lowest full-charge voltage of any cell chemistry (LTO charges to 2.8 V): a saturation or
cell voltage limit below it means no cell could ever be charged (``v_sat_v = 1e-12``)."""
MAX_CURRENT_A = 1e5
"""Largest current a load, a charger, a converter or a limit may name (100 kA)."""
MAX_VOLTAGE_V = 1e4
"""Largest pack-level voltage a setting may name (10 kV)."""
DETECT_MAX_A = 20.0
"""Largest dead band of a current-detection rule (diode conduction, reverse cut, rest,
discharge / charge detection): it must sit above sensor noise and offset (0.5 % of a 1 kA
sensor is 5 A) and below the currents it tells apart; a larger one switches the rule off in
every pack PackPilot models (``i_rev = 1e300`` was accepted)."""
SPREAD_MAX_V = 100.0
"""Largest voltage *difference* threshold between batteries, or margin above a battery voltage:
the full-to-empty swing of the highest battery a scenario can hold (64 series groups x 1.7 V
= 109 V) rounded down. A larger spread is never reached, so the rule it guards never acts."""
GROUP_DV_MAX_V = 1.0
"""Largest voltage-difference threshold between series groups (cell level): more than half of
a Li-ion cell's 1.7 V full-to-empty swing (``dv_set_v = 9.2e18`` was accepted)."""
DETECT_DELAY_MAX_S = 60.0
"""Longest delay before a plausibility or limit violation counts: a 2 C charge moves a cell
~3 % SOC per minute, so a longer delay lets a fault act unseen (a delay of 1e9 s switches
the check off)."""
OHM_MAX = 10.0
"""Largest battery or cell resistance a setting may name (a coin cell's 10 Ohm)."""
MAX_LIST_ITEMS = 1024
"""Longest array (and largest table) anywhere in a scenario file, checked on the parsed TOML
before validation: the schema's longest list (a protection table) needs a few hundred rows;
a 10^6-entry list took 34 s and 5.4 GB before a traceback."""

Seconds = Annotated[
    float, Field(ge=0, le=MAX_TIME_S, allow_inf_nan=False), AfterValidator(plus_zero)
]
"""A time or delay, 0 s to :data:`MAX_TIME_S`."""
Period = Annotated[float, Field(gt=0, le=MAX_TIME_S, allow_inf_nan=False)]
"""A duration that must pass (a timeout, a window): > 0 s, at most :data:`MAX_TIME_S`."""


MAX_SHOWN_CHARS = 80
"""Longest input value an error message quotes: a 1 MB battery name must not become a 1 MB
"one-line" error."""


def _mentions_bool(tp: Any) -> bool:
    return tp is bool or any(_mentions_bool(a) for a in get_args(tp))


def _holds_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return True
    return isinstance(value, list | tuple) and any(_holds_bool(v) for v in value)


def _longest(value: Any) -> float:
    """The largest finite magnitude of the numbers in ``value`` (also in lists and tables)."""
    if isinstance(value, int | float) and not isinstance(value, bool):
        x = abs(float(value))
        return x if math.isfinite(x) else 0.0  # inf / NaN: each field's own check says
    if isinstance(value, dict):
        value = list(value.values())
    if isinstance(value, list | tuple):
        return max((_longest(v) for v in value), default=0.0)
    return 0.0


class Strict(BaseModel):
    """Unknown keys are errors; a validated config never changes; ``true`` is not a number.

    Pydantic's lax mode reads ``dt_s = true`` as 1.0 and ``thermal_nodes = true`` as 1. One
    check here, for every field of every section, refuses a boolean (also inside a list) unless
    the field's type itself names ``bool`` -- rather than a strict type per field, which would
    also refuse a TOML array for a tuple. By the same rule every field named ``*_s`` or ``t_*``
    (sequencing's ``t_on``) is a time and holds at most :data:`MAX_TIME_S`
    (``fault_hold_s = 1e308`` was accepted)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_as_number(cls, value: Any, info: ValidationInfo) -> Any:
        field = cls.model_fields.get(info.field_name or "")
        if field is not None and _holds_bool(value) and not _mentions_bool(field.annotation):
            raise ValueError("must not be a boolean")
        name = info.field_name or ""
        if (name.endswith("_s") or name.startswith("t_")) and _longest(value) > MAX_TIME_S:
            raise ValueError(f"a time of at most {MAX_TIME_S:g} s is expected")
        return value


M = TypeVar("M", bound=BaseModel)


def _printable(text: str) -> str:
    """A key as typed, with control / separator characters escaped: a key such as ``"\\x1e"``
    must not split the one-line error message (``str.splitlines`` breaks on it)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The models a field's annotation can hold (through ``X | None``, ``list[X]``,
    ``dict[str, X]``, ``Annotated[X, ...]``)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    origin = get_origin(annotation)
    if origin is None:
        return []
    args = get_args(annotation)
    if origin is Annotated:
        args = args[:1]
    elif origin is dict:
        args = args[1:]
    return [m for a in args for m in _models_in(a)]


def _keys_at(model: type[BaseModel], loc: tuple[int | str, ...]) -> set[str]:
    """The keys allowed where ``loc`` points (its last part is the key itself)."""
    models = [model]
    for part in loc[:-1]:
        if not isinstance(part, str):
            continue  # a list index: the element is the same model
        fields = [cur.model_fields[part] for cur in models if part in cur.model_fields]
        nxt = [m for f in fields for m in _models_in(f.annotation)]
        models = nxt or models  # a validator's or a union member's tag: stay where we are
    return {k for m in models for k in m.model_fields}


def did_you_mean(model: type[BaseModel] | None, loc: tuple[int | str, ...]) -> str:
    """`` (did you mean 'cutoff_v'?)`` for an unknown key close to an allowed one, else ``""``:
    a typo in a long TOML file should point at the fix, not only at the mistake."""
    if model is None or not loc or not isinstance(loc[-1], str):
        return ""
    close = difflib.get_close_matches(loc[-1], sorted(_keys_at(model, loc)), n=1, cutoff=0.6)
    return f" (did you mean {close[0]!r}?)" if close else ""


def fmt_error(
    source: str, err: ValidationError, prefix: str = "", model: type[BaseModel] | None = None
) -> str:
    """``source: section.field: what is wrong (got value)`` on one line; with ``model`` (what
    was validated), an unknown key close to an allowed one adds ``(did you mean 'x'?)``."""
    first = err.errors()[0]
    loc = ".".join(_printable(str(p)) for p in first["loc"] if not str(p).startswith("function-"))
    loc = f"{prefix}{loc}" if loc else prefix.rstrip(".") or "(top level)"
    msg = first["msg"]
    if first["type"] == "extra_forbidden":
        msg = "unknown key" + did_you_mean(model, tuple(first["loc"]))
    elif first["type"] == "value_error":
        msg = msg.removeprefix("Value error, ")  # pydantic's prefix on a validator's message
    inp = first.get("input")
    shown = (
        ""
        if isinstance(inp, dict | list) or first["type"] == "missing" or "(got " in msg
        else f" (got {_clip(repr(inp))})"
    )
    more = len(err.errors()) - 1
    tail = f" [+{more} more error(s)]" if more else ""
    return f"{source}: {_clip(loc)}: {_clip(msg, 4 * MAX_SHOWN_CHARS)}{shown}{tail}"


def _clip(text: str, limit: int = MAX_SHOWN_CHARS) -> str:
    """``text`` shortened to ``limit`` characters (an ellipsis and the length say it was)."""
    if len(text) <= limit:
        return text
    return f"{text[: limit - 1]}… ({len(text):,} chars)"


def oversized(node: Any, path: str = "") -> tuple[str, int] | None:
    """The first array or table in parsed TOML longer than :data:`MAX_LIST_ITEMS`, as
    ``(dotted path, length)``, or None. Runs before pydantic, which would validate every
    element of a 10^6-entry list (and some validators are quadratic in it) before its length
    check fired."""
    if isinstance(node, dict | list) and len(node) > MAX_LIST_ITEMS:
        return path, len(node)
    items = (
        node.items()
        if isinstance(node, dict)
        else enumerate(node)
        if isinstance(node, list)
        else ()
    )
    for key, child in items:
        if isinstance(child, dict | list):
            hit = oversized(
                child, f"{path}.{_printable(str(key))}" if path else _printable(str(key))
            )
            if hit is not None:
                return hit
    return None


def load_section_model(
    cls: type[M], data: Mapping[str, Any] | None, section: str, source: str
) -> M:
    """Validate ``data`` as ``cls``; a bad value becomes a one-line :class:`ConfigError`
    naming the source, the section and the field (``limits.rows.3``)."""
    big = oversized(dict(data or {}))
    if big is not None:
        where, n = big
        loc = f"{section}.{where}" if where else section
        raise ConfigError(f"{source}: {loc}: at most {MAX_LIST_ITEMS:,} entries, got {n:,}")
    try:
        return cls.model_validate(dict(data or {}))
    except ValidationError as err:
        raise ConfigError(fmt_error(source, err, prefix=f"{section}.", model=cls)) from None


__all__ = [
    "CELL_V_FULL_MIN_V",
    "CELL_V_MAX_V",
    "DETECT_DELAY_MAX_S",
    "DETECT_MAX_A",
    "GROUP_DV_MAX_V",
    "MAX_CURRENT_A",
    "MAX_LIST_ITEMS",
    "MAX_SHOWN_CHARS",
    "MAX_TIME_S",
    "MAX_VOLTAGE_V",
    "OHM_MAX",
    "SPREAD_MAX_V",
    "Finite",
    "Fraction",
    "NonNegFloat",
    "Period",
    "PosFloat",
    "Seconds",
    "Strict",
    "did_you_mean",
    "fmt_error",
    "load_section_model",
    "oversized",
    "plus_zero",
]
