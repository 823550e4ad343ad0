"""What a closed-loop run records: per-step samples, events, a metrics summary; and where it
goes (a :class:`Recorder`: SQLite, the dashboard, memory).

``StepSample`` is the unit of telemetry: the loop hands one per step to the recorder (so a
crash loses at most the recorder's unflushed buffer) and appends it to the in-memory trace.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import Event, StatusValue
from packpilot.contract.events import Labels
from packpilot.contract.events import value as field_value

# Per-battery channels always present in a StepSample, in this order (SI units in the name).
BATTERY_CHANNELS: tuple[str, ...] = (
    "voltage_v",
    "current_a",
    "soc",
    "temp_c",
    "min_cell_v",
    "max_cell_v",
    "remaining_ah",
    "full_ah",
    "chg_on",
    "dsg_on",
    "chg_diode_a",
    "dsg_diode_a",
    "balancer_w",
)


@dataclass(frozen=True, slots=True)
class StepSample:
    """One control period of one pack, as recorded (truth from the plant, not the sensors)."""

    step: int
    t_s: float
    bus_v: float
    load_demand_a: float
    load_a: float
    charger_v: float
    charger_a: float
    battery: NDArray[np.float64]
    """Shape (n_batteries, len(BATTERY_CHANNELS)), columns as BATTERY_CHANNELS."""
    group_v: NDArray[np.float64]
    """Shape (n_batteries, max_groups); NaN where a battery has fewer groups."""
    status: Mapping[str, Sequence[StatusValue]] = field(default_factory=dict)
    """Controller status channels, one value per battery."""
    aux: NDArray[np.float64] | None = None
    """Auxiliary battery row (BATTERY_CHANNELS), if the pack has one."""


@dataclass(frozen=True)
class StatusLayout:
    """How a row of status *numbers* (``(batteries, slots)``, as the core writes them) reads
    as the status channels a :class:`StepSample` carries: each channel's name, slot, kind and
    labels in output order (``packpilot.contract.events.value`` renders a number), and where
    each battery's value sits in a channel's list (``Topology.spread``: ``positions[b]`` of
    ``n_strings``, ``None`` elsewhere). :meth:`SQLiteRecorder.record_numbers` stores the same
    rows from it without rendering every channel of every step."""

    channels: tuple[tuple[str, int, str, Labels], ...]
    positions: tuple[int, ...]
    n_strings: int

    def render(self, row: NDArray[np.float64]) -> dict[str, list[StatusValue]]:
        """Every channel of one row as the status mapping of a sample."""
        out: dict[str, list[StatusValue]] = {}
        for name, slot, kind, labels in self.channels:
            vals: list[StatusValue] = [None] * self.n_strings
            for b, x in enumerate(row[:, slot].tolist()):
                vals[self.positions[b]] = field_value(x, kind, labels)
            out[name] = vals
        return out


class Recorder(Protocol):
    """Where a run's telemetry goes while it runs (SQLite by default)."""

    def start(self, config: Mapping[str, Any], battery_names: Sequence[str]) -> int: ...

    def record(self, sample: StepSample) -> None: ...

    def record_events(self, events: Sequence[Event]) -> None: ...

    def finish(self, metrics: Mapping[str, Any], status: str = "ok") -> None: ...


@dataclass
class Trace:
    """Column-oriented copy of all StepSamples of a run (built once at the end)."""

    t_s: NDArray[np.float64]
    bus_v: NDArray[np.float64]
    load_demand_a: NDArray[np.float64]
    load_a: NDArray[np.float64]
    charger_v: NDArray[np.float64]
    charger_a: NDArray[np.float64]
    battery: NDArray[np.float64]
    """Shape (steps, n_batteries, len(BATTERY_CHANNELS))."""
    group_v: NDArray[np.float64]
    """Shape (steps, n_batteries, max_groups)."""
    status: Mapping[str, list[Sequence[StatusValue]]]
    """Per channel, a row per step (one value per string). A run's trace renders a channel
    only when it is read (``sim/record.py:TraceStatus``); read-only."""
    aux: NDArray[np.float64] | None = None
    step: NDArray[np.int64] | None = None
    """Step index of each row (None when unknown: then the row index is the step)."""

    def channel(self, name: str) -> NDArray[np.float64]:
        """Per-battery time series, shape (steps, n_batteries)."""
        return self.battery[:, :, BATTERY_CHANNELS.index(name)]

    @classmethod
    def from_samples(cls, samples: Sequence[StepSample]) -> Trace:
        if not samples:
            raise ValueError("a trace needs at least one sample")
        status: dict[str, list[Sequence[StatusValue]]] = {}
        for s in samples:
            for k, v in s.status.items():
                status.setdefault(k, []).append(v)
        aux = None
        if samples[0].aux is not None:
            aux = np.stack(
                [
                    s.aux if s.aux is not None else np.full_like(samples[0].aux, np.nan)
                    for s in samples
                ]
            )
        return cls(
            t_s=np.array([s.t_s for s in samples]),
            bus_v=np.array([s.bus_v for s in samples]),
            load_demand_a=np.array([s.load_demand_a for s in samples]),
            load_a=np.array([s.load_a for s in samples]),
            charger_v=np.array([s.charger_v for s in samples]),
            charger_a=np.array([s.charger_a for s in samples]),
            battery=np.stack([s.battery for s in samples]),
            group_v=np.stack([s.group_v for s in samples]),
            status=status,
            aux=aux,
            step=np.array([s.step for s in samples], dtype=np.int64),
        )


@dataclass
class Result:
    """A finished run: its trace, its events and the metrics summary (JSON-able)."""

    battery_names: list[str]
    trace: Trace
    events: list[Event]
    metrics: dict[str, Any]
    run_id: int | None = None
    build_time_s: float = 0.0
    """Wall seconds the run spent compiling kernels or loading them from the on-disk cache
    (its first calls of each kernel); ``metrics["wall_time_s"]`` is the simulation alone."""
