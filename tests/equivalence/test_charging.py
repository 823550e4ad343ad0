"""The compiled staged-charging method against the scalar oracle it replaced (``common.py``).

Three kinds of input, each compared at every step (commands, events, status):

* garbage: the shared random sequences (``common.sequence``) under a per-cell config whose
  volts fit their 2.5-4.3 V cells;
* charging-shaped: batteries with an OCV, an ohmic R and a relaxing polarization, placed on
  voltage levels around the config's thresholds (exact boundary values included), their
  currents stepping and holding (the R estimate and its settle windows), with NaN / absent /
  not-present batteries, undocking, charger status missing / offline / flagged, an aux
  battery around its SOC floor and target, and odd ``dt``;
* closed loops: the toy plant of the behavioural tests and the real plant (the runner on the
  eVTOL charging bus with faults injected, and the whole UAV mission under the supervisor).
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace
from pathlib import Path
from typing import Any, ClassVar

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from packpilot.config import load_config, parse_config
from packpilot.config.charging import ChargingConfig
from packpilot.contract.bms import (
    BatteryMeasurement,
    ControlOutput,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.charger import CHARGER_FLAGS, ChargerStatus
from packpilot.contract.topology import PackInfo
from packpilot.control.charging import ChargingController, Volts
from packpilot.control.registry import REGISTRY
from packpilot.sim.runner import Runner
from tests.equivalence.common import WEIRD, assert_same_output, sequence
from tests.oracles.charging import ChargingController as Oracle
from tests.test_charging_helpers import ToyPack, pack_info

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"

# --------------------------------------------------------------------------- configurations

CELL = {
    "voltage_basis": "cell",
    "v_sat_v": 4.1,
    "delta_v1_v": 0.1,
    "d1_v": 0.03,
    "eps_eq_v": 0.02,
    "reach_tol_v": 0.02,
    "overvoltage_margin_v": 0.05,
    "cell_v_limit_v": 4.25,
    "charger_current_limit_a": 20.0,
    "termination_current_a": 1.0,
    "dock_rest_s": 1.0,
    "charger_status_timeout_s": 2.0,
    "charger_fault_clear_s": 1.0,
    "r_settle_s": 2.0,
}
"""Per-cell volts for ``common.sequence``'s batteries (the other voltages default to /30)."""

CONFIGS: dict[str, dict[str, Any]] = {
    "binary": {
        "v_sat_v": 16.0,
        "delta_v1_v": 1.0,
        "d1_v": 0.375,
        "vc1_margin_v": 0.5,
        "vc3_margin_v": 0.25,
        "step_v": 1.0,
        "delta_v2_v": 2.0,
        "eps_eq_v": 0.25,
        "reach_tol_v": 0.125,
        "overvoltage_margin_v": 0.5,
        "cell_v_limit_v": 4.5,
        "charger_current_limit_a": 20.0,
        "termination_current_a": 1.0,
        "r_settle_s": 2.0,
        "dock_rest_s": 2.0,
        "charger_status_timeout_s": 2.0,
        "charger_fault_clear_s": 2.0,
        "aux_soc_floor": 0.25,
        "aux_soc_target": 0.875,
        "aux_soc_hysteresis": 0.125,
        "aux_cv_v": 14.5,
        "aux_cv_band_v": 0.25,
    },
    "battery": {
        "v_sat_v": 16.0,
        "delta_v1_v": 0.6,
        "d1_v": 0.2,
        "vc1_margin_v": 0.3,
        "step_v": 1.0,
        "delta_v2_v": 1.0,
        "eps_eq_v": 0.1,
        "reach_tol_v": 0.1,
        "overvoltage_margin_v": 0.2,
        "cell_v_limit_v": 4.2,
        "charger_current_limit_a": 20.0,
        "termination_current_a": 1.0,
        "r_comp_initial_ohm": 0.02,
        "r_settle_s": 2.0,
        "dock_rest_s": 1.0,
        "charger_status_timeout_s": 2.0,
        "charger_fault_clear_s": 1.5,
    },
    "cell_saturation_sqrt": {
        **CELL,
        "target_mode": "saturation",
        "current_law": "sqrt",
        "full_current_a": 30.0,
        "battery_current_limit_a": 6.0,
        "vc2_margin_v": 0.01,
        "vc3_margin_v": 0.02,
        "r_est_gain": 1.0,
        "r_settle_max_ratio": 1.5,
    },
    "cell_fixed_r": {
        **CELL,
        "r_comp_adapt": False,
        "r_comp_initial_ohm": 0.05,
        "battery_current_limit_a": 3.0,
        "dock_rest_s": 0.0,
        "charger_fault_clear_s": 0.0,
        "aux_soc_hysteresis": 0.0,
    },
    "cell_step_r_only": {
        **CELL,
        "r_settle_s": 0.0,
        "r_est_min_step_a": 0.5,
        "r_comp_max_ohm": 0.2,
        "current_law": "sqrt",
        # the floor above target - hysteresis: docked, below the floor still starts charging
        "aux_soc_floor": 0.3,
        "aux_soc_target": 0.4,
        "aux_soc_hysteresis": 0.2,
    },
}


def _info(n: int, series: int, has_aux: bool) -> PackInfo:
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(series,) * n,
        cells_per_group=(1,) * n,
        switch_kind=(SwitchKind.RELAY,) * n,
        has_aux=has_aux,
        has_charger=True,
        capacity_ah=tuple(5.0 + i for i in range(n)),
    )


def _pair(cfg: ChargingConfig, info: PackInfo) -> tuple[ChargingController, Oracle]:
    return ChargingController(cfg, info), Oracle(cfg, info)


def _run(new: ChargingController, old: Oracle, seq: list[tuple[Measurements, float]]) -> None:
    n = new.pack.n_batteries
    for k, (meas, dt) in enumerate(seq):
        assert_same_output(new.step(meas, dt), old.step(meas, dt), n, f"step {k}")


# --------------------------------------------------------------------------- garbage


@settings(max_examples=150, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 4),
    groups=st.integers(1, 4),
    name=st.sampled_from(sorted(k for k in CONFIGS if k.startswith("cell"))),
    has_aux=st.booleans(),
)
def test_same_on_random_sequences(
    data: Any, n: int, groups: int, name: str, has_aux: bool
) -> None:
    new, old = _pair(ChargingConfig.model_validate(CONFIGS[name]), _info(n, groups, has_aux))
    _run(new, old, data.draw(sequence(n, groups, steps=80, current=(-30.0, 10.0))))


# --------------------------------------------------------------------------- charging-shaped


def _levels(vs: Volts) -> list[float]:
    """Voltages on and around the thresholds the rules compare with: near V_sat, and a base
    level with the offsets of the grouping rules (with the binary-exact config their
    differences are exact, so ``<=`` against ``<`` is decided by the input)."""
    top = vs.v_sat
    base = top - vs.delta_v2 - 2.0 * vs.delta_v1
    offsets = [
        0.0,
        vs.eps_eq,
        vs.d1,
        vs.d1 - vs.eps_eq,
        2.0 * vs.d1,
        vs.delta_v1 - vs.d1,
        vs.delta_v1,
        vs.delta_v1 + vs.eps_eq,
        -vs.d1,
        vs.delta_v2 - vs.reach_tol,
        vs.delta_v2,
    ]
    return [
        top,
        top - vs.reach_tol,
        top + vs.overvoltage_margin,
        top - vs.delta_v2 - vs.reach_tol,
        top - 2.5 * vs.delta_v2,
        *(base + d for d in offsets),
    ]


@st.composite
def charging_sequence(
    draw: Any, n: int, series: int, vs: Volts, cfg: ChargingConfig, steps: int = 120
) -> list[tuple[Measurements, float]]:
    levels = _levels(vs)
    span = vs.v_sat - min(levels)
    jitter = st.floats(-vs.eps_eq, vs.eps_eq, allow_nan=False)
    ocv = [draw(st.sampled_from(levels)) + draw(st.sampled_from([0.0, 0.0, 1.0])) * draw(jitter)
           for _ in range(n)]  # fmt: skip
    r0 = [draw(st.sampled_from([0.0, 0.01, 0.03, 0.1])) for _ in range(n)]
    r1 = [draw(st.sampled_from([0.0, 0.01, 0.05])) for _ in range(n)]
    pol = [0.0] * n
    cur = [0.0] * n
    cell_off = [draw(st.sampled_from([0.0, 0.0, 0.0, 0.01, 0.5])) for _ in range(n)]
    gain_v_per_as = draw(st.sampled_from([0.0, span / 2000.0, span / 200.0]))
    quiet = draw(st.integers(0, 2)) == 0  # no current at all: est = v exactly
    currents = st.one_of(
        st.sampled_from(
            [0.0, -cfg.termination_current_a, -0.5, -2.0, -5.0, -20.0, 3.0, -cfg.r_est_min_step_a]
        ),
        st.floats(-30.0, 10.0, allow_nan=False),
    )
    docked = True
    charger_mode = "ok"
    flags = dict.fromkeys(CHARGER_FLAGS, False)
    floor, target, hyst = cfg.aux_soc_floor, cfg.aux_soc_target, cfg.aux_soc_hysteresis
    aux_socs = [floor, floor + hyst, target - hyst, target, 0.2, 0.25, 0.33, 0.86, 0.95]
    aux_soc = draw(st.sampled_from([None, *aux_socs]))
    aux_v = cfg.aux_cv_v - cfg.aux_cv_band_v / 2.0
    t = 0.0
    out: list[tuple[Measurements, float]] = []
    for _ in range(draw(st.integers(1, steps))):
        dt = draw(st.sampled_from([1.0] * 6 + [0.5, 2.0, 5.0, 0.0, -1.0, math.nan, math.inf]))
        step = dt if math.isfinite(dt) and dt > 0.0 else 0.0
        for i in range(n):
            if not quiet and draw(st.integers(0, 9)) == 0:
                cur[i] = draw(currents)
            ocv[i] -= cur[i] * step * gain_v_per_as
            pol[i] += (cur[i] * r1[i] - pol[i]) * (1.0 - math.exp(-step / 3.0))
        if draw(st.integers(0, 12)) == 0:
            ocv[draw(st.integers(0, n - 1))] = draw(st.sampled_from(levels))
        if draw(st.integers(0, 40)) == 0:
            docked = not docked
        if draw(st.integers(0, 15)) == 0:
            charger_mode = draw(st.sampled_from(["ok", "ok", "none", "offline", "flag"]))
            flags = {f: draw(st.sampled_from([False, False, True])) for f in CHARGER_FLAGS}
        bats = []
        for i in range(n):
            v = ocv[i] - cur[i] * r0[i] - pol[i]
            cell = v / series
            b = BatteryMeasurement(
                voltage_v=v,
                current_a=cur[i],
                temp_c=25.0,
                min_cell_v=cell - 0.005,
                max_cell_v=cell + cell_off[i],
                soc=0.5,
                full_capacity_ah=5.0,
                remaining_capacity_ah=2.5,
                group_voltages_v=(cell,) * series,
                switch=SwitchState(True, True),
                present=draw(st.sampled_from([True] * 30 + [False])),
            )
            if draw(st.integers(0, 25)) == 0:
                field = draw(st.sampled_from(["voltage_v", "current_a", "max_cell_v", "soc"]))
                b = _replace(b, field, draw(st.sampled_from(WEIRD)))
            if draw(st.integers(0, 60)) == 0:
                b = _replace(b, "group_voltages_v", (cell,) * (series - 1) + (math.nan,))
            bats.append(b)
        nb = n if draw(st.integers(0, 40)) else draw(st.integers(0, n - 1))
        charger = None
        if charger_mode != "none":
            charger = ChargerStatus(
                output_v=vs.v_sat,
                output_a=draw(st.sampled_from([0.0, 5.0, math.nan])),
                online=charger_mode != "offline",
                **(flags if charger_mode == "flag" else {}),
            )
        aux = None
        if aux_soc is not None:
            if draw(st.integers(0, 5)) == 0:
                aux_soc = draw(st.sampled_from(aux_socs))
            if draw(st.integers(0, 10)) == 0:
                band = cfg.aux_cv_band_v
                d = draw(st.sampled_from([-2.0 * band, -band, -0.5 * band, 0.0, band]))
                aux_v = cfg.aux_cv_v + d
            aux = BatteryMeasurement(
                voltage_v=draw(st.sampled_from([aux_v] * 20 + [math.nan])),
                current_a=0.0,
                temp_c=25.0,
                min_cell_v=3.3,
                max_cell_v=3.4,
                soc=aux_soc,
                full_capacity_ah=20.0,
                remaining_capacity_ah=20.0 * aux_soc,
            )
        meas = Measurements(
            t_s=t,
            batteries=tuple(bats[:nb]),
            bus_v=vs.v_sat,
            charger=charger,
            aux=aux,
            docked=docked,
        )
        out.append((meas, dt))
        t += step
        if draw(st.integers(0, 50)) == 0:
            t -= 3.0
    return out


def _replace(b: BatteryMeasurement, field: str, value: Any) -> BatteryMeasurement:
    import dataclasses

    return dataclasses.replace(b, **{field: value})


@settings(max_examples=300, deadline=None)
@given(
    data=st.data(),
    n=st.integers(1, 6),
    name=st.sampled_from(sorted(CONFIGS)),
    has_aux=st.booleans(),
)
def test_same_on_charging_sequences(data: Any, n: int, name: str, has_aux: bool) -> None:
    cfg = ChargingConfig.model_validate(CONFIGS[name])
    # battery-volt configs are written for ~4 V cells in 4 series (1: every cell over its limit)
    series = data.draw(st.sampled_from([1, 4, 30] if cfg.voltage_basis == "cell" else [4, 4, 1]))
    info = _info(n, series, has_aux)
    new, old = _pair(cfg, info)
    seq = data.draw(charging_sequence(n, series, Volts.resolve(cfg, info), cfg))
    _run(new, old, seq)


# --------------------------------------------------------------------------- closed loops


def _toy_loop(
    cfg: ChargingConfig, toy: ToyPack, has_aux: bool, seconds: int, faults: bool = False
) -> set[str]:
    """Drive the toy plant with the compiled controller, the oracle on the same samples."""
    new, old = _pair(cfg, pack_info(toy.n, has_aux=has_aux))
    kinds: set[str] = set()
    for k in range(seconds):
        if faults and k == 400:
            toy.charger_flags = {"over_temperature": True}
        if faults and k == 420:
            toy.charger_flags = {}
        if faults and k == 700:
            toy.charger_online = False
        if faults and k == 705:
            toy.charger_online = True
        meas = toy.measure()
        a, b = new.step(meas, 1.0), old.step(meas, 1.0)
        assert_same_output(a, b, toy.n, f"t={meas.t_s}")
        kinds.update(e.kind for e in a.events)
        toy.apply(a)
        toy.step(1.0)
        if any(e.kind == "ChargeComplete" for e in a.events) and toy.aux_soc is None:
            break
    return kinds


@pytest.mark.parametrize(
    ("v0", "kw"),
    [
        ([80.0, 90.0], {}),
        ([80.0, 80.0, 90.0, 90.0, 100.0, 100.0], {}),
        ([80.0, 80.0, 90.0, 90.0, 100.0, 100.0], {"target_mode": "saturation"}),
        ([80.0, 80.0, 90.0, 90.0, 100.0, 100.0], {"current_law": "sqrt"}),
        ([100.0, 100.0, 100.0], {"battery_current_limit_a": 5.0, "vc3_margin_v": 3.0}),
        ([85.0], {"r_settle_s": 0.0}),
    ],
)
def test_same_in_toy_closed_loop(v0: list[float], kw: dict[str, Any]) -> None:
    toy = ToyPack(v0, noise_v=0.05, seed=len(v0), slope_v_per_ah=40.0, capacity_ah=1.0)
    kinds = _toy_loop(ChargingConfig.model_validate(kw), toy, False, 20_000)
    assert "ChargeComplete" in kinds


def test_same_in_toy_closed_loop_with_faults_and_aux() -> None:
    toy = ToyPack([95.0, 100.0, 112.0], aux_soc=0.25, cell_offset_v=[0.0, 0.0, 0.02])
    kinds = _toy_loop(ChargingConfig(cell_v_limit_v=3.95), toy, True, 3_000, faults=True)
    assert {"StageChanged", "Fault", "BatteryFull"} <= kinds


class Twin:
    """The compiled controller inside a simulator run, checked against the oracle each step."""

    steps: ClassVar[int] = 0
    kinds: ClassVar[set[str]] = set()

    def __init__(self, config: ChargingConfig, info: PackInfo) -> None:
        self.new = ChargingController(config, info)
        self.old = Oracle(config, info)

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        a, b = self.new.step(meas, dt_s), self.old.step(meas, dt_s)
        assert_same_output(a, b, self.new.pack.n_batteries, f"t={meas.t_s}")
        Twin.steps += 1
        Twin.kinds.update(e.kind for e in a.events)
        return a


@pytest.fixture
def twin(monkeypatch: pytest.MonkeyPatch) -> type[Twin]:
    twin = replace(REGISTRY["charging"], target=f"{__name__}:Twin")
    monkeypatch.setitem(REGISTRY, "charging", twin)
    Twin.steps = 0
    Twin.kinds = set()
    return Twin


def test_same_on_the_evtol_charging_bus_with_faults(twin: type[Twin]) -> None:
    """examples/evtol_charging.toml at 2 Ah (a full charge in ~4000 s), with a NaN voltage
    sensor, a stuck current sensor, a charger fault flag, a silent CAN link and undocking."""
    data = tomllib.loads((EXAMPLES / "evtol_charging.toml").read_text())
    for b in data["pack"]["batteries"]:
        if b.get("role", "traction") == "traction":
            b["capacity_ah"] = 2.0
    data["charger"].update({"current_a": 10.0, "disconnect_s": 4300.0})
    data["charging"].update({"charger_current_limit_a": 10.0, "termination_current_a": 0.2})
    data["sim"].update({"dt_s": 1.0, "duration_s": 4400.0})
    data["faults"] = [
        {"kind": "sensor_nan", "battery": "B3", "quantity": "voltage_v", "at_s": 500.0,
         "until_s": 520.0},
        {"kind": "sensor_stuck", "battery": "B5", "quantity": "current_a", "at_s": 1200.0,
         "until_s": 1300.0},
        {"kind": "charger_fault", "flag": "input_voltage_fault", "at_s": 900.0, "until_s": 960.0},
        {"kind": "can_silence", "at_s": 1500.0, "until_s": 1530.0},
    ]  # fmt: skip
    res = Runner(parse_config(data), progress=False).run()
    assert twin.steps == 4400
    assert {"StageChanged", "Fault", "BatteryFull", "ChargeComplete"} <= twin.kinds
    assert any(e.kind == "StageChanged" and e.data["reason"] == "undocked" for e in res.events)


def test_same_over_the_uav_mission(twin: type[Twin]) -> None:
    """The whole UAV mission under the supervisor: flight (undocked), docking, charging."""
    cfg = load_config(EXAMPLES / "uav_mission.toml")
    Runner(cfg, progress=False).run()
    assert twin.steps == round(cfg.sim.duration_s / cfg.sim.dt_s)
    assert "StageChanged" in twin.kinds


# --------------------------------------------------------------------------- exact thresholds

BIN = ChargingConfig.model_validate(CONFIGS["binary"])
"""Binary-exact volts: every threshold below is hit exactly, not approximately."""
BASE = 12.0


def _bm(v: float, cur: float = 0.0, cell_max: float | None = None) -> BatteryMeasurement:
    return BatteryMeasurement(
        voltage_v=v,
        current_a=cur,
        temp_c=25.0,
        min_cell_v=v / 4.0,
        max_cell_v=v / 4.0 if cell_max is None else cell_max,
        soc=0.5,
        full_capacity_ah=5.0,
        remaining_capacity_ah=2.5,
        group_voltages_v=(v / 4.0,) * 4,
    )


def _script(
    rows: list[tuple[float, ...]],
    *,
    cur: float = 0.0,
    cell_max: float | None = None,
    charger: list[bool] | None = None,
    aux_soc: list[float] | None = None,
    docked: list[bool] | None = None,
) -> list[tuple[Measurements, float]]:
    """One measurement per row of battery voltages, 1 s apart."""
    out = []
    for k, row in enumerate(rows):
        aux = None
        if aux_soc is not None:
            aux = BatteryMeasurement(
                voltage_v=BIN.aux_cv_v - BIN.aux_cv_band_v,
                current_a=0.0,
                temp_c=25.0,
                min_cell_v=3.25,
                max_cell_v=3.25,
                soc=aux_soc[k],
                full_capacity_ah=20.0,
                remaining_capacity_ah=10.0,
            )
        status = ChargerStatus(output_v=16.0, output_a=0.0)
        meas = Measurements(
            t_s=float(k),
            batteries=tuple(_bm(v, cur, cell_max) for v in row),
            bus_v=16.0,
            charger=status if charger is None or charger[k] else None,
            aux=aux,
            docked=True if docked is None else docked[k],
        )
        out.append((meas, 1.0))
    return out


E, D1, DV1, DV2, RT = BIN.eps_eq_v, BIN.d1_v, BIN.delta_v1_v, BIN.delta_v2_v, BIN.reach_tol_v
REST = [(BASE, BASE)] * 3
SCRIPTS: dict[str, list[tuple[Measurements, float]]] = {
    # S30 (levels d1 apart), then the two batteries exactly eps_eq apart: merged
    "s30_merges_at_eps": _script([(BASE, BASE + D1)] * 4 + [(BASE + D1 - E, BASE + D1)] * 3),
    # S20 until the first battery reaches exactly Vr1 = V2 - d1
    "s20_exits_at_vr1": _script([(BASE, BASE + DV1)] * 4 + [(BASE + DV1 - D1, BASE + DV1)] * 3),
    # S40 until exactly Vr2 - reach_tol
    "s40_exits_at_vr2": _script([(BASE,)] * 4 + [(BASE + DV2 - RT,)] * 3),
    # S40 or top-off: V_sat - V exactly dV2 + reach_tol
    "s40_or_top_off": _script([(16.0 - DV2 - RT,)] * 4),
    # S20 with a third battery falling to exactly eps_eq above the connected one: regroup
    "regroup_at_eps": _script(
        [(BASE, BASE + DV1, BASE + DV1)] * 4 + [(BASE, BASE + DV1, BASE + E)] * 3
    ),
    # top-off kept while the eligible batteries are at most dV1 apart (exactly)
    "top_off_span": _script([(15.5, 15.5)] * 4 + [(15.5, 15.5 - DV1)] * 3),
    # full exactly at V_sat - reach_tol with exactly the termination current
    "full_exactly": _script([(16.0 - RT,)] * 4, cur=-BIN.termination_current_a),
    "overvoltage_exactly": _script([(16.0 + BIN.overvoltage_margin_v,)] * 4),
    "cell_limit_exactly": _script([(BASE,)] * 4, cell_max=BIN.cell_v_limit_v),
    # no charger status for exactly the timeout (2 s), then back
    "status_timeout": _script(
        [(BASE, BASE + DV1)] * 8, charger=[True] * 3 + [False] * 3 + [True] * 2
    ),
    # aux exactly at its floor / target thresholds, docked and not
    "aux_thresholds": _script(
        [(BASE,)] * 8,
        aux_soc=[0.25, 0.375, 0.75, 0.875, 0.75, 0.25, 0.375, 0.25],
        docked=[True] * 4 + [False] * 4,
    ),
}


@pytest.mark.parametrize("name", sorted(SCRIPTS))
def test_same_at_exact_thresholds(name: str) -> None:
    seq = SCRIPTS[name]
    n = len(seq[0][0].batteries)
    new, old = _pair(BIN, _info(n, 4, name.startswith("aux")))
    _run(new, old, seq)
