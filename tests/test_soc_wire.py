"""The SOC on the wire is the core's (issue #28): Pylontech's SOC, DroneCAN BatteryInfo's
``state_of_charge_pct`` (pack and each battery) and the platform's ``StateOfCharge`` frame
(0x232) carry the SOC the core uses, labelled by its source, decoded by the inverter, the
aircraft and the platform of the twin over a real python-can bus (lock-step). Before, every
frame carried the batteries' own reported SOC.

The core's SOC is made to differ from the batteries' by starting under load: the coulomb
counter initialises from the loaded cell voltage (below the rest voltage), the batteries
report their true SOC."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from packpilot.config.scenario import parse_config
from packpilot.contract.soc_source import SOURCES
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.lockstep import lockstep
from packpilot.runtime.publish import FALLBACK_STDEV_PCT, Channels

DT = 0.2


def _cfg(soc: dict[str, Any] | None) -> Any:
    data: dict[str, Any] = {
        "pack": {"name": "socwire", "cell": "uav_5ah", "ambient_c": 25.0,
                 "switch": {"kind": "mosfet_pair", "on_ohm": 0.0005},
                 "batteries": [
                     {"name": "A", "cells_per_group": 6, "soc0": 0.7, "resistance_ohm": 0.03},
                     {"name": "B", "cells_per_group": 6, "soc0": 0.68,
                      "resistance_ohm": 0.04, "capacity_ah": 4.0},
                 ]},
        "limits": {},
        "load": {"kind": "current", "value": 25.0},
        "sim": {"dt_s": DT, "duration_s": 200.0},
    }  # fmt: skip
    if soc is not None:
        data["soc"] = soc
    return parse_config(data, "test")


class Snap:
    """What the core had when the publisher last sent its frames (it sends once a second;
    the core moves on every period): each battery's SOC estimate, deviation and the
    batteries' own reported SOC and full capacity."""

    def __init__(self, ls: Any) -> None:
        self.ls = ls
        self.last: dict[str, np.ndarray] = {}
        pub = ls.bms.publisher
        send = pub.frames

        def frames(t: float) -> Any:
            ch, m = Channels(ls.bms.core), ls.bms.core.m
            self.last = {
                "est": np.array([ch.value("soc_est", i) for i in range(2)]),
                "sigma": np.array([ch.value("soc_sigma", i) for i in range(2)]),
                "ok": np.array([ch.value("soc_observer_ok", i) for i in range(2)]),
                "reported": np.asarray(m.bat.soc[0], np.float64).copy(),
                "full": np.asarray(m.bat.full_capacity_ah[0], np.float64).copy(),
            }
            return send(t)

        pub.frames = frames

    def run(self, seconds: float) -> None:
        """``seconds`` of periods, then on to the next publication and two periods more
        (the twin decodes what was sent in the following periods)."""
        for _ in range(round(seconds / DT)):
            self.ls.step(DT)
        pub = self.ls.bms.publisher
        due = pub.next_s
        while pub.next_s == due:
            self.ls.step(DT)
        for _ in range(2):
            self.ls.step(DT)


def _start(cfg: Any, wrong: float = 0.0) -> tuple[Any, Snap]:
    """A lock-step run whose SOC estimator starts ``wrong`` below the truth (the
    acceptance's wrong initial SOC; the observer starts from it)."""
    ls = lockstep(cfg, RuntimeOptions(allow_unmonitored=True))
    if wrong:
        part = next(x for x in ls.bms.core.compiled if x.method.name == "soc")
        part.st.soc[0, :] = np.array([0.7, 0.68]) - wrong
    return ls, Snap(ls)


def _check_frames(ls: Any, soc: np.ndarray, full: np.ndarray) -> None:
    """Every frame carries ``soc`` (per battery) and its capacity-weighted pack figure."""
    pack = 100.0 * float(np.sum(soc * full) / np.sum(full))
    assert ls.hil.soc["Soc"] == pytest.approx(pack, abs=0.006)  # 0.01 % counts
    assert ls.hil.inverter.last["Pylon_SocSoh"]["SOC"] == pytest.approx(pack, abs=0.51)
    air = ls.hil.aircraft.last
    assert air[0].soc_pct == pytest.approx(pack, abs=0.51)
    for i in (1, 2):
        assert air[i].soc_pct == pytest.approx(100.0 * soc[i - 1], abs=0.51)


def test_the_frames_carry_the_fallback_then_the_observer_labelled() -> None:
    ls, snap = _start(_cfg({}), wrong=0.10)
    try:
        snap.run(5.0)
        got = snap.last
        assert list(got["ok"]) == [0.0, 0.0]  # the observer is settling: its fallback's SOC
        # the core's SOC is 10 % below the batteries' own: a frame carrying theirs fails
        assert np.all(got["reported"] - got["est"] > 0.05)
        _check_frames(ls, got["est"], got["full"])
        assert ls.hil.soc["Source"] == SOURCES.index("fallback")
        assert ls.hil.soc["Fallback"] == 2 and ls.hil.soc["Observed"] == 0
        assert math.isnan(ls.hil.soc["SocStdev"])  # not the observer's: no deviation claimed
        assert all(ls.hil.aircraft.last[i].soc_stdev_pct == FALLBACK_STDEV_PCT for i in (0, 1, 2))
        snap.run(70.0)  # past the observer's 60 s window: trusted
        got = snap.last
        assert list(got["ok"]) == [1.0, 1.0]
        _check_frames(ls, got["est"], got["full"])
        assert ls.hil.soc["Source"] == SOURCES.index("observer")
        assert ls.hil.soc["Observed"] == 2 and ls.hil.soc["Fallback"] == 0
        w = got["full"] / got["full"].sum()
        sd = 100.0 * math.sqrt(float(np.sum((w * got["sigma"]) ** 2)))
        assert ls.hil.soc["SocStdev"] == pytest.approx(sd, abs=0.006)
        for i in (1, 2):
            want = max(1, math.ceil(100.0 * got["sigma"][i - 1] - 1e-9))
            assert ls.hil.aircraft.last[i].soc_stdev_pct == want
    finally:
        ls.close()


def test_without_an_estimator_the_frames_say_it_is_the_batterys_own() -> None:
    ls, snap = _start(_cfg(None))
    try:
        snap.run(5.0)
        got = snap.last
        assert np.all(np.isnan(got["est"]))
        _check_frames(ls, got["reported"], got["full"])
        assert ls.hil.soc["Source"] == SOURCES.index("battery")
        assert ls.hil.soc["Observed"] == 0 and ls.hil.soc["Fallback"] == 0
    finally:
        ls.close()
