"""The control methods and safety layers, each registered once: name -> config model, the
compiled method (or, while it is being moved to the core, its scalar controller)."""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel

from packpilot.contract.bms import Controller
from packpilot.contract.topology import PackInfo
from packpilot.control.method import Method

if TYPE_CHECKING:
    from packpilot.control.core import Part


@dataclass(frozen=True)
class Entry:
    name: str
    role: Literal["method", "safety"]
    target: str
    """``module:METHOD`` of the compiled method, or ``module:Class`` of a scalar controller."""

    def resolve(self) -> Any:
        mod, attr = self.target.split(":")
        return getattr(importlib.import_module(mod), attr)

    def method(self, config: BaseModel, infos: Sequence[PackInfo] = ()) -> Method | None:
        """The compiled method for ``config`` on the topology of ``infos`` (a method whose
        status channels depend on them, such as the limits table or the equalizer's group
        count, provides ``method_for(config, infos)``)."""
        mod = importlib.import_module(self.target.split(":")[0])
        method_for = getattr(mod, "method_for", None)
        if callable(method_for):
            m: Method = method_for(config, infos)
            return m
        obj = self.resolve()
        return obj if isinstance(obj, Method) else None

    def part(self, config: BaseModel, infos: Sequence[PackInfo]) -> Part | Controller:
        """This method for ``len(infos)`` packs (a scalar controller: one pack only)."""
        from packpilot.control.core import Part  # the core also reads the registry

        method = self.method(config, infos)
        if method is not None:
            return Part.build(method, config, infos)
        obj = self.resolve()
        if len(infos) != 1:
            raise ValueError(f"{self.name} has no compiled form yet: it runs at one pack only")
        ctl: Controller = obj(config, infos[0])
        return ctl


REGISTRY: dict[str, Entry] = {
    e.name: e
    for e in (
        Entry("protection", "method", "packpilot.control.protection:METHOD"),
        Entry("sequencing", "method", "packpilot.control.sequencing:METHOD"),
        Entry("charging", "method", "packpilot.control.charging:METHOD"),
        Entry("equalization", "method", "packpilot.control.equalization:METHOD"),
        Entry("limits", "safety", "packpilot.control.limits:METHOD"),
        Entry("plausibility", "safety", "packpilot.control.plausibility:METHOD"),
        Entry("soc", "safety", "packpilot.control.soc:METHOD"),
    )
}
"""Methods run in the order a scenario lists them; safety layers after them, in this order."""

METHODS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "method")
SAFETY: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "safety")

__all__ = ["METHODS", "REGISTRY", "SAFETY", "Entry"]
