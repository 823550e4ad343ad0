"""The control methods and safety layers: name -> role, config model, compiled method (or a
scalar controller), replay adapter.

A method is registered by **one line**, its typed section in
:class:`~packpilot.config.ScenarioConfig` (``name: Annotated[NameConfig | None, Section(role)]``,
which names its control package); this module derives its entries from those sections and
adds the optional ``packpilot replay`` adapters (:data:`REPLAYS`). Everything that needs the
list of methods derives it from here: ``sim/loop.py:build_core``, the ``packpilot replay``
commands, the report. The core's fused step is generated from the parts a core has
(:mod:`packpilot.control.core_kernel`), so it lists no method either.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel

from packpilot.config import scenario
from packpilot.contract.bms import Controller
from packpilot.contract.topology import PackInfo
from packpilot.control.method import Method

if TYPE_CHECKING:
    from pathlib import Path

    from packpilot.control.core import Part


def _resolve(target: str) -> Any:
    mod, attr = target.split(":")
    return getattr(importlib.import_module(mod), attr)


@dataclass(frozen=True)
class Replay:
    """How ``packpilot replay NAME LOG`` runs a CSV log through a method."""

    target: str
    """``module:function``, ``function(log_path, config) -> ReplayResult``; a string, because
    ``control`` does not import ``replay`` (it sits above)."""
    help: str
    """The command's help: the log's columns and what they run through."""

    def function(self) -> Callable[[Path, Any], Any]:
        fn: Callable[[Path, Any], Any] = _resolve(self.target)
        return fn


@dataclass(frozen=True)
class Entry:
    name: str
    role: Literal["method", "safety"]
    config: type[BaseModel]
    """The model of its ``[name]`` section (``config/<name>.py``)."""
    target: str
    """``module:METHOD`` of the compiled method, or ``module:Class`` of a scalar controller."""
    replay: Replay | None = None

    def resolve(self) -> Any:
        return _resolve(self.target)

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


REPLAYS: dict[str, Replay] = {
    "protection": Replay(
        "packpilot.replay.protection:replay",
        "Replay t_s,current_a,temp_c,min_cell_v through discharge protection.",
    ),
    "sequencing": Replay(
        "packpilot.replay.sequencing:replay",
        "Replay t_s,v_0..v_{N-1},i_0..i_{N-1} through parallel discharge sequencing.",
    ),
    "equalization": Replay(
        "packpilot.replay.equalization:replay",
        "Replay t_s,current_a,v_0..v_{M-1} through Newton-iterated equalization.",
    ),
}
"""The ``packpilot replay NAME`` commands: a method with a log adapter in ``packpilot/replay``
(optional; a method runs in every other command without one)."""


def _entries() -> dict[str, Entry]:
    """One entry per section :class:`~packpilot.config.ScenarioConfig` registers (its
    :class:`~packpilot.config.scenario.Section` fields), in their order."""
    roles: dict[str, Literal["method", "safety"]] = {
        **dict.fromkeys(scenario.METHODS, "method"),
        **dict.fromkeys(scenario.SAFETY, "safety"),
    }
    return {
        name: Entry(
            name,
            role,
            scenario.SECTIONS[name],
            f"{scenario.PACKAGES[name]}:METHOD",
            REPLAYS.get(name),
        )
        for name, role in roles.items()
    }


REGISTRY: dict[str, Entry] = _entries()
"""Methods run in the order a scenario lists them; safety layers after them, in this order."""

METHODS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "method")
SAFETY: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "safety")
if not set(REPLAYS) <= set(REGISTRY):
    raise ImportError(f"replay adapters of unregistered methods: {set(REPLAYS) - set(REGISTRY)}")

__all__ = ["METHODS", "REGISTRY", "REPLAYS", "SAFETY", "Entry", "Replay"]
