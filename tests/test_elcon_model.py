"""The compiled TC/Elcon link (``sim/elcon.py``) against the python-can path it models.

Two closed loops of the same scenario step side by side: one on :class:`ElconLinks` (what a
run without a frame log uses), one on a ``CanChargerLink`` per pack (client, virtual bus,
emulated charger node). After every step the charger status the BMS saw (``m.charger``), what
reached each dock (``request(v, a, enable, t)``: the dock's request arrays), the dock's output
and flags, the plant's interval, the events, both nodes' frame counters and whether the dock's
node has lost the heartbeat must be identical, and at the end the metrics. Whole runs compare
traces, status, events and metrics. Scenarios: the UAV mission through docking and charging,
the eVTOL charging bus (its dock put on a virtual CAN bus; the example's is direct),
``can_silence`` before docking / across it / during charging, shorter than, between and longer
than the timeouts, for good, two at once; charger fault flags; undocking; a dock no controller
commands (the default setpoint); odd periods and timeouts (one under the heartbeat period);
a batch of four packs that differ.

The quantization is checked against the codec itself (``io/can/codec.py`` encode/decode) on
hostile values (negative, NaN, inf, huge, exact halves, the whole 0.005 grid).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from packpilot.config import ScenarioConfig, load_config
from packpilot.contract.charger import ChargerCommand
from packpilot.io.can import client as can_client
from packpilot.io.can import codec
from packpilot.io.can.link import CanChargerLink
from packpilot.model.charger import ChargerModel, ChargerParams
from packpilot.sim import elcon
from packpilot.sim.elcon import ElconLinks
from packpilot.sim.links import ChargerLinks, can_link, modelled
from packpilot.sim.loop import ClosedLoop, n_steps
from packpilot.sim.plant_io import SimulatedPlant
from packpilot.sim.runner import Runner
from tests.budget import budget
from tests.conftest import EXAMPLES
from tests.golden.fingerprint import events_of, trace_arrays

# ------------------------------------------------------------------ scenarios


def scenario(
    name: str,
    *,
    duration_s: float | None = None,
    dt_s: float | None = None,
    charger: dict[str, Any] | None = None,
    **sections: Any,
) -> ScenarioConfig:
    """An example, shortened, its ``[charger]`` amended, other sections replaced."""
    doc = load_config(EXAMPLES / f"{name}.toml").model_dump()
    doc["sim"]["progress"] = False
    if duration_s is not None:
        doc["sim"]["duration_s"] = duration_s
    if dt_s is not None:
        doc["sim"]["dt_s"] = dt_s
    doc["charger"].update(charger or {})
    if doc["can"] is None:  # evtol_charging's dock is direct in the example: put it on CAN
        doc["can"] = {"interface": "virtual"}
    doc.update(sections)
    cfg = ScenarioConfig.model_validate(doc)
    assert modelled(cfg)
    return cfg


def silence(at_s: float, until_s: float | None = None) -> dict[str, Any]:
    return {"kind": "can_silence", "at_s": at_s, "until_s": until_s}


# ------------------------------------------------------------------ side by side


def _plant_charger(loop: ClosedLoop) -> dict[str, Any]:
    ch = loop.plant.pack.charger
    return {
        "v_req": ch.v_req,
        "i_req": ch.i_req,
        "on_req": ch.on_req,
        "last_request_s": ch.last_request_s,
        "flags": ch.flags,
        "out_v": ch.out_v,
        "out_a": ch.out_a,
        "connected": ch.connected,
    }


def _meas_charger(loop: ClosedLoop) -> dict[str, Any]:
    return dict(loop.m.charger._asdict())


def _same(a: dict[str, Any], b: dict[str, Any], what: str, k: int) -> None:
    for name in a:
        x, y = np.asarray(a[name]), np.asarray(b[name])
        assert x.dtype == y.dtype and x.shape == y.shape, (what, name, k)
        # bit for bit (NaN == NaN): compare the bytes
        assert x.tobytes() == y.tobytes(), f"step {k}: {what}.{name}: {x!r} != {y!r}"


def _counters(link: Any) -> dict[str, dict[str, int]]:
    inner = getattr(link, "inner", link)
    assert isinstance(inner, CanChargerLink) and inner.emulator is not None
    fields = [f.name for f in dataclasses.fields(inner.client.counters)]  # implausible too
    return {
        "client": {f: getattr(inner.client.counters, f) for f in fields},
        "emulator": {f: getattr(inner.emulator.counters, f) for f in fields},
    }


def lockstep(
    cfg: ScenarioConfig, n_packs: int = 1, overrides: dict[str, Any] | None = None
) -> dict[str, int]:
    """Run ``cfg`` on the model and on python-can side by side; assert every step equal.
    Returns a few counts so a test can check the scenario did what it is there for."""
    model = ClosedLoop.of(cfg, n_packs, overrides)
    assert isinstance(model.links, ElconLinks)
    plant = SimulatedPlant(cfg, n_packs, overrides)
    raw = [can_link(cfg, plant.pack, p) for p in range(n_packs)]
    ref = ClosedLoop.of(cfg, links=raw, plant=plant)
    assert isinstance(ref.links, ChargerLinks)
    if ref.faults is not None:
        assert model.faults is not None and model.faults.links == [model.links]
    dt = cfg.sim.dt_s
    seen = {"steps": 0, "offline": 0, "unreported": 0, "comm_timeout": 0, "silent": 0}
    seen["charging"] = seen["requests"] = seen["default"] = 0
    last_req = np.full(n_packs, -np.inf)
    try:
        for k in range(n_steps(cfg)):
            a = model.step(k, dt)
            b = ref.step(k, dt)
            _same(_meas_charger(model), _meas_charger(ref), "m.charger", k)
            _same(_plant_charger(model), _plant_charger(ref), "dock", k)
            _same(vars(a.iv), vars(b.iv), "interval", k)
            assert repr(a.events) == repr(b.events), k
            t = a.iv.t_s
            lost = model.links.heartbeat_lost(t)
            for p, link in enumerate(ref.links.links):  # type: ignore[attr-defined]
                assert model.links.counters(p) == _counters(link), (k, p)
                emulator = getattr(link, "inner", link).emulator
                assert bool(lost[p]) == emulator.heartbeat_lost(t), (k, p)
            m = model.m.charger
            seen["steps"] += 1
            seen["offline"] += int(np.sum(m.reported & ~m.online))
            seen["unreported"] += int(np.sum(~m.reported))
            seen["comm_timeout"] += int(np.sum(m.flags[:, 4]))
            seen["silent"] += int(model.links.st[:, elcon.I_SILENCED].sum())
            seen["charging"] += int(np.sum(a.iv.charger_a > 0.1))
            seen["default"] += int(np.sum(~model.core.cmd.charger_set))
            req = model.plant.pack.charger.last_request_s
            seen["requests"] += int(np.sum(req != last_req))
            last_req = req.copy()
            if not (model.running or ref.running):
                break
            assert model.running == ref.running
        for p in range(n_packs):
            assert repr(model.metrics.of(p, 0.0, [])) == repr(ref.metrics.of(p, 0.0, []))
            assert model.links.counters(p) == _counters(ref.links.links[p])  # type: ignore[attr-defined]
    finally:
        model.close()
        ref.close()
    return seen


# ------------------------------------------------------------------ whole runs (Runner)


def _result(cfg: ScenarioConfig, python_can: bool) -> Any:
    runner = Runner(cfg, progress=False)
    if python_can:
        assert runner.charger_link is None  # modelled by default ...
        runner.charger_link = can_link(cfg, runner.pack)  # ... unless a link is passed
    res = runner.run()
    assert isinstance(runner.loop.links, ChargerLinks if python_can else ElconLinks)
    return res


def _same_result(cfg: ScenarioConfig) -> Any:
    a, b = _result(cfg, False), _result(cfg, True)
    ta, tb = trace_arrays(a), trace_arrays(b)
    for name in ta:
        x, y = ta[name], tb[name]
        if x is None or y is None:
            assert x is None and y is None, name
            continue
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), name
    assert repr(a.trace.status) == repr(b.trace.status)
    assert repr(events_of(a)) == repr(events_of(b))  # repr: NaN fields compare equal
    wa = {k: v for k, v in a.metrics.items() if k != "wall_time_s"}
    wb = {k: v for k, v in b.metrics.items() if k != "wall_time_s"}
    assert repr(wa) == repr(wb)
    return a


def test_uav_mission_whole_runs_are_identical() -> None:
    """The whole mission (flight, landing, docking at 1,300 s, staged charging, balancing)."""
    res = _same_result(scenario("uav_mission", dt_s=0.5))
    assert res.metrics["events"].get("ChargeComplete", 0) == 1


def test_evtol_charging_runs_are_identical() -> None:
    res = _same_result(scenario("evtol_charging", duration_s=6000.0))
    assert res.metrics["energy_in_wh"] > 1000.0


# ------------------------------------------------------------------ step by step


def test_uav_mission_step_by_step_through_docking_and_charging() -> None:
    seen = lockstep(scenario("uav_mission", duration_s=2600.0))
    assert seen["charging"] > 1000 and seen["unreported"] > 0


def test_evtol_step_by_step() -> None:
    seen = lockstep(scenario("evtol_charging", duration_s=6000.0))
    assert seen["charging"] > 1000


NO_CONTROLLER: dict[str, Any] = {"controller": [], "soc": {}}
"""No method commands the dock: the supervisor switches it off outside its CHARGE mode, and in
CHARGE mode nobody has an opinion, so the scenario's default setpoint goes out."""

CASES: dict[str, tuple[str, float, dict[str, Any]]] = {
    # the UAV docks at 1,300 s: silence before docking, across it, during charging
    "uav_before_docking": ("uav_mission", 1400.0, {"faults": [silence(1200.0, 1290.0)]}),
    "uav_across_docking": ("uav_mission", 1400.0, {"faults": [silence(1296.0, 1311.3)]}),
    "uav_shorter_than_timeouts": ("uav_mission", 1560.0, {"faults": [silence(1500.0, 1503.0)]}),
    "uav_between_the_timeouts": (  # client status timeout 5 s < link and dock timeout 9 s
        "uav_mission",
        1560.0,
        {"faults": [silence(1500.0, 1507.1)], "charger": {"heartbeat_timeout_s": 9.0}},
    ),
    "uav_long_while_charging": ("uav_mission", 1600.0, {"faults": [silence(1500.0, 1530.0)]}),
    "uav_for_good": ("uav_mission", 1600.0, {"faults": [silence(1520.0)]}),
    "uav_two_silences": (  # the injector's rule for several (the last one listed sets it)
        "uav_mission",
        1600.0,
        {"faults": [silence(1500.0, 1540.0), silence(1510.0, 1520.0)]},
    ),
    "uav_fault_flag": (
        "uav_mission",
        1700.0,
        {
            "faults": [
                {
                    "kind": "charger_fault",
                    "at_s": 1600.0,
                    "until_s": 1640.0,
                    "flag": "over_temperature",
                }
            ]
        },
    ),
    "uav_undock": ("uav_mission", 1760.0, {"charger": {"disconnect_s": 1700.0}}),
    "evtol_silence_from_start": ("evtol_charging", 600.0, {"faults": [silence(0.0, 13.0)]}),
    "evtol_silence_odd_dt": (
        "evtol_charging",
        600.0,
        {"faults": [silence(300.0, 340.0)], "dt_s": 0.3},
    ),
    "evtol_short_timeout": (  # link and dock time out at 1.5 s, the client at 5 s
        "evtol_charging",
        600.0,
        {"faults": [silence(100.0, 104.0)], "charger": {"heartbeat_timeout_s": 1.5}},
    ),
    "evtol_timeout_under_a_heartbeat": (  # the dock loses the 1 s heartbeat between frames
        "evtol_charging",
        200.0,
        {"charger": {"heartbeat_timeout_s": 0.7}, "dt_s": 0.3},
    ),
    "evtol_flag_and_silence": (
        "evtol_charging",
        600.0,
        {
            "faults": [
                {
                    "kind": "charger_fault",
                    "at_s": 50.0,
                    "until_s": 90.0,
                    "flag": "hardware_failure",
                },
                silence(70.0, 80.0),
                {"kind": "charger_fault", "at_s": 200.0, "flag": "input_voltage_fault"},
            ]
        },
    ),
    "evtol_no_controller": ("evtol_charging", 1200.0, NO_CONTROLLER),
    "evtol_no_controller_silenced": (
        "evtol_charging",
        600.0,
        {**NO_CONTROLLER, "faults": [silence(40.0, 60.0)], "dt_s": 0.7},
    ),
    "evtol_late_dock_and_undock": (
        "evtol_charging",
        600.0,
        {"charger": {"connect_s": 30.0, "disconnect_s": 400.0}, "dt_s": 1.1},
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_step_by_step(case: str) -> None:
    name, duration, kw = CASES[case]
    if name == "uav_mission":  # 1,300 s of flight before the dock: at test_mission's period
        kw = {"dt_s": 0.5, **kw}
    seen = lockstep(scenario(name, duration_s=duration, **kw))
    assert seen["charging"] > 0 or case == "evtol_timeout_under_a_heartbeat"
    if any(f["kind"] == "can_silence" for f in kw.get("faults", [])):
        assert seen["silent"] > 0
    if case in ("uav_across_docking", "uav_long_while_charging", "evtol_silence_odd_dt"):
        assert seen["offline"] > 0 and seen["comm_timeout"] > 0  # both timeouts reached
    if case == "evtol_timeout_under_a_heartbeat":
        assert seen["comm_timeout"] > 0 and seen["silent"] == 0
    if kw.get("controller") == []:
        assert seen["default"] > 0


def test_batch_of_different_packs_step_by_step() -> None:
    """P = 4 packs that charge differently, silenced and faulted together."""
    faults = [silence(60.0, 75.0), {"kind": "charger_fault", "at_s": 200.0, "until_s": 230.0}]
    cfg = scenario("evtol_charging", duration_s=600.0, faults=faults, **NO_CONTROLLER)
    overrides = {
        "soc_offset": np.array([0.0, -0.1, 0.05, 0.12]),
        "capacity_scale": np.array([1.0, 0.9, 1.1, 0.8]),
    }
    seen = lockstep(cfg, 4, overrides)
    assert seen["charging"] > 0 and seen["default"] > 0 and seen["offline"] > 0


# ------------------------------------------------------------------ the codec, directly

HOSTILE = [
    0.0, -0.0, 0.05, 0.15, 0.25, 0.35, 0.45, 1.05, 2.5, 4.15, 98.05, 98.15, 117.0, 117.05,
    6553.45, 6553.5, 6553.55, 6553.6, 1e5, 1e300, -1e300, -0.04, -0.05, -0.06, -5.0,
    math.nan, math.inf, -math.inf, 5e-324, 0.049999999999999996, 1e-17,
    float(np.nextafter(0.05, 1.0)), float(np.nextafter(0.05, 0.0)),
]  # fmt: skip


def _codec_counts(v: float, a: float, enable: bool) -> tuple[int, int, bool]:
    req = codec.decode_request(codec.encode_request(ChargerCommand(v, a, enable)))
    return (
        round(req.voltage_v * codec.COUNTS_PER_UNIT),
        round(req.current_a * codec.COUNTS_PER_UNIT),
        req.enable,
    )


def test_protocol_numbers_match_the_python_path() -> None:
    assert elcon.PERIOD_S == codec.PERIOD_S
    assert elcon.COUNTS_PER_UNIT == codec.COUNTS_PER_UNIT
    assert elcon.RAW_MAX == codec._RAW_MAX
    assert elcon.CONTROL_ON == codec.CONTROL_ON
    assert can_client.MAX_FRAMES_PER_POLL >= 1  # the model queues at most one frame
    import inspect

    sig = inspect.signature(CanChargerLink)
    assert sig.parameters["status_timeout_s"].default == elcon.CLIENT_STATUS_TIMEOUT_S


def _overflows(x: float) -> bool:
    """Finite, but ``x * 10`` is not: ``round(inf)`` in the codec raises OverflowError."""
    return math.isfinite(x) and not math.isfinite(x * 10)


def _check_value(x: float) -> None:
    try:
        expect = codec._raw(x)
    except OverflowError:  # round(inf) of a huge finite value: the model clamps instead
        assert _overflows(x)
        expect = codec._RAW_MAX if x > 0 else 0
    assert elcon.raw_count(x) == expect, x
    raw = elcon.raw_count(x)
    # the status frame: encode with the codec, decode with the codec, decode with the model
    if not _overflows(x):
        status = codec.decode_status(codec.encode_status(x, x, {}))
        assert status.output_v == elcon.decode_count(raw), x
        assert status.output_a == elcon.decode_count(raw), x


@pytest.mark.parametrize("x", HOSTILE)
def test_quantization_equals_the_codec_on_hostile_values(x: float) -> None:
    _check_value(x)
    _check_value(-x)


@given(st.floats(allow_nan=True, allow_infinity=True, width=64))
@budget(500)
def test_quantization_equals_the_codec_on_any_float(x: float) -> None:
    _check_value(x)


@given(st.integers(0, 655350).map(lambda n: n / 100.0))
@budget(500)
def test_quantization_on_the_grid_of_halves(x: float) -> None:
    _check_value(x)


@pytest.mark.parametrize("v", HOSTILE)
@pytest.mark.parametrize("a", [0.0, 10.05, -1.0, math.nan, math.inf, 99.95])
@pytest.mark.parametrize("enable", [True, False])
def test_a_request_reaches_the_dock_as_over_python_can(v: float, a: float, enable: bool) -> None:
    """One send of the model vs encode_request -> decode_request -> ChargerModel.request."""
    if _overflows(v) or _overflows(a):
        pytest.skip("the codec raises OverflowError on these (the model clamps)")
    rated_v, rated_a = 60.0, 20.0
    want = ChargerModel(ChargerParams(rated_v=rated_v, rated_a=rated_a), 1)
    req = codec.decode_request(codec.encode_request(ChargerCommand(v, a, enable)))
    want.request(0, req.voltage_v, req.current_a, req.enable, 3.0)

    prm = np.zeros(elcon.NP)
    prm[[elcon.P_STATUS_TIMEOUT, elcon.P_LINK_TIMEOUT, elcon.P_HB_TIMEOUT]] = 5.0
    prm[elcon.P_PERIOD] = 1.0
    prm[elcon.P_RATED_V], prm[elcon.P_RATED_A] = rated_v, rated_a
    fs = np.full((1, elcon.NF), math.nan)
    stt = np.zeros((1, elcon.NI), np.int64)
    got = ChargerModel(ChargerParams(rated_v=rated_v, rated_a=rated_a), 1)
    elcon.elcon_send(
        prm, fs, stt, 3.0,
        np.array([True]), np.array([v]), np.array([a]), np.array([enable]),
        got.v_req, got.i_req, got.on_req, got.last_request_s, got.flags, got.out_v, got.out_a,
    )  # fmt: skip
    for name in ("v_req", "i_req", "on_req", "last_request_s"):
        x, y = getattr(got, name), getattr(want, name)
        assert x.tobytes() == y.tobytes(), (name, x, y)
    assert _codec_counts(v, a, enable)[2] == bool(got.on_req[0])
