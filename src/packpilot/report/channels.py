"""Controller status channels of a run: aligned, compressed, grouped, and judged nominal or not.

A run records dozens of status channels (``lim_*`` per limit, ``seq_*``, ``chg_*``, ``eq_*_g<k>``
per group, …). Most of them say nothing on a given run: a limit that stayed ``ok``, a flag that
never rose, a setting that never moved. :func:`nominal` finds those so the report can say so in
one line each and chart only the channels that did something.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import StatusValue
from packpilot.contract.record import Result
from packpilot.contract.soc_source import BATTERY, SOURCES, source_codes
from packpilot.report.style import unit_of

ChannelKind = Literal["numeric", "bool", "label"]
MAX_CATEGORIES = 14
"""A label channel with more distinct values shows the most frequent ones and 'other'."""


@dataclass(frozen=True)
class StatusChannel:
    """One controller status channel, compressed to the steps where its tuple changed.

    ``rows[j]`` is the step index (into the trace) from which ``values[j, :]`` holds, up to
    the next row; ``values`` has one column per battery (None where a battery has no value).
    """

    name: str
    kind: ChannelKind
    rows: NDArray[np.intp]
    values: NDArray[Any]
    columns: tuple[int, ...]
    """Batteries that carry a value at least once (the aux battery usually does not)."""
    pack_level: bool
    """Every battery carries the same value at every step (a pack-wide quantity)."""

    def column(self, b: int) -> NDArray[Any]:
        return self.values[:, b]

    def numeric(self, b: int) -> NDArray[np.float64]:
        """Column ``b`` as floats, None as NaN, booleans as 0/1."""
        col = self.values[:, b]
        return np.array([math.nan if v is None else float(v) for v in col], dtype=np.float64)

    def lanes(self) -> list[int]:
        """The columns to draw: one for a pack-wide channel."""
        return [self.columns[0]] if self.pack_level else list(self.columns)


def _compress(seqs: Sequence[Sequence[StatusValue]]) -> tuple[list[int], list[tuple[Any, ...]]]:
    """Indices where the per-step tuple differs from the previous one (Python-level, cheap)."""
    rows: list[int] = []
    vals: list[tuple[Any, ...]] = []
    prev: Any = object()
    for i, s in enumerate(seqs):
        if s is prev:  # a loaded run repeats the very same tuple object between changes
            continue
        prev = s
        t = tuple(s)
        if vals and t == vals[-1]:
            continue
        rows.append(i)
        vals.append(t)
    return rows, vals


def _kind_of(values: NDArray[Any]) -> ChannelKind:
    seen = {type(v) for v in values.ravel() if v is not None}
    if not seen:
        return "numeric"
    if any(issubclass(t, str) for t in seen):
        return "label"
    if all(issubclass(t, bool | np.bool_) for t in seen):
        return "bool"
    return "numeric"


def _present(v: Any) -> bool:
    return v is not None and not (isinstance(v, float) and v != v)


def status_channels(
    result: Result, only: Sequence[str] | None = None
) -> dict[str, StatusChannel]:
    """Every status channel of a run (or those named in ``only``), aligned to the trace's
    steps and compressed.

    A channel shorter than the run is taken to cover the run's end (how telemetry stores it:
    a channel starts at the first step that carried it); its earlier steps have no value.
    """
    n_s = len(result.trace.t_s)
    n_b = len(result.battery_names)
    out: dict[str, StatusChannel] = {}
    names = list(result.trace.status) if only is None else only
    for name in names:
        seqs = result.trace.status.get(name)
        if not seqs or n_s == 0:
            continue
        if len(seqs) > n_s:
            seqs = seqs[len(seqs) - n_s :]
        offset = n_s - len(seqs)
        rows_l, vals_l = _compress(seqs)
        width = max(n_b, max(len(v) for v in vals_l))
        values = np.full((len(vals_l), width), None, dtype=object)
        for j, v in enumerate(vals_l):
            values[j, : len(v)] = v
        rows = np.asarray(rows_l, dtype=np.intp) + offset
        if offset > 0:
            rows = np.concatenate([[0], rows]).astype(np.intp)
            values = np.concatenate([np.full((1, width), None, dtype=object), values])
        columns = tuple(b for b in range(min(width, n_b)) if any(_present(v) for v in values[:, b]))
        pack_level = len(columns) > 1 and all(
            bool(np.all(values[:, b] == values[:, columns[0]])) for b in columns[1:]
        )
        out[name] = StatusChannel(
            name, _kind_of(values[:, list(columns)]), rows, values, columns, pack_level
        )
    return out


SOC_CHANNELS = ("soc_est", "soc_observer_ok", "soc_sigma", "bms_soc")
"""What the SOC the core used is read from (``contract/soc_source.py``)."""


def expanded(ch: StatusChannel | None, n: int, b: int) -> NDArray[np.float64] | None:
    """Battery ``b``'s column of a channel at every one of the run's ``n`` steps (NaN where
    absent), or None without the channel."""
    if ch is None or b >= ch.values.shape[1]:
        return None
    counts = np.diff(np.append(ch.rows, n))
    return np.repeat(ch.numeric(b), counts)


def core_soc(
    channels: Mapping[str, StatusChannel], n: int, b: int, recorded: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The SOC the core used for battery ``b`` at each of ``n`` steps and its source there
    (codes of ``contract/soc_source.SOURCES``): the observer's estimate where trusted, the
    coulomb counter as fallback, the battery's own report without an estimator (what the BMS
    read of it, ``bms_soc``, else ``recorded``, the trace's SOC column)."""
    nan = np.full(n, math.nan)
    est = expanded(channels.get("soc_est"), n, b)
    ok = expanded(channels.get("soc_observer_ok"), n, b)
    sigma = expanded(channels.get("soc_sigma"), n, b)
    reported = expanded(channels.get("bms_soc"), n, b)
    if reported is None:
        reported = np.asarray(recorded, np.float64)
    codes = source_codes(nan if est is None else est, nan if ok is None else ok,
                         nan if sigma is None else sigma)  # fmt: skip
    soc = np.where(codes == SOURCES.index(BATTERY), reported, nan if est is None else est)
    return soc, codes


def categories(ch: StatusChannel) -> list[str]:
    """Labels by first appearance, most frequent kept when there are too many."""
    seen: Counter[str] = Counter()
    order: list[str] = []
    for b in ch.columns:
        for v in ch.values[:, b]:
            if v is None:
                continue
            s = str(v)
            if s not in seen:
                order.append(s)
            seen[s] += 1
    if len(order) <= MAX_CATEGORIES:
        return order
    keep = {s for s, _ in seen.most_common(MAX_CATEGORIES - 1)}
    return [s for s in order if s in keep] + ["other"]


def natural_key(text: str) -> list[Any]:
    """Sort key reading digits as numbers (P2 before P10)."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text)]


# --------------------------------------------------------------------------- families

FAMILIES: tuple[tuple[str, str], ...] = (
    ("mode", "Supervisor"),
    ("seq_", "Parallel discharge sequencing"),
    ("chg_", "Staged charging"),
    ("eq_", "Equalization"),
    ("passive_", "Equalization"),
    ("protection_", "Discharge protection"),
    ("lim_", "Safety limits"),
    ("limit_", "Safety limits"),
    ("pack_limit_", "Safety limits"),
    ("plaus_", "Plausibility"),
    ("soc_", "SOC estimation"),
)


def family_of(channel: str) -> str:
    for prefix, family in FAMILIES:
        if channel == prefix or (prefix.endswith("_") and channel.startswith(prefix)):
            return family
    return "Other controller channels"


def group_base(name: str) -> tuple[str, int] | None:
    """``("eq_ah", 3)`` for a per-group channel ``eq_ah_g3``; None otherwise."""
    m = re.fullmatch(r"(.+)_g(\d+)", name)
    return (m.group(1), int(m.group(2))) if m else None


# --------------------------------------------------------------------------- nominal

NORMAL: tuple[tuple[str, frozenset[Any], str], ...] = (
    ("lim_", frozenset({"ok"}), "ok"),
    ("plaus_faults", frozenset({""}), "no fault"),
    ("plaus_isolated", frozenset({False}), "never isolated"),
    ("eq_fault", frozenset({False}), "no fault"),
    ("seq_at_risk", frozenset({False}), "never at risk"),
    ("protection_tripped", frozenset({False}), "never tripped"),
)
"""Channels with a normal band: the values that mean "nothing to report", and how to say so."""


def _normal_of(name: str) -> tuple[frozenset[Any], str] | None:
    for prefix, values, text in NORMAL:
        if name == prefix or (prefix.endswith("_") and name.startswith(prefix)):
            return values, text
    return None


def _same(values: list[Any]) -> bool:
    first = values[0]
    if isinstance(first, float) and not isinstance(first, bool):
        arr = np.asarray(values, dtype=np.float64)
        tol = 1e-9 * max(1.0, float(np.nanmax(np.abs(arr))))
        return bool(np.nanmax(arr) - np.nanmin(arr) <= tol)
    return all(v == first for v in values)


def nominal(ch: StatusChannel) -> str | None:
    """Why a channel needs no chart (``"ok throughout"``, ``"constant 20 A"``), or None when it
    did something worth drawing. A channel is nominal when every value it took lies in its
    normal band (:data:`NORMAL`) or when it never changed at all (flat)."""
    vals = [v for b in ch.columns for v in ch.values[:, b] if _present(v)]
    if not vals:
        return "no values recorded"
    normal = _normal_of(ch.name)
    if normal is not None and all(v in normal[0] for v in vals):
        return normal[1] + " throughout"
    if _same(vals):
        v = vals[0]
        text = f"{v:.4g}" if isinstance(v, float) else (repr(v) if v == "" else str(v))
        unit = unit_of(ch.name)
        return f"constant {text}" + (f" {unit}" if unit and isinstance(v, float) else "")
    return None


__all__ = [
    "FAMILIES",
    "NORMAL",
    "StatusChannel",
    "categories",
    "family_of",
    "group_base",
    "natural_key",
    "nominal",
    "status_channels",
]
