"""Charger links of a run: setpoints out, status back, one link per pack.

A link is direct (setpoints written into the plant's dock every period) or a python-can bus
(TC/Elcon frames to an emulated dock on a virtual bus, or to a real one on ``socketcan``).
:class:`ChargerLinks` keeps, per pack, the last status and marks the charger offline once
nothing arrived for the heartbeat timeout, and turns the merged commands into setpoints
(the scenario's ``[charger]`` setpoint where no controller commanded the charger).

An emulated dock on a private virtual bus with no frame log (``[can] interface = "virtual"``,
no ``log``, no ``channel``) is the compiled model of that whole path,
:class:`~packpilot.sim.elcon.ElconLinks`, for every pack (P = 1 and P = N alike): same
setpoints at the dock, same status in the measurements, step for step, without python-can.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

from packpilot.config import ScenarioConfig
from packpilot.contract.arrays import CmdArrays, MeasArrays
from packpilot.contract.charger import CHARGER_FLAGS, ChargerCommand, ChargerLink, ChargerStatus
from packpilot.model.charger import ChargerView
from packpilot.model.pack import Pack
from packpilot.sim.elcon import ElconLinks


@dataclass
class DirectChargerLink:
    """Setpoints written straight into the plant's charger: a request every control period."""

    charger: ChargerView

    def send(self, command: ChargerCommand, t_s: float) -> None:
        self.charger.request(command.voltage_v, command.current_a, command.enable, t_s)

    def poll(self, t_s: float) -> ChargerStatus | None:
        v, a = self.charger.output()
        f = self.charger.fault_flags
        return ChargerStatus(output_v=v, output_a=a, online=True, **f)

    def close(self) -> None:
        pass


def can_link(cfg: ScenarioConfig, pack: Pack, p: int = 0) -> ChargerLink:
    """Charger setpoints over python-can: an emulated dock on a virtual bus, or real hardware."""
    from packpilot.io.can.link import CanChargerLink

    assert cfg.can is not None
    emulate = cfg.can.interface == "virtual"
    return CanChargerLink(
        pack.charger.view(p) if emulate else None,
        interface=cfg.can.interface,
        channel=cfg.can.channel,
        log_path=cfg.can.log,
        heartbeat_timeout_s=cfg.charger.heartbeat_timeout_s,
        rating=(cfg.charger.rated_v, cfg.charger.rated_a),
    )


def modelled(cfg: ScenarioConfig) -> bool:
    """The scenario's charger talks TC/Elcon to an emulated dock over a virtual bus nobody
    else sees (no frame log, no named channel): :class:`ElconLinks` runs it instead."""
    can = cfg.can
    return (
        cfg.charger.present
        and can is not None
        and can.interface == "virtual"
        and can.log is None
        and can.channel is None
    )


def default_links(cfg: ScenarioConfig, pack: Pack) -> list[ChargerLink]:
    """The scenario's links as one Python object per pack: none without a charger, CAN with
    ``[can]``, else direct. (:func:`pack_links` runs a modelled CAN link compiled instead.)"""
    if not cfg.charger.present:
        return []
    if cfg.can is not None:
        return [can_link(cfg, pack, p) for p in range(pack.n_packs)]
    return [DirectChargerLink(pack.charger.view(p)) for p in range(pack.n_packs)]


class PackLinks(Protocol):
    """The charger links of every pack as the closed loop drives them."""

    def __bool__(self) -> bool: ...

    def poll(self, t_s: float, m: MeasArrays) -> None: ...

    def send(self, t_s: float, cmd: CmdArrays) -> None: ...

    def close(self) -> None: ...


def pack_links(cfg: ScenarioConfig, pack: Pack) -> ElconLinks | None:
    """The compiled link of every pack when the scenario's link is modelled, else ``None``
    (then :func:`default_links` under :class:`ChargerLinks`)."""
    return ElconLinks(cfg, pack) if modelled(cfg) else None


class ChargerLinks:
    """The charger link of every pack, with status tracking and the default setpoint."""

    def __init__(self, cfg: ScenarioConfig, links: Sequence[ChargerLink]) -> None:
        self.links = list(links)
        c = cfg.charger
        self.default = ChargerCommand(c.voltage_v, c.current_a, c.enable)
        self.timeout_s = c.heartbeat_timeout_s
        n = len(self.links)
        self.last: list[ChargerStatus | None] = [None] * n
        self.seen_s: list[float | None] = [None] * n

    def __bool__(self) -> bool:
        return bool(self.links)

    def poll(self, t_s: float, m: MeasArrays) -> None:
        """Latest status of every charger into ``m`` (offline once silent for the timeout)."""
        ch = m.charger
        for p, link in enumerate(self.links):
            status = link.poll(t_s)
            last = self.last[p]
            seen = self.seen_s[p]
            if status is not None:
                self.seen_s[p] = t_s
                last = status
            elif (
                last is not None
                and seen is not None
                and t_s - seen > self.timeout_s
                and last.online
            ):
                last = dataclasses.replace(last, online=False)
            self.last[p] = last
            ch.reported[p] = last is not None
            if last is None:
                ch.output_v[p] = ch.output_a[p] = math.nan
                ch.flags[p] = False
                ch.online[p] = False
                continue
            ch.output_v[p] = last.output_v
            ch.output_a[p] = last.output_a
            for k, name in enumerate(CHARGER_FLAGS):
                ch.flags[p, k] = bool(getattr(last, name))
            ch.online[p] = last.online

    def send(self, t_s: float, cmd: CmdArrays) -> None:
        for p, link in enumerate(self.links):
            command = self.default
            if cmd.charger_set[p]:
                command = ChargerCommand(
                    float(cmd.charger_v[p]), float(cmd.charger_a[p]), bool(cmd.charger_enable[p])
                )
            link.send(command, t_s)

    def close(self) -> None:
        for link in self.links:
            close = getattr(link, "close", None)
            if callable(close):
                close()


__all__ = [
    "ChargerLinks",
    "DirectChargerLink",
    "ElconLinks",
    "PackLinks",
    "can_link",
    "default_links",
    "modelled",
    "pack_links",
]
