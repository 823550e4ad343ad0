"""Charger current per stage (``current_law``): the square-root law, its cap at the charger
limit, its combination with the per-battery limit, and the law as followed in a closed loop."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st
from pydantic import ValidationError

from packpilot.control.charging import ChargingConfig, ChargingController, Stage, rules
from tests.budget import budget
from tests.test_charging_helpers import ToyPack, pack_info


def stage_current_a(cfg: ChargingConfig, n_connected: int, n_to_charge: int) -> float:
    """Charger current limit for a stage with ``n_connected`` of ``n_to_charge`` batteries
    (:func:`rules.stage_current` on the settings of ``cfg``)."""
    limit = float(cfg.charger_current_limit_a)
    full = cfg.full_current_a if cfg.full_current_a is not None else limit
    per = cfg.battery_current_limit_a
    current = rules.stage_current(
        limit, cfg.current_law == "sqrt", float(full), per is not None,
        math.nan if per is None else float(per), int(n_connected), int(n_to_charge),
    )  # fmt: skip
    return float(current)


@pytest.mark.parametrize("n_total", [1, 2, 3, 6, 12])
def test_sqrt_law_for_every_stage_size(n_total: int) -> None:
    cfg = ChargingConfig(charger_current_limit_a=100.0, current_law="sqrt")
    for n in range(1, n_total + 1):
        i = stage_current_a(cfg, n, n_total)
        assert i == pytest.approx(100.0 * math.sqrt(n / n_total))
        assert i <= cfg.charger_current_limit_a
    assert stage_current_a(cfg, n_total, n_total) == 100.0  # all connected: the full limit


def test_sqrt_law_equal_heat_rate_and_cap() -> None:
    """Uncapped stages see the same total heat rate I²·R/n; I_full above the charger limit
    raises the small stages while the large ones stay at the limit."""
    cfg = ChargingConfig(charger_current_limit_a=100.0, current_law="sqrt", full_current_a=150.0)
    currents = [stage_current_a(cfg, n, 6) for n in range(1, 7)]
    assert currents[:2] == pytest.approx([150.0 * math.sqrt(n / 6) for n in (1, 2)])
    assert currents[2:] == [100.0] * 4  # 150·sqrt(3/6) = 106 A is capped
    rates = [currents[n - 1] ** 2 / n for n in (1, 2)]
    assert rates[0] == pytest.approx(rates[1])
    assert rates[0] == pytest.approx(150.0**2 / 6)


def test_constant_law_and_per_battery_limit_unchanged() -> None:
    cfg = ChargingConfig(charger_current_limit_a=100.0)
    assert cfg.current_law == "constant"
    assert [stage_current_a(cfg, n, 6) for n in (1, 3, 6)] == [100.0] * 3
    per = ChargingConfig(charger_current_limit_a=100.0, battery_current_limit_a=20.0)
    assert [stage_current_a(per, n, 6) for n in (1, 2, 4, 5, 6)] == [20, 40, 80, 100, 100]
    both = ChargingConfig(
        charger_current_limit_a=100.0, battery_current_limit_a=20.0, current_law="sqrt"
    )
    # min(100, 100·sqrt(n/6), 20·n): the per-battery limit binds up to n = 4, the law at 5
    assert [stage_current_a(both, n, 6) for n in (1, 2, 4)] == [20.0, 40.0, 80.0]
    assert stage_current_a(both, 5, 6) == pytest.approx(100.0 * math.sqrt(5 / 6))
    assert stage_current_a(both, 6, 6) == 100.0


@budget(300)
@given(
    limit=st.floats(min_value=1.5, max_value=500.0),
    full=st.one_of(st.none(), st.floats(min_value=1.5, max_value=1000.0)),
    per_battery=st.one_of(st.none(), st.floats(min_value=1.5, max_value=200.0)),
    n_total=st.integers(min_value=1, max_value=24),
    data=st.data(),
)
def test_law_properties(
    limit: float,
    full: float | None,
    per_battery: float | None,
    n_total: int,
    data: st.DataObject,
) -> None:
    cfg = ChargingConfig(
        charger_current_limit_a=limit,
        current_law="sqrt",
        full_current_a=full,
        battery_current_limit_a=per_battery,
    )
    i_full = limit if full is None else full
    prev = 0.0
    for n in range(1, n_total + 1):
        i = stage_current_a(cfg, n, n_total)
        assert 0.0 < i <= limit
        assert i <= i_full * math.sqrt(n / n_total) * (1 + 1e-12)
        if per_battery is not None:
            assert i <= n * per_battery * (1 + 1e-12)
        else:
            assert i == pytest.approx(min(limit, i_full * math.sqrt(n / n_total)))
        assert i >= prev  # more batteries connected never lowers the current
        prev = i
    # an inconsistent count (more connected than still to charge) is read as "all connected"
    n = data.draw(st.integers(min_value=n_total, max_value=n_total + 5))
    assert stage_current_a(cfg, n, n_total) <= limit
    if per_battery is None:
        assert stage_current_a(cfg, n, n_total) == stage_current_a(cfg, n_total, n_total)


@pytest.mark.parametrize(
    ("kw", "fragment"),
    [
        ({"full_current_a": 0.0}, "full_current_a"),
        ({"full_current_a": math.inf}, "full_current_a"),
        ({"full_current_a": 0.5}, "must be smaller than full_current_a (0.5)"),
        ({"current_law": "linear"}, "current_law"),
    ],
)
def test_invalid_law_settings(kw: dict[str, object], fragment: str) -> None:
    with pytest.raises(ValidationError) as err:
        ChargingConfig.model_validate(kw)
    assert fragment in str(err.value)


def _charge(cfg: ChargingConfig, v0: list[float]) -> tuple[ToyPack, list[tuple[int, int, float]]]:
    """Closed loop on the toy pack; per charging period (n connected, n to charge, command)."""
    ctrl = ChargingController(cfg, pack_info(len(v0)))
    toy = ToyPack(v0, r_ohm=0.1, capacity_ah=5.0, slope_v_per_ah=8.0)
    seen: list[tuple[int, int, float]] = []
    for _ in range(40_000):
        out = ctrl.step(toy.measure(), 1.0)
        ch = out.commands.charger
        assert ch is not None
        if ch.enable and ctrl.stage not in (Stage.COMPLETE, Stage.IDLE):
            n = sum(1 for c in out.commands.chg_on if c)
            n_total = sum(1 for d in out.status["chg_done"] if not d)
            seen.append((n, n_total, ch.current_a))
        toy.apply(out)
        toy.step(1.0)
        if any(e.kind == "ChargeComplete" for e in out.events):
            return toy, seen
    raise AssertionError("charge did not complete")


def test_closed_loop_follows_the_law_and_heats_less() -> None:
    v0 = [80.0, 80.0, 90.0, 90.0, 100.0, 100.0]
    sqrt_toy, seen = _charge(ChargingConfig(current_law="sqrt"), v0)
    sizes = {n for n, _, _ in seen}
    assert {2, 4, 6} <= sizes
    for n, n_total, cmd in seen:
        assert cmd == pytest.approx(min(20.0, 20.0 * math.sqrt(n / n_total)))
    const_toy, _ = _charge(ChargingConfig(), v0)
    assert all(v >= 119.0 for v in sqrt_toy.ocv)
    # same charge delivered, lower current in the small stages: less I²R heat, more time
    assert sum(sqrt_toy.heat_j) < sum(const_toy.heat_j)
    assert sqrt_toy.t_s > const_toy.t_s
