"""The compiled discharge protection against the scalar oracle it replaced (see ``common.py``).

Open loop: Hypothesis-drawn measurement sequences (NaN / inf readings, absent and unreported
batteries, time going backwards, zero / negative / NaN and odd fractional dt) under configs
that reach every rule: the spec's table, fast trips, hysteresis + filters + reset on recovery +
strict comparisons, a three-axis table with SOH, a one-row table. Closed loop: the shipped
protection examples and a fault-injection flight on the real plant, both controllers fed the
same measurements every step. Commands, events and status must be equal at every step.
"""

from __future__ import annotations

import math
from dataclasses import replace
from fractions import Fraction
from pathlib import Path
from typing import Any, ClassVar

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from packpilot.config import load_config, parse_config
from packpilot.config.protection import ProtectionConfig, TableRow
from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.protection import ProtectionController, rules
from packpilot.control.registry import REGISTRY
from packpilot.sim.runner import Runner
from tests.conftest import dual_pack
from tests.equivalence.common import DTS, assert_same_output, sequence
from tests.oracles.protection import ProtectionController as Oracle

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _rows(*rows: tuple[str, dict[str, str]]) -> tuple[TableRow, ...]:
    return tuple(TableRow.model_validate({"param": p, "ranges": r}) for p, r in rows)


def _params(*ps: tuple[str, float, float]) -> list[dict[str, Any]]:
    return [{"name": n, "cutoff_v": v, "t_max_s": t} for n, v, t in ps]


FAST = _params(("P1", 2.8, 1.5), ("P2", 3.0, 1.0), ("P3", 3.2, 0.5))
_SOH_ROWS = [
    (name, {"soh": soh, "temp_c": t, "current_a": "(-inf, inf)"})
    for name, soh in (("P1", "(-inf, 0.8)"), ("P3", "[0.8, inf)"))
    for t in ("(-inf, 5)", "[5, inf)")
]
CONFIGS: dict[str, ProtectionConfig] = {
    "default": ProtectionConfig(),
    "fast": ProtectionConfig.model_validate({"parameters": FAST}),
    "options": ProtectionConfig.model_validate(
        {
            "parameters": FAST,
            "hysteresis": {"current_a": 2.0, "temp_c": 5.0},
            "filter_tau_s": {"current_a": 0.7, "temp_c": 3.0},
            "reset_on_recovery": True,
            "reset_on_reinsert": False,
            "voltage_comparison": "<",
            "trip_comparison": ">",
            "charge_detect_s": 0.5,
            "charge_threshold_a": 2.0,
            "discharge_threshold_a": 0.0,
        }
    ),
    "soh": ProtectionConfig(
        parameters=ProtectionConfig.model_validate({"parameters": FAST}).parameters,
        table=_rows(*_SOH_ROWS),
        filter_tau_s={"soh": 2.0},
        hysteresis={"soh": 0.05},
        charge_detect_s=0.0,
    ),
    "one_row": ProtectionConfig.model_validate(
        {"parameters": _params(("fixed", 3.1, 0.7)), "table": [{"param": "fixed"}]}
    ),
    "ties": ProtectionConfig.model_validate(  # equal cut-offs: the shorter t_max must win
        {
            "parameters": _params(("A", 3.2, 1.0), ("B", 3.2, 0.5), ("C", 3.0, 2.0)),
            "table": [
                {"param": "A", "ranges": {"temp_c": "(-inf, 10)"}},
                {"param": "B", "ranges": {"temp_c": "[10, 30)"}},
                {"param": "C", "ranges": {"temp_c": "[30, inf)"}},
            ],
        }
    ),
    "odd_weights": ProtectionConfig.model_validate(
        {
            "parameters": _params(("a", 3.0, 1.5), ("b", 3.1, 2.0), ("c", 3.2, 0.7)),
            "table": [
                {"param": "a", "ranges": {"current_a": "(-inf, 5]"}},
                {"param": "b", "ranges": {"current_a": "(5, 20)"}},
                {"param": "c", "ranges": {"current_a": "[20, inf)"}},
            ],
        }
    ),
}
ODD_DTS = (*DTS, 1 / 3, 1 / 7, 0.0137, 1e-3, 2.5e-4, 1e-300, 1e-7, 0.0015, 2 / 3, 7.0)


def _info(n: int, groups: int, cells: int) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(groups,) * n,
        cells_per_group=(cells,) * n,
        switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
        capacity_ah=tuple(5.0 + 0.5 * i for i in range(n)),
    )


# ------------------------------------------------------------------------------ dt snapping


def _reference_ms(dt: float) -> tuple[int, int]:
    f = Fraction(dt * 1000.0).limit_denominator(1000)
    return f.numerator, f.denominator


@settings(max_examples=2000, deadline=None)
@given(
    dt=st.one_of(
        st.floats(0.0, 1e12, allow_nan=False, allow_subnormal=True),
        st.floats(0.0, 1e-3, allow_subnormal=True),
        st.floats(0.0, 10.0),
        st.integers(1, 10**6).map(lambda k: k / 997.0),
        st.integers(1, 10**5).map(lambda k: k / 3.0),
    )
)
@example(dt=1e-300)
@example(dt=5e-324)
@example(dt=1 / 2_000_000)
@example(dt=0.5 / 1000 / 1000)
@example(dt=1 / 3)
@example(dt=0.1)
@example(dt=0.00031128626493226084)  # floor(den / dd) == 2 * qk: the bound comparison
@example(dt=2.0**62 / 1000.0 * 0.999)
def test_dt_snapping_is_cpython_limit_denominator(dt: float) -> None:
    if not dt * 1000.0 < 2.0**62:
        assert rules.dt_ms(dt) == (-1, 1)
        return
    assert rules.dt_ms(dt) == _reference_ms(dt)


def test_huge_dt_saturates_and_trips_instead_of_overflowing() -> None:
    info = _info(1, 6, 1)
    ctl = ProtectionController(ProtectionConfig(), info)
    bm = _bm(10.0, 25.0, 3.1)
    for dt in (1e300, math.inf, 1e20):
        c = ProtectionController(ProtectionConfig(), info)
        out = c.step(Measurements(t_s=0.0, batteries=(bm,), bus_v=18.6), dt)
        if dt == math.inf:  # not a finite dt: counts as 0
            assert out.commands.dsg_on == (None,)
        else:
            assert out.commands.dsg_on == (False,)
            (ev,) = out.events
            assert ev.kind == "ProtectionTripped" and ev.data["accumulated_s"] == 2.0**53 / 1000
    # a tiny dt counts as 0 ms, as Fraction.limit_denominator(1000) has it
    ctl.step(Measurements(t_s=0.0, batteries=(bm,), bus_v=18.6), 1e-300)
    assert ctl.fraction(0) == 0.0


def test_coprime_fractional_ticks_round_up_instead_of_overflowing() -> None:
    """Durations k/p ms for many primes p: the exact denominator outgrows int64; the sum is
    then rounded up to weighted microseconds and keeps counting (and trips) without error."""
    cfg = ProtectionConfig.model_validate(
        {"parameters": _params(("fixed", 3.2, 0.2)), "table": [{"param": "fixed"}]}
    )
    ctl = ProtectionController(cfg, _info(1, 6, 1))
    primes = [p for p in range(500, 1000) if all(p % d for d in range(2, 32))]
    exact = Fraction(0)
    t = 0.0
    tripped_at = None
    for k, p in enumerate(primes * 3):
        dt = 1.0 / p  # seconds: 1000/p ms
        out = ctl.step(Measurements(t_s=t, batteries=(_bm(10.0, 25.0, 3.1),), bus_v=18.6), dt)
        t += dt
        exact += Fraction(dt * 1000.0).limit_denominator(1000)
        got = ctl.battery(0).acc_wms
        if tripped_at is None:
            assert got >= exact and got - exact <= Fraction(k + 1, 1000)
        if any(e.kind == "ProtectionTripped" for e in out.events):
            tripped_at = exact
    assert exact.denominator > 2**53  # the exact sum did not fit
    assert ctl.battery(0).tripped and tripped_at is not None
    assert 200 - 1 <= tripped_at <= 200 + 2  # m = 200 ms; ticks of 1 to 2 ms


# ------------------------------------------------------------------------------ open loop


@settings(max_examples=300, deadline=None)
@given(
    data=st.data(),
    name=st.sampled_from(sorted(CONFIGS)),
    n=st.integers(1, 3),
    groups=st.integers(1, 4),
    cells=st.sampled_from([1, 2]),
    odd_dt=st.booleans(),
)
def test_same_as_the_scalar_protection(
    data: Any, name: str, n: int, groups: int, cells: int, odd_dt: bool
) -> None:
    cfg = CONFIGS[name]
    info = _info(n, groups, cells)
    new = ProtectionController(cfg, info)
    old = Oracle(cfg, info)
    seq = data.draw(
        sequence(n, groups, steps=80, dts=ODD_DTS if odd_dt else DTS, v_cell=(2.6, 3.6))
    )
    for k, (meas, dt) in enumerate(seq):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"{name} step {k}")
        if k % 7 == 3 and data.draw(st.integers(0, 9)) == 0:  # host starts a new cycle
            new.start_new_cycle(0)
            old.start_new_cycle(0)
        _same_accessors(new, old, n)


def _same_accessors(new: ProtectionController, old: Oracle, n: int) -> None:
    assert new.m_s == old.m_s and new.weights() == old.weights()
    for i in range(n):
        a, b = new.battery(i), old.state.batteries[i]
        assert (a.acc_wms, a.tripped, a.row, a.discharging) == (
            b.acc_wms,
            b.tripped,
            b.row,
            b.discharging,
        )
        assert (a.absent, a.charge_cycle_started, a.faults) == (
            b.absent,
            b.charge_cycle_started,
            frozenset(b.faults),
        )
        assert new.parameter(i) == old.parameter(i)
        assert new.fraction(i) == old.fraction(i)


def _bm(current_a: float, temp_c: float, v: float) -> Any:
    from packpilot.contract.bms import BatteryMeasurement

    return BatteryMeasurement(
        voltage_v=6 * v,
        current_a=current_a,
        temp_c=temp_c,
        min_cell_v=v,
        max_cell_v=v,
        soc=0.1,
        full_capacity_ah=5.0,
        remaining_capacity_ah=0.5,
    )


def _bm_full(
    current_a: float,
    temp_c: float,
    v: float,
    *,
    min_cell_v: float | None = None,
    voltage_v: float | None = None,
    present: bool = True,
) -> Any:
    from packpilot.contract.bms import BatteryMeasurement

    return BatteryMeasurement(
        voltage_v=6 * v if voltage_v is None else voltage_v,
        current_a=current_a,
        temp_c=temp_c,
        min_cell_v=v if min_cell_v is None else min_cell_v,
        max_cell_v=v,
        soc=0.1,
        full_capacity_ah=5.0,
        remaining_capacity_ah=0.5,
        present=present,
    )


SCRIPTS: dict[str, tuple[str, int, int, list[tuple[Any, float]]]] = {
    # (config, groups, cells per group, [(battery measurement, dt)])
    "absence_restarts_charge_detection": (
        "options",
        6,
        1,
        [
            (_bm_full(10.0, 25.0, 3.1), 0.2),  # accumulates under P3
            (_bm_full(-5.0, 25.0, 3.3), 0.3),  # charging 0.3 s of the 0.5 s needed
            (_bm_full(-5.0, 25.0, 3.3, present=False), 0.1),
            (_bm_full(-5.0, 25.0, 3.3), 0.3),  # 0.3 s again: not yet a new cycle
            (_bm_full(-5.0, 25.0, 3.3), 0.3),  # 0.6 s: a new cycle
        ],
    ),
    "mean_cell_counts_series_cells": (
        "default",
        3,
        2,
        [
            (_bm_full(10.0, 25.0, 3.1, min_cell_v=math.nan, voltage_v=6 * 3.1), 1.0),
            (_bm_full(10.0, 25.0, 3.3, min_cell_v=math.nan, voltage_v=6 * 3.3), 1.0),
        ]
        * 3,
    ),
    "equal_cutoffs_take_the_shorter_t_max": (
        "ties",
        6,
        1,
        [(_bm_full(10.0, math.nan, 3.1), 0.1)] * 3 + [(_bm_full(10.0, 5.0, 3.1), 0.1)] * 4,
    ),
}


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_scripted_edges(script: str) -> None:
    """Hand-made sequences for rules the random sequences rarely reach."""
    name, groups, cells, rows = SCRIPTS[script]
    info = _info(1, groups, cells)
    new = ProtectionController(CONFIGS[name], info)
    old = Oracle(CONFIGS[name], info)
    t = 0.0
    for k, (bm, dt) in enumerate(rows):
        meas = Measurements(t_s=t, batteries=(bm,), bus_v=20.0)
        assert_same_output(new.step(meas, dt), old.step(meas, dt), 1, f"{script} step {k}")
        _same_accessors(new, old, 1)
        t += dt


# ------------------------------------------------------------------------------ closed loop


class Twin:
    """Runs the compiled controller and the oracle on the same measurements; the loop is
    closed through the compiled one. Counts steps, events and trips seen."""

    seen: ClassVar[list[dict[str, int]]] = []

    def __init__(self, config: ProtectionConfig, pack: PackInfo) -> None:
        self.new = ProtectionController(config, pack)
        self.old = Oracle(config, pack)
        self.n = pack.n_batteries
        self.stats = {"steps": 0, "events": 0, "trips": 0, "faults": 0, "resets": 0}
        Twin.seen.append(self.stats)

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        out = self.new.step(meas, dt_s)
        ref = self.old.step(meas, dt_s)
        k = self.stats["steps"]
        assert_same_output(out, ref, self.n, f"t={meas.t_s} step {k}")
        self.stats["steps"] += 1
        self.stats["events"] += len(out.events)
        for e in out.events:
            key = {"ProtectionTripped": "trips", "Fault": "faults", "ProtectionReset": "resets"}
            self.stats[key[e.kind]] += 1
        return out


def _run_twin(cfg: Any, monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """Run ``cfg`` with the protection part replaced by a :class:`Twin` (a Python part of the
    core, at P = 1), everything else as the scenario has it."""
    twin = replace(REGISTRY["protection"], target="tests.equivalence.test_protection:Twin")
    monkeypatch.setitem(REGISTRY, "protection", twin)
    Twin.seen.clear()
    Runner(cfg, progress=False).run()
    (stats,) = Twin.seen
    return stats


@pytest.mark.parametrize(
    ("scenario", "protection"),
    [
        ("cold_heavy", None),
        ("warm_light", None),
        ("warming_flight", None),
        (
            "warming_flight",
            {
                "hysteresis": {"current_a": 1.0, "temp_c": 0.5},
                "filter_tau_s": {"current_a": 2.0, "temp_c": 10.0},
                "reset_on_recovery": True,
                "trip_comparison": ">",
                "voltage_comparison": "<",
            },
        ),
    ],
)
def test_closed_loop_examples(
    scenario: str, protection: dict[str, Any] | None, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = load_config(EXAMPLES / f"protection_{scenario}.toml")
    update: dict[str, Any] = {"sim": cfg.sim.model_copy(update={"stop_when_unsupplied_s": 20.0})}
    if protection is not None:
        update["protection"] = ProtectionConfig.model_validate(protection)
    stats = _run_twin(cfg.model_copy(update=update), monkeypatch)
    assert stats["trips"] == 1 and stats["steps"] > 1000


def test_closed_loop_with_injected_faults(monkeypatch: pytest.MonkeyPatch) -> None:
    """A dual-battery flight under the supervisor with NaN cell and temperature readings and a
    dropped-out battery (re-inserted: a new cycle)."""
    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=21.0,
        v_b=20.8,
        duration_s=240.0,
        load={"kind": "current", "value": 30.0},
    )
    d["controller"] = ["sequencing", "protection"]
    d["supervisor"] = {}
    d["limits"] = {}
    d["plausibility"] = {"stuck_time_s": 10.0}
    d["protection"] = {"parameters": FAST}
    d["faults"] = [
        {
            "kind": "sensor_nan",
            "at_s": 5.0,
            "until_s": 30.0,
            "battery": "A",
            "quantity": "min_cell_v",
        },
        {"kind": "sensor_nan", "at_s": 20.0, "until_s": 40.0, "battery": "B", "quantity": "temp_c"},
        {
            "kind": "sensor_nan",
            "at_s": 50.0,
            "until_s": 60.0,
            "battery": "B",
            "quantity": "current_a",
        },
        {"kind": "sensor_dropout", "at_s": 70.0, "until_s": 90.0, "battery": "A"},
    ]
    stats = _run_twin(parse_config(d), monkeypatch)
    assert stats["faults"] >= 3 and stats["steps"] > 100


@pytest.mark.parametrize(
    ("example", "update", "expect"),
    [
        (  # flight, landing, docking, staged charging under the supervisor: trips, then
            # the charge starts new cycles
            "uav_mission.toml",
            {
                "duration_s": 1500.0,
                "protection": {
                    "parameters": _params(("hi", 3.75, 900.0), ("lo", 3.6, 300.0)),
                    "table": [
                        {"param": "hi", "ranges": {"current_a": "(-inf, 10]"}},
                        {"param": "lo", "ranges": {"current_a": "(10, inf)"}},
                    ],
                },
            },
            {"trips": 2, "resets": 2},
        ),
        (  # a battery inserted at 300 s (absent before)
            "sequencing_hot_insert.toml",
            {
                "duration_s": 900.0,
                "controller": ["sequencing", "protection"],
                "protection": {
                    "parameters": _params(("hi", 4.0, 600.0)),
                    "table": [{"param": "hi"}],
                },
            },
            {},
        ),
    ],
)
def test_closed_loop_composed(
    example: str, update: dict[str, Any], expect: dict[str, int], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = load_config(EXAMPLES / example)
    upd = dict(update)
    upd["sim"] = cfg.sim.model_copy(update={"duration_s": upd.pop("duration_s")})
    upd["protection"] = ProtectionConfig.model_validate(upd["protection"])
    stats = _run_twin(cfg.model_copy(update=upd), monkeypatch)
    assert stats["steps"] > 5000
    for key, n in expect.items():
        assert stats[key] == n, stats
