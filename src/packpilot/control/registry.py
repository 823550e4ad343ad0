"""The control methods and safety layers, each registered once: name -> role, config model,
compiled method (or, while it is being moved to the core, its scalar controller), replay
adapter.

Everything that needs the list of methods derives it from here: the core (its order, the
branches it knows), ``sim/loop.py:build_core``, the ``packpilot replay`` commands. The typed
sections of :class:`~packpilot.config.ScenarioConfig` are the config layer's own declaration of
the same names (``config`` sits below ``control`` and cannot import this module); the check at
the bottom makes an import fail unless both agree on names, roles, models and order.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel

from packpilot.config import scenario
from packpilot.config.charging import ChargingConfig
from packpilot.config.equalization import EqualizationConfig
from packpilot.config.limits import LimitsConfig
from packpilot.config.plausibility import PlausibilityConfig
from packpilot.config.protection import ProtectionConfig
from packpilot.config.sequencing import SequencingConfig
from packpilot.config.soc import SocConfig
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


REGISTRY: dict[str, Entry] = {
    e.name: e
    for e in (
        Entry(
            "protection", "method", ProtectionConfig, "packpilot.control.protection:METHOD",
            Replay(
                "packpilot.replay.protection:replay",
                "Replay t_s,current_a,temp_c,min_cell_v through discharge protection.",
            ),
        ),
        Entry(
            "sequencing", "method", SequencingConfig, "packpilot.control.sequencing:METHOD",
            Replay(
                "packpilot.replay.sequencing:replay",
                "Replay t_s,v_0..v_{N-1},i_0..i_{N-1} through parallel discharge sequencing.",
            ),
        ),
        Entry("charging", "method", ChargingConfig, "packpilot.control.charging:METHOD"),
        Entry(
            "equalization", "method", EqualizationConfig, "packpilot.control.equalization:METHOD",
            Replay(
                "packpilot.replay.equalization:replay",
                "Replay t_s,current_a,v_0..v_{M-1} through Newton-iterated equalization.",
            ),
        ),
        Entry("limits", "safety", LimitsConfig, "packpilot.control.limits:METHOD"),
        Entry(
            "plausibility", "safety", PlausibilityConfig, "packpilot.control.plausibility:METHOD"
        ),
        Entry("soc", "safety", SocConfig, "packpilot.control.soc:METHOD"),
    )
}  # fmt: skip
"""Methods run in the order a scenario lists them; safety layers after them, in this order."""

METHODS: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "method")
SAFETY: tuple[str, ...] = tuple(n for n, e in REGISTRY.items() if e.role == "safety")


def _check_matches_config() -> None:
    """The registry and the typed sections of ``ScenarioConfig`` name the same methods and
    safety layers, in the same order, with the same config models."""
    ours = {n: e.config for n, e in REGISTRY.items()}
    theirs = {n: scenario.SECTIONS[n] for n in (*scenario.METHODS, *scenario.SAFETY)}
    if (METHODS, SAFETY) != (scenario.METHODS, scenario.SAFETY) or ours != theirs:
        raise ImportError(
            "control.registry and the sections of config.ScenarioConfig disagree: "
            f"registered {METHODS} + {SAFETY} with {ours}; "
            f"the config declares {scenario.METHODS} + {scenario.SAFETY} with {theirs}"
        )


_check_matches_config()

__all__ = ["METHODS", "REGISTRY", "SAFETY", "Entry", "Replay"]
