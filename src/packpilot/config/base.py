"""What every configuration section shares: strict models, number types, and the one error
formatter that turns a validation error into one line naming the file and the field."""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from typing import Annotated, Any, TypeVar, get_args, get_origin

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from packpilot.errors import ConfigError

Finite = Annotated[float, Field(allow_inf_nan=False)]
PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]


class Strict(BaseModel):
    """Unknown keys are errors; a validated config never changes."""

    model_config = ConfigDict(extra="forbid", frozen=True)


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
        else f" (got {inp!r})"
    )
    more = len(err.errors()) - 1
    tail = f" [+{more} more error(s)]" if more else ""
    return f"{source}: {loc}: {msg}{shown}{tail}"


def load_section_model(
    cls: type[M], data: Mapping[str, Any] | None, section: str, source: str
) -> M:
    """Validate ``data`` as ``cls``; a bad value becomes a one-line :class:`ConfigError`
    naming the source, the section and the field (``limits.rows.3``)."""
    try:
        return cls.model_validate(dict(data or {}))
    except ValidationError as err:
        raise ConfigError(fmt_error(source, err, prefix=f"{section}.", model=cls)) from None


__all__ = [
    "Finite",
    "Fraction",
    "NonNegFloat",
    "PosFloat",
    "Strict",
    "did_you_mean",
    "fmt_error",
    "load_section_model",
]
