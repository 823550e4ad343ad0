"""Scheduled fault injection: what goes wrong, when, on which battery.

Faults act where they would act in reality:

* sensor faults (``sensor_nan``, ``sensor_stuck``, ``sensor_dropout``) corrupt the
  *measurements* between plant and BMS — the plant itself is unaffected;
* switch faults (``welded_relay``, ``shorted_fet``) change the plant's hardware: the switch
  conducts whatever the gate says, and its feedback shows it;
* ``charger_fault`` raises a status flag in the dock; ``can_silence`` drops every frame between
  BMS and charger (so the dock's heartbeat times out and the BMS sees the charger offline);
* ``cooling_failure`` cuts one battery's heat transfer to ambient.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from packpilot.config import FaultConfig, ScenarioConfig
from packpilot.control.types import BatteryMeasurement, ChargerCommand, ChargerStatus, Measurements
from packpilot.model.pack import Pack

if TYPE_CHECKING:
    from packpilot.sim.runner import ChargerLink, Runner


def _with(b: BatteryMeasurement, quantity: str, value: float) -> BatteryMeasurement:
    """A copy of ``b`` with one numeric field replaced (a lying sensor)."""
    fields: dict[str, float] = {quantity: value}
    return dataclasses.replace(b, **fields)  # type: ignore[arg-type]


def _stale(b: BatteryMeasurement, age_s: float) -> BatteryMeasurement:
    """A repeated frame from a monitor that stopped reporting, with the age of its sample."""
    return dataclasses.replace(b, sample_age_s=age_s)


def _active(f: FaultConfig, t_s: float) -> bool:
    return t_s >= f.at_s - 1e-9 and (f.until_s is None or t_s < f.until_s - 1e-9)


@dataclass
class SilenceableLink:
    """Wraps a charger link; while silenced nothing crosses in either direction."""

    inner: ChargerLink
    silenced: bool = False

    def send(self, command: ChargerCommand, t_s: float) -> None:
        if not self.silenced:
            self.inner.send(command, t_s)

    def poll(self, t_s: float) -> ChargerStatus | None:
        status = self.inner.poll(t_s)
        return None if self.silenced else status

    def close(self) -> None:
        close = getattr(self.inner, "close", None)
        if callable(close):
            close()


@dataclass
class FaultInjector:
    """Applies the scenario's ``[[faults]]`` to the plant, the sensors and the charger link."""

    cfg: ScenarioConfig
    pack: Pack
    link: SilenceableLink | None = None
    stuck: dict[tuple[int, str], float] = field(default_factory=dict)
    frozen: dict[int, BatteryMeasurement] = field(default_factory=dict)
    applied: set[int] = field(default_factory=set)
    cooling: dict[int, bool] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.index = {b.name: i for i, b in enumerate(self.cfg.pack.batteries)}

    # ------------------------------------------------------------------ plant side
    def before_step(self, runner: Runner, t_s: float) -> None:
        pack = self.pack
        for k, f in enumerate(self.cfg.faults):
            on = _active(f, t_s)
            i = self.index.get(f.battery or "", -1)
            if f.kind == "welded_relay":
                pack.welded[i] = on or (k in self.applied and f.until_s is None)
            elif f.kind == "shorted_fet":
                pack.fet_shorted[:, i, 0 if f.fet == "chg" else 1] = on
            elif f.kind == "charger_fault":
                pack.charger.view(0).set_fault(f.flag, on)
            elif f.kind == "can_silence" and self.link is not None:
                self.link.silenced = on
            elif f.kind == "cooling_failure":
                self._cooling(i, f, on)
            if on:
                self.applied.add(k)

    def _cooling(self, string: int, f: FaultConfig, on: bool) -> None:
        """Cut (or restore) one battery's heat transfer to ambient, on state changes only."""
        if self.cooling.get(string) == on:
            return
        self.cooling[string] = on
        self.pack.set_cooling(string, f.cooling_factor if on else 1.0)

    # ------------------------------------------------------------------ sensor side
    def filter(self, meas: Measurements) -> Measurements:
        """Corrupt the measurements as the active sensor faults dictate."""
        t = meas.t_s
        batteries = list(meas.batteries)
        traction = [i for i, b in enumerate(self.cfg.pack.batteries) if b.role == "traction"]
        changed = False
        for f in self.cfg.faults:
            if f.kind not in ("sensor_nan", "sensor_stuck", "sensor_dropout"):
                continue
            i = self.index[f.battery or ""]
            if i not in traction:
                continue
            k = traction.index(i)
            b = batteries[k]
            if not _active(f, t):
                self.stuck.pop((k, f.quantity), None)
                self.frozen.pop(k, None)
                continue
            changed = True
            if f.kind == "sensor_nan":
                batteries[k] = _with(b, f.quantity, math.nan)
            elif f.kind == "sensor_stuck":
                value = self.stuck.setdefault((k, f.quantity), float(getattr(b, f.quantity)))
                batteries[k] = _with(b, f.quantity, value)
            else:  # dropout: the battery's monitor stops reporting; the last frame repeats
                batteries[k] = _stale(self.frozen.setdefault(k, b), max(t - f.at_s, 0.0))
        if not changed:
            return meas
        return dataclasses.replace(meas, batteries=tuple(batteries))
