"""Realistic sensing (issue #28 item 0): what a BMS's front end reads instead of the truth.

Each measured quantity (every cell voltage, every battery current, every cell temperature, the
bus voltage) reads ``gain * truth + offset + noise``, rounded to its ``quantum``, from the
sample ``delay_s`` old (the latest truth at or before ``t - delay_s``; before the first such
sample, the oldest one). The noise comes from one NumPy generator per quantity seeded from
``[sensors] seed``, drawn in the same order every run, so a run is reproducible. Without a
``[sensors]`` section nothing here runs and the sensors read the truth (the golden runs).

Why errors apply to cells and not to the reductions: a battery's front end measures each cell
(or parallel group); the battery voltage, its min and max cell and its group voltages are
sums and extremes of those readings, so they must carry the same errors consistently.
"""

from __future__ import annotations

from collections import deque

import numpy as np
from numpy.typing import NDArray

from packpilot.config import SensorError, SensorsConfig

Array = NDArray[np.float64]


class _Channel:
    """One quantity's error model and its delay line."""

    def __init__(self, err: SensorError, rng: np.random.Generator) -> None:
        self.err = err
        self.rng = rng
        self.history: deque[tuple[float, Array]] = deque()

    def _delayed(self, t_s: float, truth: Array) -> Array:
        if self.err.delay_s <= 0.0:
            return truth
        self.history.append((t_s, truth.copy()))
        cut = t_s - self.err.delay_s + 1e-9
        while len(self.history) > 1 and self.history[1][0] <= cut:
            self.history.popleft()
        return self.history[0][1]

    def read(self, t_s: float, truth: Array) -> Array:
        """The reading of ``truth`` (any shape) at ``t_s``; a new array (truth untouched)."""
        e = self.err
        x = self._delayed(t_s, truth)
        out = x * e.gain + e.offset
        if e.noise_sigma > 0.0:
            out = out + self.rng.normal(0.0, e.noise_sigma, size=x.shape)
        if e.quantum > 0.0:
            out = np.round(out / e.quantum) * e.quantum
        return np.ascontiguousarray(out, dtype=np.float64)


class Sensors:
    """The plant's sensors with the scenario's ``[sensors]`` errors (every pack alike)."""

    def __init__(self, cfg: SensorsConfig) -> None:
        seeds = np.random.SeedSequence(cfg.seed).spawn(4)
        errs = (cfg.cell_v, cfg.current, cfg.temp, cfg.pack_v)
        self.cell_v, self.current, self.temp, self.pack_v = (
            _Channel(e, np.random.default_rng(s)) for e, s in zip(errs, seeds, strict=True)
        )

    def read(
        self, t_s: float, cell_v: Array, string_a: Array, temp_c: Array, bus_v: Array
    ) -> tuple[Array, Array, Array, Array]:
        """(cell volts, string amperes, cell temperatures, bus volts) as the sensors read them."""
        return (
            self.cell_v.read(t_s, cell_v),
            self.current.read(t_s, string_a),
            self.temp.read(t_s, temp_c),
            self.pack_v.read(t_s, bus_v),
        )


def sensors_of(cfg: SensorsConfig | None) -> Sensors | None:
    """The sensors for a scenario, or None (truth) without ``[sensors]`` or with only perfect
    quantities."""
    if cfg is None:
        return None
    if all(e.perfect for e in (cfg.cell_v, cfg.current, cfg.temp, cfg.pack_v)):
        return None
    return Sensors(cfg)


__all__ = ["Sensors", "sensors_of"]
