"""What every configuration section shares: strict models, number types, and the one error
formatter that turns a validation error into one line naming the file and the field."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any, TypeVar

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


def fmt_error(source: str, err: ValidationError, prefix: str = "") -> str:
    """``source: section.field: what is wrong (got value)`` on one line."""
    first = err.errors()[0]
    loc = ".".join(_printable(str(p)) for p in first["loc"] if not str(p).startswith("function-"))
    loc = f"{prefix}{loc}" if loc else prefix.rstrip(".") or "(top level)"
    msg = first["msg"]
    if first["type"] == "extra_forbidden":
        msg = "unknown key"
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
        raise ConfigError(fmt_error(source, err, prefix=f"{section}.")) from None


__all__ = [
    "Finite",
    "Fraction",
    "NonNegFloat",
    "PosFloat",
    "Strict",
    "fmt_error",
    "load_section_model",
]
