"""ORACLE: the scalar SOC estimator as it was before the compiled core (tests only; deleted
once the golden and equivalence tests pass).

 State-of-charge estimation: coulomb counting, corrected from the OCV after a rest.

Coulomb counting is exact for the charge that flowed but drifts with current-sensor offset and
starts from whatever the initial SOC was; the open-circuit voltage tells the SOC directly, but
only once the cell has rested (the RC overpotentials have decayed). So: integrate the measured
current every tick; when a battery's current has stayed below ``rest_current_a`` for
``rest_time_s``, read the SOC off the OCV table at the cell voltage and move the estimate there
(fully, or by ``blend``), then again after every further ``rest_time_s`` of the same rest.

``control`` may not import the cell model, so the OCV curve (SOC -> cell volts) comes in as
plain arrays, e.g. ``CellParams.ocv_soc`` / ``ocv_table_v`` handed over by the shell. The table
is per cell at its reference temperature (temperature dependence of the OCV is ignored).

Timing: a measurement at ``t`` carries the current that flowed during ``[t - dt, t]`` (the
simulator's and a sampling BMS's convention), so that current times ``dt_s`` is exactly the
charge moved since the previous tick.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from packpilot.config.base import load_section_model
from packpilot.contract.bms import BatteryMeasurement, Commands, ControlOutput, Event, Measurements
from packpilot.contract.topology import PackInfo
from packpilot.errors import ConfigError

EPS = 1e-9
VoltageSource = Literal["min", "avg"]


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


class SocConfig(BaseModel):
    """Settings of :class:`SocEstimator` (the OCV table itself comes from the cell set)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rest_current_a: float = Field(
        default=0.1, description="A battery rests while |current| is below this (A, > 0)."
    )
    rest_time_s: float = Field(
        default=600.0,
        description="Rest needed before an OCV correction, and between corrections (s, > 0); "
        "long enough for the RC overpotentials to decay (several time constants).",
    )
    blend: float = Field(
        default=1.0,
        description="Weight of the OCV reading in a correction (0..1; 1 = replace).",
    )
    voltage: VoltageSource = Field(
        default="min",
        description="Cell voltage read against the OCV table: 'min' (the weakest cell, which "
        "empties first in a series string) or 'avg' (battery voltage / series cells).",
    )

    @model_validator(mode="after")
    def _check(self) -> SocConfig:
        if not (_finite(self.rest_current_a) and self.rest_current_a > 0.0):
            raise ValueError(f"rest_current_a must be > 0 A, got {self.rest_current_a}")
        if not (_finite(self.rest_time_s) and self.rest_time_s > 0.0):
            raise ValueError(f"rest_time_s must be > 0 s, got {self.rest_time_s}")
        if not (_finite(self.blend) and 0.0 <= self.blend <= 1.0):
            raise ValueError(f"blend must be within 0..1, got {self.blend}")
        return self

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<soc>") -> SocConfig:
        return load_section_model(cls, data, "soc", source)


@dataclass(slots=True)
class _Battery:
    soc: float
    rest_s: float = 0.0
    next_fix_s: float = 0.0
    corrections: int = 0


class SocEstimator:
    """Per-battery SOC by coulomb counting with OCV correction after a rest.

    ``capacity_ah`` per battery; ``ocv_soc`` / ``ocv_v`` the cell OCV curve (``ocv_v`` strictly
    increasing); ``series_cells`` per battery is needed for ``voltage='avg'``. ``soc0`` gives
    initial estimates; without it (or where an entry is NaN) the first tick initialises the
    battery from the OCV of its cell voltage, as a BMS does at power-up after the pack rested.
    """

    def __init__(
        self,
        capacity_ah: Iterable[float],
        ocv_soc: Iterable[float],
        ocv_v: Iterable[float],
        rest_current_a: float = 0.1,
        rest_time_s: float = 600.0,
        *,
        blend: float = 1.0,
        voltage: VoltageSource = "min",
        series_cells: Iterable[int] | None = None,
        soc0: Iterable[float] | None = None,
    ) -> None:
        cfg = SocConfig(
            rest_current_a=rest_current_a, rest_time_s=rest_time_s, blend=blend, voltage=voltage
        )
        self.config = cfg
        self.capacity_ah = tuple(float(c) for c in capacity_ah)
        for i, c in enumerate(self.capacity_ah):
            if not (_finite(c) and c > 0.0):
                raise ConfigError(f"soc: capacity_ah[{i}] must be > 0 Ah, got {c}")
        self._ocv_v, self._ocv_soc = _check_ocv(ocv_soc, ocv_v)
        n = len(self.capacity_ah)
        self.series_cells = (
            tuple(int(s) for s in series_cells) if series_cells is not None else (0,) * n
        )
        if len(self.series_cells) != n:
            raise ConfigError(f"soc: series_cells has {len(self.series_cells)} entries, need {n}")
        if voltage == "avg" and not all(s > 0 for s in self.series_cells):
            raise ConfigError("soc: voltage = 'avg' needs series_cells > 0 for every battery")
        init = list(soc0) if soc0 is not None else [math.nan] * n
        if len(init) != n:
            raise ConfigError(f"soc: soc0 has {len(init)} entries, need {n}")
        self._bat = [
            _Battery(soc=min(1.0, max(0.0, float(s))) if _finite(s) else math.nan) for s in init
        ]

    @classmethod
    def from_config(
        cls,
        config: SocConfig,
        pack: PackInfo,
        ocv_soc: Iterable[float],
        ocv_v: Iterable[float],
        soc0: Iterable[float] | None = None,
    ) -> SocEstimator:
        """Build for a pack: capacities and series cell counts from :class:`PackInfo`."""
        if len(pack.capacity_ah) != pack.n_batteries:
            raise ConfigError("soc: PackInfo.capacity_ah must give one capacity per battery")
        series = tuple(
            g * c for g, c in zip(pack.groups_per_battery, pack.cells_per_group, strict=True)
        )
        return cls(
            pack.capacity_ah,
            ocv_soc,
            ocv_v,
            config.rest_current_a,
            config.rest_time_s,
            blend=config.blend,
            voltage=config.voltage,
            series_cells=series,
            soc0=soc0,
        )

    @property
    def soc(self) -> tuple[float, ...]:
        """Current estimates (NaN until a battery has been initialised)."""
        return tuple(b.soc for b in self._bat)

    def soc_from_ocv(self, cell_v: float) -> float:
        """Inverse of the OCV table, clamped to its ends and to 0..1 (NaN for a NaN input)."""
        if not _finite(cell_v):
            return math.nan
        xs, ys = self._ocv_v, self._ocv_soc
        if cell_v <= xs[0]:
            s = ys[0]
        elif cell_v >= xs[-1]:
            s = ys[-1]
        else:
            k = bisect.bisect_right(xs, cell_v)
            x0, x1, y0, y1 = xs[k - 1], xs[k], ys[k - 1], ys[k]
            s = y0 + (y1 - y0) * (cell_v - x0) / (x1 - x0)
        return min(1.0, max(0.0, s))

    def cell_voltage(self, i: int, bm: BatteryMeasurement) -> float:
        if self.config.voltage == "min":
            return bm.min_cell_v
        return bm.voltage_v / self.series_cells[i]

    def update(self, meas: Measurements, dt_s: float) -> tuple[tuple[float, ...], list[Event]]:
        """Advance every battery by one tick; returns the estimates and any correction events."""
        dt = float(dt_s) if _finite(dt_s) and dt_s > 0.0 else 0.0
        cfg = self.config
        events: list[Event] = []
        for i, b in enumerate(self._bat):
            bm = meas.batteries[i] if i < len(meas.batteries) else None
            if bm is None or not bm.present:
                b.rest_s = b.next_fix_s = 0.0
                continue
            if not _finite(b.soc):
                b.soc = self.soc_from_ocv(self.cell_voltage(i, bm))
                continue  # initialised from this sample; its current belongs to the past
            cur = bm.current_a
            if not _finite(cur):
                b.rest_s = b.next_fix_s = 0.0  # unknown current: hold, and no rest
                continue
            b.soc = min(1.0, max(0.0, b.soc - cur * dt / (3600.0 * self.capacity_ah[i])))
            if abs(cur) >= cfg.rest_current_a:
                b.rest_s = b.next_fix_s = 0.0
                continue
            b.rest_s += dt
            if b.next_fix_s == 0.0:
                b.next_fix_s = cfg.rest_time_s
            if b.rest_s < b.next_fix_s - EPS:
                continue
            v = self.cell_voltage(i, bm)
            ocv_soc = self.soc_from_ocv(v)
            if not _finite(ocv_soc):
                continue  # retry on the next tick of this rest
            before = b.soc
            b.soc = (1.0 - cfg.blend) * b.soc + cfg.blend * ocv_soc
            b.next_fix_s += cfg.rest_time_s
            b.corrections += 1
            events.append(
                Event(
                    t_s=meas.t_s,
                    kind="SocCorrected",
                    battery=i,
                    message=f"SOC {before:.3f} -> {b.soc:.3f} from OCV {v:.4f} V",
                    data={"before": before, "after": b.soc, "ocv_soc": ocv_soc, "cell_v": v},
                )
            )
        return self.soc, events

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        """Controller form: no commands; ``soc_est`` and ``soc_rest_s`` status channels."""
        soc, events = self.update(meas, dt_s)
        return ControlOutput(
            commands=Commands(),
            events=tuple(events),
            status={"soc_est": list(soc), "soc_rest_s": [b.rest_s for b in self._bat]},
        )


def _check_ocv(
    ocv_soc: Iterable[float], ocv_v: Iterable[float]
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    soc = tuple(float(x) for x in ocv_soc)
    volts = tuple(float(x) for x in ocv_v)
    if len(soc) < 2 or len(soc) != len(volts):
        raise ConfigError(
            f"soc: OCV table needs >= 2 points and equal lengths, got {len(soc)} SOC and "
            f"{len(volts)} voltage values"
        )
    if not all(_finite(x) for x in soc + volts):
        raise ConfigError("soc: OCV table values must be finite numbers")
    if any(b <= a for a, b in pairwise(soc)):
        raise ConfigError("soc: ocv_soc must be strictly increasing")
    if any(b <= a for a, b in pairwise(volts)):
        k = next(k for k, (a, b) in enumerate(pairwise(volts)) if b <= a)
        raise ConfigError(
            f"soc: ocv_v must be strictly increasing to be inverted; point {k + 1} "
            f"({volts[k + 1]} V) is not above point {k} ({volts[k]} V)"
        )
    return volts, soc


__all__ = ["SocConfig", "SocEstimator"]
