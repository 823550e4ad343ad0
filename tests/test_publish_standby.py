"""Issue #24 item 1: what the aircraft is told about the soonest trip while a battery stands by.

A battery in sequencing's STANDBY predicts no time to trip (NaN). The 0x230 protection frame
carries the soonest time to trip over the batteries that have one, whichever order the pack
lists them in: with the standby battery first, Python's ``min`` kept the NaN and the frame read
0xFFFF ("none") while the discharging battery's trip was counting down.

The closed loop is the demo's pack (``examples/uav_mission.toml``: B, at 80 % SOC, stands by
while A hovers), run lock-step against the twin over a real python-can bus, in the file's
order and with the batteries swapped.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from packpilot.cli import scenario_path
from packpilot.config import ScenarioConfig, load_config
from packpilot.runtime.lockstep import lockstep
from packpilot.runtime.publish import Channels, latest, soonest

DT = 0.2
END_S = 40.0


def _cfg(swap: bool) -> ScenarioConfig:
    cfg = load_config(scenario_path(Path("uav_mission")))
    if not swap:
        return cfg
    pack = cfg.pack.model_copy(update={"batteries": list(reversed(cfg.pack.batteries))})
    return cfg.model_copy(update={"pack": pack})


def _frames(swap: bool) -> list[tuple[float, list[float], float]]:
    """(t, per-battery predicted time to trip in the core, TimeToTrip the 0x230 frame carried)
    for every period in which the publisher sent the protection frame."""
    ls = lockstep(_cfg(swap))
    ch = Channels(ls.bms.core)
    n = ls.bms.core.m.bat.reported.shape[1]
    out = []
    try:
        for _ in range(round(END_S / DT)):
            t, sent = ls.hil.t_s, ls.bms.publisher.sent
            ls.step(DT)
            if ls.bms.publisher.sent == sent:
                continue
            per = [ch.value("protection_time_to_trip_s", i) for i in range(n)]
            out.append((t, per, float(ls.hil.protection["TimeToTrip"])))
    finally:
        ls.close()
    return out


@pytest.mark.parametrize("swap", [False, True], ids=["file_order", "standby_first"])
def test_time_to_trip_frame_ignores_the_standby_battery_in_both_orders(swap: bool) -> None:
    frames = _frames(swap)
    standby = 0 if swap else 1  # B, the battery at 80 % SOC, stands by while A hovers
    mixed = [
        (t, per, got)
        for t, per, got in frames
        if math.isnan(per[standby]) and math.isfinite(per[1 - standby])
    ]
    # The case of the issue happens in the run: B stands by (NaN), A predicts a time.
    assert len(mixed) >= 10
    for t, per, got in mixed:
        want = per[1 - standby]
        if want < 65535.0:  # beyond the frame's range it reads "none / beyond" by definition
            assert got == pytest.approx(want, abs=0.5), (t, per, got)
    # Whenever any battery predicts a time, the frame carries the soonest one.
    for t, per, got in frames:
        want = soonest(per)
        if math.isfinite(want) and want < 65535.0:
            assert got == pytest.approx(want, abs=0.5), (t, per, got)


@pytest.mark.parametrize(
    "times",
    [[math.nan, 2.0], [2.0, math.nan], [math.nan, 7.0, 2.0], [7.0, math.nan, 2.0, math.nan]],
)
def test_soonest_and_latest_skip_nan_wherever_it_stands(times: list[float]) -> None:
    assert soonest(times) == 2.0
    assert latest(times) == max(x for x in times if math.isfinite(x))


def test_soonest_of_no_prediction_is_none() -> None:
    assert math.isnan(soonest([math.nan, math.nan]))
    assert math.isnan(latest([]))
