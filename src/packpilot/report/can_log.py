"""The CAN section of the report: what a run's CAN log (``--can-log`` .blf / .asc) holds.

Read with python-can's own readers. Per arbitration id: the message name from the packaged DBC,
frames sent and received, the rate, the typical period and the longest silence (a charger link
that went quiet shows here), and frames the codec rejects; for the log: error and remote
frames. A frames-per-second chart shares the report's time axis, so a silence lines up with
what the batteries did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np

from packpilot.io.can.bus import SIM_EPOCH_S
from packpilot.io.can.codec import REQUEST_ID, STATUS_ID, FrameError, database
from packpilot.io.can.codec import decode_request as _decode_request
from packpilot.io.can.codec import decode_status as _decode_status
from packpilot.report.charts import Chart, Series, Store
from packpilot.report.fmt import esc, fmt_num, table
from packpilot.report.style import battery_color

_DECODERS = {REQUEST_ID: _decode_request, STATUS_ID: _decode_status}


@dataclass
class IdStats:
    """One arbitration id of a log."""

    arbitration_id: int
    extended: bool
    name: str
    times: list[float] = field(default_factory=list)
    rx: int = 0
    tx: int = 0
    malformed: int = 0

    @property
    def frames(self) -> int:
        return len(self.times)

    def rate_hz(self) -> float:
        span = self.times[-1] - self.times[0] if self.frames > 1 else 0.0
        return (self.frames - 1) / span if span > 0 else math.nan

    def period_s(self) -> float:
        return float(np.median(np.diff(self.times))) if self.frames > 1 else math.nan

    def longest_gap(self) -> tuple[float, float]:
        """(gap in s, time it started); NaN when fewer than two frames."""
        if self.frames < 2:
            return math.nan, math.nan
        d = np.diff(self.times)
        k = int(np.argmax(d))
        return float(d[k]), self.times[k]


@dataclass
class CanLogStats:
    """What the report shows of one CAN log."""

    path: Path
    ids: dict[int, IdStats] = field(default_factory=dict)
    error_frames: int = 0
    remote_frames: int = 0

    @property
    def frames(self) -> int:
        return sum(s.frames for s in self.ids.values()) + self.error_frames


def _sim_time(ts: float) -> float:
    """Simulation time of a logged frame (FrameLog writes SIM_EPOCH_S + t)."""
    return ts - SIM_EPOCH_S if ts >= SIM_EPOCH_S / 2 else ts


def _reader(path: Path) -> can.io.generic.MessageReader:
    if path.suffix.lower() == ".asc":
        return can.ASCReader(str(path), relative_timestamp=False)
    return can.BLFReader(str(path))


def read_can_log(path: Path) -> CanLogStats:
    """Per-id statistics of a .blf or .asc log."""
    names = {m.frame_id: m.name for m in database().messages}
    stats = CanLogStats(path)
    for msg in _reader(path):
        if msg.is_error_frame:
            stats.error_frames += 1
            continue
        if msg.is_remote_frame:
            stats.remote_frames += 1
        s = stats.ids.get(msg.arbitration_id)
        if s is None:
            name = names.get(msg.arbitration_id, "not in the DBC")
            s = stats.ids[msg.arbitration_id] = IdStats(
                msg.arbitration_id, msg.is_extended_id, name
            )
        s.times.append(_sim_time(float(msg.timestamp)))
        if msg.is_rx:
            s.rx += 1
        else:
            s.tx += 1
        decode = _DECODERS.get(msg.arbitration_id)
        if decode is not None and not msg.is_remote_frame:
            try:
                decode(msg)
            except FrameError:
                s.malformed += 1
    return stats


def can_section(path: Path | None, store: Store) -> tuple[str, list[Chart]]:
    """The section's HTML and its chart (frames per second per id, its data put in ``store``);
    ``("", [])`` without a log."""
    if path is None:
        return "", []
    if not path.is_file():
        return (
            f'<p class="note">The CAN log <code>{esc(path)}</code> named for this run was not'
            " found (a relative path is read from the current directory; <code>packpilot report"
            " --can-log</code> names it).</p>",
            [],
        )
    try:
        stats = read_can_log(path)
    except Exception as err:  # a truncated or foreign file: say so, do not fail the report
        return f'<p class="note">Cannot read the CAN log {esc(path)}: {esc(err)}.</p>', []
    return _tables(stats), [_rate_chart(stats, store)] if stats.ids else []


def _tables(stats: CanLogStats) -> str:
    ids = sorted(stats.ids.values(), key=lambda s: s.arbitration_id)
    first = min((s.times[0] for s in ids), default=math.nan)
    last = max((s.times[-1] for s in ids), default=math.nan)
    kv = [
        ("file", str(stats.path)),
        ("frames", f"{stats.frames:,}"),
        ("span", f"{fmt_num(first)} – {fmt_num(last)} s" if ids else "–"),
        ("error frames", str(stats.error_frames)),
        ("remote frames", str(stats.remote_frames)),
        ("frames the codec rejects", str(sum(s.malformed for s in ids))),
    ]
    rows = []
    for s in ids:
        gap, at = s.longest_gap()
        ident = f"0x{s.arbitration_id:08X}" if s.extended else f"0x{s.arbitration_id:03X}"
        rows.append(
            (
                ident,
                s.name,
                f"{s.frames:,}",
                f"{s.tx:,} / {s.rx:,}",
                fmt_num(s.rate_hz()),
                fmt_num(s.period_s()),
                "–" if math.isnan(gap) else f"{fmt_num(gap)} s from {fmt_num(at)} s",
                str(s.malformed),
            )
        )
    head = ("id", "message", "frames", "sent / received", "rate (Hz)", "median period (s)",
            "longest silence", "rejected")  # fmt: skip
    return table(None, kv, cls="kv") + table(head, rows, cls="counts")


RATE_WINDOW_MIN_S = 10.0
RATE_POINTS_MAX = 1500


def rate_window_s(span_s: float) -> float:
    """The averaging window of the rate chart: a whole number of seconds, at least 10 s and
    about 1/300 of the log. A window much longer than a frame period turns "0, 1, 2 frames in
    this bin" (a 1 Hz message counted in 1 s bins: a solid band) into its steady rate."""
    return float(max(RATE_WINDOW_MIN_S, math.ceil(span_s / 300.0)))


def _rate_chart(stats: CanLogStats, store: Store) -> Chart:
    """Frames per second of each id over time: frames in the trailing window (see
    :func:`rate_window_s`) divided by its length, on at most ``RATE_POINTS_MAX`` points."""
    all_t = np.concatenate([np.asarray(s.times) for s in stats.ids.values()])
    t0, t1 = float(all_t.min()), float(all_t.max())
    window = rate_window_s(t1 - t0)
    step = max((t1 - t0) / RATE_POINTS_MAX, 0.1)
    x = np.arange(t0 + window, t1 + step, step) if t1 - t0 > window else np.array([t1])
    x_key = store.add_raw("can/t", x, 1e-3)
    title = f"CAN frames per second, per id (mean over the last {window:g} s)"
    chart = Chart("can-rate", title, "1/s", height=150, x_key=x_key)
    ids = sorted(stats.ids.values(), key=lambda x: x.arbitration_id)
    top = 0.0
    for k, s in enumerate(ids):
        times = np.sort(np.asarray(s.times))
        n = np.searchsorted(times, x, side="right") - np.searchsorted(times, x - window, "right")
        key = store.add_raw(f"can/{s.arbitration_id}", n / min(window, max(t1 - t0, 1e-9)))
        # ids at the same rate draw the same line: later ones dashed, so each stays visible
        chart.series.append(Series(key, s.name, battery_color(k + 3), dash=k > 0, width=1.6))
        top = max(top, float(n.max(initial=0)) / min(window, max(t1 - t0, 1e-9)))
    chart.y_range = (0.0, max(top, 1e-3) * 1.2)  # from 0: a missed frame is a small dip
    return chart


__all__ = ["CanLogStats", "IdStats", "can_section", "read_can_log"]
