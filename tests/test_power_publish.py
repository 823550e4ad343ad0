"""State of power on the wire (issue #28 item 3): the Pylontech CCL/DCL, the StateOfPower frame
(0x231) and DroneCAN BatteryPeriodic carry the core's prediction, decoded by the inverter, the
platform and the aircraft of the twin over a real python-can bus (lock-step)."""

from __future__ import annotations

import math
import time

import pytest

from packpilot.config.scenario import parse_config
from packpilot.runtime.bms import RuntimeOptions
from packpilot.runtime.lockstep import lockstep
from packpilot.runtime.publish import HORIZON_CCL, Channels


def _cfg(soc: float) -> object:
    return parse_config({
        "pack": {"name": "sop", "cell": "uav_5ah", "ambient_c": 25.0,
                 "switch": {"kind": "mosfet_pair", "on_ohm": 0.0005},
                 "batteries": [
                     {"name": "A", "cells_per_group": 6, "soc0": soc, "resistance_ohm": 0.02},
                     {"name": "B", "cells_per_group": 6, "soc0": soc - 0.05,
                      "resistance_ohm": 0.036, "capacity_ah": 4.0},
                 ]},
        "limits": {}, "soc": {},
        "load": {"kind": "current", "value": 20.0},
        "sim": {"dt_s": 0.2, "duration_s": 4.0},
    }, "test")  # fmt: skip


def test_the_wire_carries_the_state_of_power_and_ccl_dcl_follow_it() -> None:
    ls = lockstep(_cfg(0.25), RuntimeOptions(allow_unmonitored=True))  # type: ignore[arg-type]
    try:
        for _ in range(12):
            ls.step(0.2)
        pub = ls.bms.publisher
        # the state of power is computed on a worker thread and published once finished: wait
        # for it in wall time (interpreted, as the mutation runner runs it, it takes seconds)
        deadline = time.monotonic() + 120.0
        while pub.sop is None and time.monotonic() < deadline:
            ls.step(0.2)
        sop = pub.sop
        assert sop is not None
        # the platform frame: 2 / 10 / 30 s discharge, 10 s charge, 0.1 A counts
        got = ls.hil.power
        for name, want in (("Dcl2s", sop.pack_dsg_a[0, 0]), ("Dcl10s", sop.pack_dsg_a[0, 1]),
                           ("Dcl30s", sop.pack_dsg_a[0, 2]), ("Ccl10s", sop.pack_chg_a[0, 1])):
            assert got[name] == pytest.approx(want, abs=0.051), name
        assert sop.pack_dsg_a[0, 0] >= sop.pack_dsg_a[0, 2] > 0.0
        # Pylontech: the smaller of the limits layer's and the 30 s state of power
        limits_dcl = Channels(ls.bms.core).value("pack_limit_dsg_a")
        limits_ccl = Channels(ls.bms.core).value("pack_limit_chg_a")
        told = ls.hil.inverter.last["Pylon_Limits"]
        sop_dcl = float(sop.pack_dsg_a[0, HORIZON_CCL])
        assert told["DischargeCurrentLimit"] == pytest.approx(min(limits_dcl, sop_dcl), abs=0.051)
        assert told["ChargeCurrentLimit"] == pytest.approx(
            min(limits_ccl, float(sop.pack_chg_a[0, HORIZON_CCL])), abs=0.051
        )
        # the split, not N x the weakest battery's table limit, sets the pack's limit
        assert sop_dcl < limits_dcl - 5.0
        assert told["DischargeCurrentLimit"] < limits_dcl - 5.0
        # DroneCAN: BatteryPeriodic's 30 s burst is the 30 s state of power (float32)
        per = ls.hil.aircraft.periodic
        assert per is not None
        assert per.discharge_maximum_burst_current_a == pytest.approx(sop_dcl, rel=1e-6)
        assert per.discharge_maximum_current_a == pytest.approx(
            told["DischargeCurrentLimit"], abs=0.051
        )
        assert per.cells_in_series == 6
        assert per.discharge_minimum_voltage_v == pytest.approx(2.7, abs=2e-3)  # float16
        # what went out is the prediction from the core's own state (SOC method, feedback)
        ch = Channels(ls.bms.core)
        assert all(math.isfinite(ch.value("soc_est", i)) for i in range(2))
        again = pub.state_of_power()
        assert again is not None
        assert again.pack_dsg_a[0, 1] == pytest.approx(sop.pack_dsg_a[0, 1], rel=0.02)
    finally:
        ls.close()

