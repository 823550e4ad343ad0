"""``packpilot replay … --config FILE``: a method's section from a scenario TOML, or from the
JSON a replay printed (``--json``), so a replay's own output feeds the next replay.

A replay's summary states the values the method derives from its parameters (protection's
``m_s`` and ``weights``); a section that carries them (copied from that output) is accepted
when they agree with what the parameters give, and refused naming the field when they do not —
they can be checked, never set.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel

from packpilot.config import load_section
from packpilot.config.base import load_section_model
from packpilot.config.scenario import SECTIONS, read_toml
from packpilot.errors import ConfigError


def _protection_derived(cfg: BaseModel) -> dict[str, Any]:
    from packpilot.control.protection import ProtectionController
    from packpilot.replay.protection import ONE_CELL

    ctl = ProtectionController(cfg, ONE_CELL)  # type: ignore[arg-type]
    return {"m_s": ctl.m_s, "weights": ctl.weights()}


DERIVED: Mapping[str, tuple[tuple[str, ...], Callable[[BaseModel], dict[str, Any]]]] = {
    "protection": (("m_s", "weights"), _protection_derived),
}
"""Per method: the keys its replay summary derives, and how to derive them from a config."""


def _read(path: Path) -> dict[str, Any]:
    """TOML, or JSON (a replay's ``--json`` output, or ``{"<method>": {...}}``)."""
    if path.suffix.lower() != ".json":
        return read_toml(path)
    if not path.is_file():
        raise ConfigError(f"{path}: file not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # a BOM is dropped
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: not valid JSON: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a JSON object")
    return data


def _section(
    data: dict[str, Any], method: str, path: Path, other_method_ok: bool
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(the section, derived values stated beside it): a replay's output has its config under
    ``config`` and the derived values at the top level."""
    if data.get("method") == method and isinstance(data.get("config"), dict):
        stated = {k: data[k] for k in DERIVED.get(method, ((), None))[0] if k in data}
        return dict(data["config"]), stated
    if "method" in data and "config" in data:
        if other_method_ok:
            return {}, {}
        raise ConfigError(
            f"{path}: the output of a {data['method']} replay has no [{method}] section"
        )
    raw = data.get(method)
    if raw is None:
        return {}, {}
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: [{method}] must be a table")
    section = dict(raw)
    stated = {k: section.pop(k) for k in DERIVED.get(method, ((), None))[0] if k in section}
    return section, stated


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return bool(a == b)


def load_replay_config(
    path: Path | None, method: str, *, other_method_ok: bool = False
) -> BaseModel:
    """The ``[method]`` section of ``path`` (defaults when None), derived keys checked. The
    output of another method's replay is an error unless ``other_method_ok`` (then: defaults)."""
    if path is None:
        return load_section(None, method)
    section, stated = _section(_read(path), method, path, other_method_ok)
    cfg = load_section_model(SECTIONS[method], section, method, str(path))
    if stated:
        derived = DERIVED[method][1](cfg)
        for key, value in stated.items():
            if not _same(value, derived[key]):
                raise ConfigError(
                    f"{path}: {method}.{key} = {value!r} does not match the parameters, which"
                    f" give {derived[key]!r} (a derived value: it can be checked, not set)"
                )
    return cfg


__all__ = ["DERIVED", "load_replay_config"]
