"""Reason tables: how an event code from the compiled core becomes an :class:`Event`.

A kernel emits ``(src, code, battery, numbers)``; it never builds a string. Each controller
declares a table with one :class:`Reason` per code: the event kind, a message template and the
data fields, each read from one slot of the numbers (labels such as a parameter name travel as
an index into one of the controller's label lists). Rendering happens outside the compiled code
and only when something was emitted, so a quiet step costs nothing, and every message a user
reads is written down in one table per controller instead of inside the rules.

Field kinds: ``f`` float, ``o`` float or ``None`` (NaN), ``i`` int, ``b`` bool, ``l:NAME``
the label ``labels[NAME][int(x)]`` (``None`` when the code is negative), ``m`` a set of
battery indices sent as a bit mask, shown as ``"0,2"``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from packpilot.contract.arrays import EventBuf
from packpilot.contract.bms import Event, EventValue


@dataclass(frozen=True, slots=True)
class Field:
    """One value of an event: its name, the slot it is read from, and its kind."""

    name: str
    slot: int
    kind: str = "f"
    in_data: bool = True
    """False: the value only fills the message template."""


@dataclass(frozen=True, slots=True)
class Reason:
    """One row of a reason table: what an event code means to a reader."""

    kind: str
    message: str
    """``str.format`` template over the fields (``{cutoff_v:g}``)."""
    fields: tuple[Field, ...] = ()


def fields(*specs: str) -> tuple[Field, ...]:
    """Shorthand: ``fields("param:l:params", "cutoff_v", "weight:i", "_src:l:src")`` gives
    slots 0, 1, 2, ... in order; a leading ``_`` on a name keeps it out of the data."""
    out = []
    for slot, spec in enumerate(specs):
        name, _, kind = spec.partition(":")
        in_data = not name.startswith("_")
        out.append(Field(name.lstrip("_"), slot, kind or "f", in_data))
    return tuple(out)


Labels = Mapping[str, Sequence[str]]


def value(x: float, kind: str, labels: Labels) -> EventValue:
    """Slot value ``x`` as a Python value of ``kind``."""
    if kind == "f":
        return float(x)
    if kind == "o":
        return None if math.isnan(x) else float(x)
    if kind == "i":
        return int(x)
    if kind == "b":
        return bool(x != 0.0)
    if kind == "m":
        bits = int(x)
        return ",".join(str(i) for i in range(bits.bit_length()) if bits >> i & 1)
    if kind.startswith("l:"):
        k = int(x) if math.isfinite(x) else -1
        return None if k < 0 else labels[kind[2:]][k]
    raise ValueError(f"unknown field kind {kind!r}")


BATTERY_FIELDS = frozenset({"battery", "source", "first", "second", "closed"})
"""Fields that hold a battery index (kinds ``i``/``o``) or a set of them (``m``): the message
shows the battery's configured name, the data keeps the index (what programs match on)."""


def _name(i: int, names: Sequence[str]) -> str:
    return names[i] if 0 <= i < len(names) else str(i)


def _named(v: EventValue, kind: str, names: Sequence[str]) -> EventValue:
    """A battery index (or ``"0,2"`` set) as the names a user knows the batteries by."""
    if kind == "m" and isinstance(v, str):
        return ",".join(_name(int(x), names) for x in v.split(",") if x)
    if isinstance(v, int) and not isinstance(v, bool):
        return _name(v, names)
    return v


def render_one(
    reason: Reason,
    t_s: float,
    battery: int,
    vals: Sequence[float],
    labels: Labels,
    names: Sequence[str] = (),
) -> Event:
    """One event; ``names`` (the pack's battery names, by index) fill the message's battery
    fields so it reads "battery B", as every table and chart names it."""
    data: dict[str, EventValue] = {}
    fmt: dict[str, Any] = {}
    for f in reason.fields:
        v = value(float(vals[f.slot]), f.kind, labels)
        fmt[f.name] = _named(v, f.kind, names) if names and f.name in BATTERY_FIELDS else v
        if f.in_data:
            data[f.name] = v
    return Event(
        t_s=float(t_s),
        kind=reason.kind,
        battery=None if battery < 0 else int(battery),
        message=reason.message.format(**fmt),
        data=data,
    )


@dataclass(frozen=True, slots=True)
class Source:
    """A controller's reason table and label lists, as the renderer needs them."""

    reasons: Sequence[Reason]
    labels: Labels


def render(
    buf: EventBuf, sources: Sequence[Source], n_packs: int, names: Sequence[str] = ()
) -> list[list[Event]]:
    """The events in ``buf``, per pack, in emission order."""
    out: list[list[Event]] = [[] for _ in range(n_packs)]
    for k in range(int(buf.n[0])):
        src = sources[int(buf.src[k])]
        reason = src.reasons[int(buf.code[k])]
        out[int(buf.pack[k])].append(
            render_one(reason, buf.t_s[k], int(buf.battery[k]), buf.val[k], src.labels, names)
        )
    return out


def reset(buf: EventBuf) -> None:
    """Empty the buffer for the next step."""
    buf.n[0] = 0


__all__ = ["Field", "Labels", "Reason", "Source", "fields", "render", "render_one", "reset"]
