"""The compiled safety limits against the scalar oracle they replaced (see ``common.py``).

Two kinds of evidence: Hypothesis-drawn measurement sequences over drawn limit tables (every
quantity, direction, path, context, tier, latch including manual, derating tables with one or
several points) with explicit resets between steps; and closed loops on the real plant, where
the compiled controller is the one in the loop and the oracle sees the same measurements
(plus tighter tables beside them, so every tier is entered and cleared on plant data).
Commands, events, status, the query API and ``reset_trips``' answers must be equal at every
step.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

from hypothesis import event, given, settings
from hypothesis import strategies as st

from packpilot.config import load_config, parse_config
from packpilot.config.limits import (
    QUANTITY_DIRECTION,
    TIERS,
    CurveTable,
    DeratingConfig,
    LimitRow,
    LimitsConfig,
)
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.bms import ControlOutput, Measurements, SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core, Part
from packpilot.control.limits import LimitsController
from packpilot.sim.runner import Runner
from tests.conftest import EXAMPLES, dual_pack
from tests.equivalence.common import assert_same_output, same, sequence
from tests.oracles.limits import LimitsController as Oracle

RANGES: dict[str, tuple[float, float]] = {
    "cell_v_max": (3.0, 4.4),
    "cell_v_min": (2.4, 4.0),
    "chg_c_rate": (0.0, 6.0),
    "dsg_c_rate": (0.0, 12.0),
    "temp_max_c": (-10.0, 80.0),
    "temp_min_c": (-30.0, 40.0),
}
"""Where the drawn measurements put each quantity (5 Ah batteries, -30..60 A)."""


# ------------------------------------------------------------------------------ drawn tables


@st.composite
def ladder(draw: Any, name: str) -> list[LimitRow]:
    """One limit: a non-empty set of tiers in rank order, thresholds further out per tier."""
    quantity = draw(st.sampled_from(sorted(QUANTITY_DIRECTION)))
    above = QUANTITY_DIRECTION[quantity] == "above"
    lo, hi = RANGES[quantity]
    path = draw(st.sampled_from(["charge", "discharge"]))
    when = draw(st.sampled_from(["always", "always", "charging", "discharging"]))
    tiers = [t for t in TIERS if draw(st.booleans())] or [draw(st.sampled_from(TIERS))]
    span = hi - lo
    x = draw(st.floats(lo, hi))
    rows = []
    for tier in tiers:
        band = draw(st.sampled_from([0.0, 0.01, 0.1, 0.3])) * span + 1e-3
        reset = x - band if above else x + band
        rows.append(
            LimitRow(
                limit=name,
                quantity=quantity,
                direction=QUANTITY_DIRECTION[quantity],
                path=path,
                when=when,
                tier=tier,
                threshold=x,
                reset=reset,
                debounce=draw(st.integers(1, 3)),
                # 1e-9 = the rules' time tolerance: a step of dt 0 lands on the comparison
                delay_s=draw(st.sampled_from([0.0, 0.0, 0.1, 0.3, 1.0, 1e-9])),
                latch_s=draw(st.sampled_from([None, 0.0, 0.0, 0.2, 1.0, 1e-9])),
            )
        )
        step = draw(st.sampled_from([0.02, 0.1, 0.25])) * span
        x = x + step if above else x - step
    return rows


@st.composite
def curve(draw: Any, lo: float, hi: float) -> CurveTable:
    xs = sorted(set(draw(st.lists(st.floats(lo, hi), min_size=1, max_size=5))))
    ys = [draw(st.one_of(st.floats(0.0, 20.0), st.sampled_from([0.0, -0.0, 2.0]))) for _ in xs]
    return CurveTable(x=tuple(xs), c_rate=tuple(ys))


@st.composite
def derating(draw: Any) -> DeratingConfig:
    if draw(st.booleans()):
        return DeratingConfig()
    return DeratingConfig(
        charge_vs_cell_v=draw(curve(2.5, 4.4)),
        charge_vs_temp_c=draw(curve(-30.0, 80.0)),
        charge_vs_soc=draw(curve(0.0, 1.0)),
        discharge_vs_cell_v=draw(curve(2.5, 4.4)),
        discharge_vs_temp_c=draw(curve(-30.0, 80.0)),
        discharge_vs_soc=draw(curve(0.0, 1.0)),
    )


@st.composite
def configs(draw: Any) -> LimitsConfig:
    kind = draw(st.integers(0, 4))
    if kind == 0:
        return LimitsConfig()
    if kind == 1:
        rows: tuple[LimitRow, ...] = LimitsConfig().rows
    else:
        n = draw(st.integers(1, 4))
        rows = tuple(r for j in range(n) for r in draw(ladder(f"lim{j}")))
        if draw(st.booleans()):  # interleave the ladders' rows
            rows = tuple(draw(st.permutations(rows)))
    return LimitsConfig(
        rows=rows,
        derating=draw(derating()),
        derate_fraction=draw(st.sampled_from([0.5, 0.0, 0.25, 1.0])),
        context_current_c=draw(st.sampled_from([0.05, 0.0, 0.5, 2.0])),
    )


@st.composite
def infos(draw: Any, n: int, groups: int) -> PackInfo:
    caps = draw(
        st.one_of(
            st.just(()),
            st.lists(
                st.one_of(st.floats(1.0, 20.0), st.sampled_from([5.0, 0.0, -1.0, math.nan])),
                min_size=n,
                max_size=n,
            ),
            st.lists(st.floats(1.0, 20.0), min_size=1, max_size=n),  # too short: the rest unknown
        )
    )
    return PackInfo(
        n_batteries=n,
        groups_per_battery=(groups,) * n,
        cells_per_group=(1,) * n,
        switch_kind=tuple(draw(st.sampled_from(list(SwitchKind))) for _ in range(n)),
        capacity_ah=tuple(caps),
    )


def knots(cfg: LimitsConfig) -> dict[str, list[float]]:
    """The derating tables' input points, per reading they are read at."""
    d = cfg.derating
    return {
        "max_cell_v": list(d.charge_vs_cell_v.x),
        "min_cell_v": list(d.discharge_vs_cell_v.x),
        "temp_c": [*d.charge_vs_temp_c.x, *d.discharge_vs_temp_c.x],
        "min_temp_c": [*d.charge_vs_temp_c.x, *d.discharge_vs_temp_c.x],
        "soc": [*d.charge_vs_soc.x, *d.discharge_vs_soc.x],
    }


@st.composite
def on_knots(draw: Any, meas: Measurements, points: dict[str, list[float]]) -> Measurements:
    """``meas`` with some readings exactly on a table's points (where the interpolation
    switches segment)."""
    bats = []
    for b in meas.batteries:
        kw = {f: draw(st.sampled_from(xs)) for f, xs in points.items() if draw(st.booleans())}
        bats.append(dataclasses.replace(b, **kw))
    return dataclasses.replace(meas, batteries=tuple(bats))


# ------------------------------------------------------------------------------ comparison


def same_queries(new: LimitsController, old: Oracle, where: str) -> None:
    n = new.pack.n_batteries
    got = [
        [new.is_active(i, k) for i in range(n) for k in range(len(new.rows))],
        [new.active_tier(i, name) for i in range(n) for name in (*new.ladders, "nope")],
        [new.tripped(i, path) for i in range(n) for path in ("charge", "discharge")],
        new.limit_chg_a,
        new.limit_dsg_a,
        new.pack_limit_chg_a,
        new.pack_limit_dsg_a,
    ]
    want = [
        [old.is_active(i, k) for i in range(n) for k in range(len(old.rows))],
        [old.active_tier(i, name) for i in range(n) for name in (*old.ladders, "nope")],
        [old.tripped(i, path) for i in range(n) for path in ("charge", "discharge")],
        old.limit_chg_a,
        old.limit_dsg_a,
        old.pack_limit_chg_a,
        old.pack_limit_dsg_a,
    ]
    assert same(got, want), (where, got, want)


@settings(max_examples=300, deadline=None)
@given(data=st.data(), n=st.integers(1, 4), groups=st.integers(1, 4))
def test_same_as_the_scalar_controller(data: Any, n: int, groups: int) -> None:
    cfg = data.draw(configs())
    info = data.draw(infos(n, groups))
    new, old = LimitsController(cfg, info), Oracle(cfg, info)
    seq = data.draw(sequence(n, groups))
    points = knots(cfg)
    for k, (drawn, dt) in enumerate(seq):
        meas = drawn if data.draw(st.integers(0, 4)) else data.draw(on_knots(drawn, points))
        if data.draw(st.integers(0, 7)) == 0:  # an operator's explicit reset
            b = data.draw(st.sampled_from([None, -1, n, *range(n)]))
            cleared = new.reset_trips(b)
            assert cleared == old.reset_trips(b), f"reset before step {k}"
            if cleared:
                event("explicit reset cleared a row")
        out = new.step(meas, dt)
        assert_same_output(out, old.step(meas, dt), n, f"step {k}")
        same_queries(new, old, f"step {k}")
        for e in out.events:
            event(e.message.split(": ")[0].split(" ", 1)[1])  # "warn", "trip cleared", ...
        if out.commands.charger is not None:
            event("charger off")
        if any(x is False for x in out.commands.chg_on + out.commands.dsg_on):
            event("path opened")
        if any(x != x for x in out.status["pack_limit_dsg_a"]):  # NaN
            event("pack limit unknown")


# ------------------------------------------------------------------------------ closed loops


def _rows(*specs: tuple[Any, ...]) -> tuple[LimitRow, ...]:
    out = []
    for limit, quantity, path, when, ladder_ in specs:
        for tier, threshold, reset, debounce, delay_s, latch_s in ladder_:
            out.append(
                LimitRow(
                    limit=limit,
                    quantity=quantity,
                    direction=QUANTITY_DIRECTION[quantity],
                    path=path,
                    when=when,
                    tier=tier,
                    threshold=threshold,
                    reset=reset,
                    debounce=debounce,
                    delay_s=delay_s,
                    latch_s=latch_s,
                )
            )
    return tuple(out)


TIGHT_DISCHARGE = LimitsConfig(
    rows=_rows(
        (
            "dsg",
            "dsg_c_rate",
            "discharge",
            "always",
            [
                ("warn", 1.0, 0.8, 2, 0.0, 0.0),
                ("derate", 2.0, 1.0, 3, 0.2, 1.0),
                ("trip", 2.8, 1.0, 3, 0.5, 2.0),
            ],
        ),
        (
            "uv",
            "cell_v_min",
            "discharge",
            "discharging",
            [("warn", 3.96, 3.97, 1, 0.0, 0.0), ("trip", 3.93, 3.95, 2, 1.0, None)],
        ),
        ("hot", "temp_max_c", "discharge", "always", [("derate", 25.5, 25.2, 3, 1.0, 5.0)]),
        ("cold", "temp_min_c", "charge", "charging", [("warn", 30.0, 31.0, 1, 0.0, 0.0)]),
    ),
    derate_fraction=0.25,
)
"""Enters and leaves every tier on a 6S 5 Ah pack under a few C of discharge."""

TIGHT_CHARGE = LimitsConfig(
    rows=_rows(
        (
            "ocv",
            "cell_v_max",
            "charge",
            "always",
            [("warn", 3.5, 3.45, 2, 0.0, 0.0), ("trip", 3.9, 3.85, 3, 0.5, None)],
        ),
        (
            "occ",
            "chg_c_rate",
            "charge",
            "charging",
            [("derate", 0.3, 0.2, 2, 0.5, 0.5), ("trip", 0.45, 0.1, 3, 0.5, 30.0)],
        ),
        ("any", "dsg_c_rate", "discharge", "discharging", [("warn", 0.01, 0.0, 1, 0.0, 0.0)]),
    ),
    derate_fraction=0.5,
    context_current_c=0.01,
)
"""Charge-side rows: the charger is switched off while docked with a charge trip."""


class Checked:
    """The compiled controller in the loop; the oracle, and side pairs with other tables, see
    the same measurements; every output is compared. ``reset_every`` steps, every battery gets
    an explicit reset (on both sides)."""

    def __init__(
        self,
        cfg: LimitsConfig,
        info: PackInfo,
        side: Sequence[LimitsConfig] = (),
        reset_every: int = 0,
    ) -> None:
        self.pairs = [(LimitsController(c, info), Oracle(c, info)) for c in (cfg, *side)]
        self.n = info.n_batteries
        self.reset_every = reset_every
        self.steps = 0
        self.kinds: collections.Counter[str] = collections.Counter()

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        self.steps += 1
        outs = []
        for j, (new, old) in enumerate(self.pairs):
            where = f"table {j} step {self.steps} t={meas.t_s}"
            if self.reset_every and self.steps % self.reset_every == 0:
                assert new.reset_trips() == old.reset_trips(), where
            a, b = new.step(meas, dt_s), old.step(meas, dt_s)
            assert_same_output(a, b, self.n, where)
            same_queries(new, old, where)
            self.kinds.update(f"{j}:{e.kind}" for e in a.events)
            outs.append(a)
        return outs[0]


def _run(cfg_dict: dict[str, Any], checked: Callable[[PackInfo], Checked]) -> Checked:
    runner = Runner(parse_config(cfg_dict), progress=False)
    chk = checked(runner.info)
    runner.controller = chk
    runner.run()
    return chk


def _supervised(
    runner: Runner,
    side: Sequence[LimitsConfig] = (),
    reset_every: int = 0,
    table: LimitsConfig | None = None,
) -> Checked:
    """Put a :class:`Checked` in place of the supervisor's limits layer (with its table, or
    ``table``)."""
    core = runner.controller
    assert isinstance(core, Core)
    (k,) = [
        j for j, x in enumerate(core.parts) if isinstance(x, Part) and x.method.name == "limits"
    ]
    assert runner.cfg.limits is not None
    chk = Checked(table or runner.cfg.limits, runner.info, side, reset_every)
    parts = [*core.parts[:k], chk, *core.parts[k + 1 :]]
    runner.controller = Core(core.infos, parts, core.supervisor_config)
    return chk


def _seen(chk: Checked, table: int) -> set[str]:
    return {k.split(":", 1)[1] for k in chk.kinds if k.startswith(f"{table}:")}


def test_closed_loop_uav_mission() -> None:
    """The example with ``[limits]`` (defaults, under the supervisor), 600 s, with the tight
    tables beside it."""
    cfg = load_config(EXAMPLES / "uav_mission.toml")
    cfg = cfg.model_copy(
        update={"sim": cfg.sim.model_copy(update={"duration_s": 600.0, "progress": False})}
    )
    runner = Runner(cfg, progress=False)
    chk = _supervised(runner, [TIGHT_DISCHARGE, TIGHT_CHARGE], reset_every=250)
    runner.run()
    assert chk.steps == 3000
    assert {"LimitWarning", "LimitDerate", "LimitReset"} <= _seen(chk, 1), chk.kinds


def test_closed_loop_tight_discharge_with_a_dead_sensor() -> None:
    """Two MOSFET batteries under 30 A with the tight table in the loop (trips open paths and
    latch; manual rows reset every 5 s); battery B's sensors read NaN from 10 s."""
    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=24.0,
        v_b=23.9,
        duration_s=40.0,
        load={"kind": "current", "value": 30.0},
    )
    d["controller"] = ["sequencing", "protection"]
    d["faults"] = [{"kind": "sensor_nan", "at_s": 10.0, "battery": "B"}]
    chk = _run(d, lambda info: Checked(TIGHT_DISCHARGE, info, [LimitsConfig()], reset_every=50))
    assert {"LimitWarning", "LimitDerate", "LimitTripped", "LimitReset"} <= _seen(chk, 0), chk.kinds


def test_closed_loop_relay_overcurrent_trip() -> None:
    """A relay pack under 60 A: both discharge trips open their relays, latch and clear."""
    d = dual_pack(switch={"kind": "relay"}, v_a=24.0, v_b=24.0, duration_s=30.0)
    d["load"] = {"kind": "current", "value": 60.0}
    d["controller"] = ["sequencing"]
    chk = _run(d, lambda info: Checked(TIGHT_DISCHARGE, info))
    assert {"LimitTripped", "LimitReset"} <= _seen(chk, 0), chk.kinds


def test_closed_loop_docked_charging() -> None:
    """The eVTOL charging example (six relay batteries, staged charging) under the supervisor
    with the charge-side table in the loop: charge-path trips open relays and switch the
    charger off; the manual voltage trip is reset every 100 s. Defaults beside it."""
    cfg = load_config(EXAMPLES / "evtol_charging.toml")
    cfg = cfg.model_copy(
        update={
            "sim": cfg.sim.model_copy(update={"duration_s": 3000.0, "progress": False}),
            "supervisor": SupervisorConfig(),
            "limits": LimitsConfig(),
        }
    )
    runner = Runner(cfg, progress=False)
    chk = _supervised(runner, [LimitsConfig()], reset_every=50, table=TIGHT_CHARGE)
    runner.run()
    assert {"LimitWarning", "LimitDerate", "LimitTripped", "LimitReset"} <= _seen(chk, 0), chk.kinds


def test_closed_loop_cooling_failure_trips_over_temperature() -> None:
    """The fault-injection scenario: a battery without cooling trips its over-temperature row
    (default table, under the supervisor)."""
    d = dual_pack(
        switch={"kind": "mosfet_pair"},
        v_a=24.0,
        v_b=24.0,
        duration_s=700.0,
        dt_s=0.5,
        load={"kind": "current", "value": 50.0},
    )
    d["controller"] = ["sequencing", "protection"]
    d["supervisor"] = {}
    d["limits"] = {}
    d["pack"]["ambient_c"] = 40.0
    d["faults"] = [{"kind": "cooling_failure", "at_s": 0.0, "battery": "A", "cooling_factor": 0.01}]
    runner = Runner(parse_config(d), progress=False)
    chk = _supervised(runner, [TIGHT_DISCHARGE], reset_every=100)
    runner.run()
    assert "LimitTripped" in _seen(chk, 0), chk.kinds
