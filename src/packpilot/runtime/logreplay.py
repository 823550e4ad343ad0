"""Re-run the BMS over a recorded frame log (BLF / ASC written by ``run`` or ``hil``).

Every frame the BMS *received* in the recording (``is_rx``) goes back onto a private virtual
bus at its recorded time; the runtime steps every ``period_s`` of the recording's clock, as
fast as the CPU goes, and reads them as it read them live (a frame belongs to the period
whose start it is within half a period of: a recording's clock sums its periods and rounds).
The BMS's own frames of the recording are not replayed: it sends them anew, so a changed
configuration (a threshold, a method) shows what it would have done with the same telemetry.
Frame times are the recording's simulation / runtime seconds, written as ``SIM_EPOCH_S + t``
(``docs/can.md``).
"""

from __future__ import annotations

import itertools
import math
import struct
import zlib
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path

import can

from packpilot.config import ScenarioConfig
from packpilot.contract.record import Recorder
from packpilot.errors import ConfigError
from packpilot.io.can.bus import LOG_SUFFIXES, SIM_EPOCH_S, open_bus
from packpilot.runtime.bms import BmsRuntime, RuntimeOptions

_channels = itertools.count()


def received_frames(path: Path) -> list[tuple[float, can.Message]]:
    """(t_s, frame) of every received frame of a log, in time order."""
    suffix = path.suffix.lower()
    if suffix not in LOG_SUFFIXES:
        raise ConfigError(f"{path}: unsupported frame log format {suffix!r}, use .blf/.asc")
    frames: list[tuple[float, can.Message]] = []
    try:
        reader: Iterable[can.Message]
        if suffix == ".asc":
            reader = can.ASCReader(path, relative_timestamp=False)
        else:
            reader = can.BLFReader(path)
        it = iter(reader)
        while True:
            try:
                m = next(it)
            except StopIteration:
                break
            except (ValueError, EOFError, struct.error, zlib.error):
                break  # a log cut short by a killed writer: keep what was written whole
            if m.is_rx:
                frames.append((m.timestamp - SIM_EPOCH_S, m))
    except (OSError, ValueError, EOFError, struct.error) as err:
        raise ConfigError(f"{path}: cannot read the frame log ({err})") from None
    frames.sort(key=lambda x: x[0])
    return frames


def periods(frames: list[tuple[float, can.Message]], period_s: float) -> int:
    """How many periods of ``period_s`` from 0 s the replay steps over the frames' times."""
    t_end = frames[-1][0]
    if not (math.isfinite(t_end) and t_end + period_s / 2 >= 0.0):
        return 0
    return math.floor((t_end + period_s / 2) / period_s + 1e-9) + 1


def replay_log(
    cfg: ScenarioConfig,
    path: Path,
    opts: RuntimeOptions | None = None,
    recorder: Recorder | None = None,
) -> BmsRuntime:
    """The BMS of ``cfg`` over the received frames of ``path``; returns the (closed) runtime
    with its events and metrics."""
    frames = received_frames(path)
    if not frames:
        raise ConfigError(f"{path}: the log holds no frame the BMS received: nothing to replay")
    opts_period = (opts or RuntimeOptions()).period_s
    if periods(frames, opts_period) == 0:
        raise ConfigError(
            f"{path}: no period to replay: its frames end at {frames[-1][0]:.6g} s, before the "
            "recording's 0 s (a BLF whose header was never written, e.g. by a writer killed "
            "before it flushed)"
        )
    channel = f"packpilot-replay-{next(_channels)}"
    opts = replace(opts or RuntimeOptions(), interface="virtual", channel=channel,
                   charger_channel=None, log_path=None, bus_kwargs=())  # fmt: skip
    feeder = open_bus("virtual", channel)
    bms = BmsRuntime(cfg, opts, recorder)
    period = opts.period_s
    try:
        t_end = frames[-1][0]
        j, k = 0, 0
        while True:
            t = k * period
            if t > t_end + period / 2:
                break
            while j < len(frames) and frames[j][0] <= t + period / 2:  # a clock's rounding
                feeder.send(frames[j][1])
                j += 1
            bms.step(t, period)
            k += 1
        if recorder is not None:
            recorder.finish(bms.metrics())
    finally:
        bms.close()
        feeder.shutdown()
    return bms


__all__ = ["received_frames", "replay_log"]
