"""Realistic sensing (issue #28 item 0): what a BMS's front end reads instead of the truth.

Each measured quantity (every cell voltage, every battery current, every cell temperature, the
bus voltage) reads ``gain * truth + offset + noise``, rounded to its ``quantum``, from the
sample ``delay_s`` old (the latest truth at or before ``t - delay_s``; before the first such
sample, the oldest one). The noise comes from one NumPy generator per quantity seeded from
``[sensors] seed``, drawn in the same order every run, so a run is reproducible. Without a
``[sensors]`` section nothing here runs and the sensors read the truth (the golden runs).

**Per-run noise in a campaign.** A campaign batch steps P runs in one plant; if the P packs drew
their noise from one stream, a run's noise would depend on its batch (its position, the batch
size). So a campaign gives every pack its own streams (``streams``: one key per pack, the
campaign's ``(seed, run)``), seeded from ``[sensors] seed`` and that key: a run then reads the same
noise alone or in any batch, and a worst run can be replayed by itself. A single run without a
key keeps the scenario's streams (the golden runs).

**A wrong starting SOC** (``soc0_error``, :func:`start_soc_wrong`): what a BMS restoring a stale SOC
from its memory at power-up starts from; the estimator's state is set once, when the loop is
built, and it learns from there like a BMS in the field.

Why errors apply to cells and not to the reductions: a battery's front end measures each cell
(or parallel group); the battery voltage, its min and max cell and its group voltages are
sums and extremes of those readings, so they must carry the same errors consistently.
"""

from __future__ import annotations

from collections import deque
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import SensorError, SensorsConfig

if TYPE_CHECKING:
    from packpilot.control.core import Core
    from packpilot.model.pack import Pack

Array = NDArray[np.float64]


class _Channel:
    """One quantity's error model and its delay line. ``rng``: one generator for every pack
    (a single run), or one per pack (a campaign batch: each run its own noise)."""

    def __init__(self, err: SensorError, rng: np.random.Generator | list[np.random.Generator]):
        self.err = err
        self.rng = rng
        self.history: deque[tuple[float, Array]] = deque()

    def _noise(self, shape: tuple[int, ...]) -> Array:
        sigma = self.err.noise_sigma
        if isinstance(self.rng, list):  # pack p's noise from pack p's stream
            return np.stack([g.normal(0.0, sigma, size=shape[1:]) for g in self.rng])
        return self.rng.normal(0.0, sigma, size=shape)

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
            out = out + self._noise(x.shape)
        if e.quantum > 0.0:
            out = np.round(out / e.quantum) * e.quantum
        return np.ascontiguousarray(out, dtype=np.float64)


class Sensors:
    """The plant's sensors with the scenario's ``[sensors]`` errors (every pack alike)."""

    def __init__(self, cfg: SensorsConfig, streams: NDArray[np.int64] | None = None) -> None:
        errs = (cfg.cell_v, cfg.current, cfg.temp, cfg.pack_v)
        rngs: list[Any]
        if streams is None:
            seeds = np.random.SeedSequence(cfg.seed).spawn(4)
            rngs = [np.random.default_rng(s) for s in seeds]
        else:  # per pack: 4 streams from (seed, the pack's key)
            per = [
                np.random.SeedSequence([cfg.seed, *(int(k) for k in np.atleast_1d(key))]).spawn(4)
                for key in streams
            ]
            rngs = [[np.random.default_rng(pk[q]) for pk in per] for q in range(4)]
        self.cell_v, self.current, self.temp, self.pack_v = (
            _Channel(e, r) for e, r in zip(errs, rngs, strict=True)
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


def sensors_of(
    cfg: SensorsConfig | None, streams: NDArray[np.int64] | None = None
) -> Sensors | None:
    """The sensors for a scenario, or None (truth) without ``[sensors]`` or with only perfect
    quantities. ``streams``: one noise key per pack (a campaign's ``(seed, run)``), or None."""
    if cfg is None:
        return None
    if all(e.perfect for e in (cfg.cell_v, cfg.current, cfg.temp, cfg.pack_v)):
        return None
    return Sensors(cfg, streams)


def true_soc(pack: Pack, traction: NDArray[np.intp]) -> Array:
    """(P, B) the plant's SOC of every traction battery: its weakest cell's remaining charge
    over the weakest cell's full charge (a series string empties with its weakest cell), the
    trace's ``soc`` channel."""
    soc, _ = pack.cell_states()
    starts = pack.string_cell_starts
    cap = pack.capacity_ah
    rem = np.minimum.reduceat(soc * cap, starts, axis=1)
    full = np.minimum.reduceat(cap, starts, axis=1)
    out: Array = (rem / full)[:, traction]
    return out


def soc_state(core: Core) -> Any:
    """The ``[soc]`` estimator's state in ``core`` (``soc``: the coulomb counter with OCV after
    a rest; ``shown_soc``: the SOC the BMS shows), or None when the core has no ``[soc]``."""
    part = next((x for x in core.compiled if x.method.name == "soc"), None)
    return None if part is None else part.st


def start_soc_wrong(core: Core, pack: Pack, traction: NDArray[np.intp], error: float) -> None:
    """Start the ``[soc]`` estimator of every pack ``error`` away from the plant's SOC, toward
    50 % (above half: lower; else higher), as a BMS restoring a stale SOC at power-up. Both
    estimators start there: the coulomb counter takes it instead of the OCV of its first sample,
    and the observer starts from the counter. No ``[soc]``: nothing to start."""
    st = soc_state(core)
    if st is None or error <= 0.0:
        return
    truth = true_soc(pack, traction)
    st.soc[:, :] = np.clip(np.where(truth > 0.5, truth - error, truth + error), 0.0, 1.0)


__all__ = ["Sensors", "sensors_of", "soc_state", "start_soc_wrong", "true_soc"]
