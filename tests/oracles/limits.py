"""ORACLE: the scalar limits controller as it was before the compiled core (tests only; deleted
once the golden and equivalence tests pass).

Absolute safety limits: warn / derate / trip tiers with debounce, delay, hysteresis and latch.

The tiers follow foxBMS's safe-operating-area layers: a *warn* row is the maximum operating
limit (MOL, an event only), a *derate* row the recommended safety limit (RSL, the published
current limit of that path drops to ``derate_fraction``), a *trip* row the maximum safety limit
(MSL, the path is opened and stays open until its reset condition). Every row is data
(:class:`LimitRow`), so a pack's limits are a table in the TOML file, not code.

A row is violated while its quantity is strictly beyond ``threshold``. It becomes active once
``debounce`` consecutive samples violated it *and* the violation then persisted ``delay_s``
more seconds (the debounce rejects single-sample glitches, the delay sets the time scale).
It clears when the quantity is back at or past ``reset`` (hysteresis) and it has been active
for at least ``latch_s``; ``latch_s = None`` means only :meth:`LimitsController.reset_trips`
(an operator or supervisor decision) clears it. A non-finite value neither counts nor clears
(sensor plausibility is :mod:`packpilot.control.plausibility`'s job); this layer holds its state.

The published current limits (charge and discharge, per battery and for the pack) are the
minimum of three piecewise-linear C-rate tables over cell voltage, temperature and SOC, scaled
by the battery's capacity. For parallel batteries the pack limit is N x the smallest limit of
the N batteries that can conduct in that direction (current shares roughly equally, so the
weakest battery sets everyone's share).

Defaults are for a Li-ion NMC / LiPo pouch cell (4.2 V full); see ``docs/safety.md``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from packpilot.config.limits import (
    QUANTITY_DIRECTION,
    TIER_RANK,
    LimitsConfig,
    Path,
)
from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    ControlOutput,
    Event,
    Measurements,
    SwitchKind,
)
from packpilot.contract.charger import CHARGER_OFF
from packpilot.contract.topology import PackInfo

TIER_EVENT: Mapping[str, str] = {
    "warn": "LimitWarning",
    "derate": "LimitDerate",
    "trip": "LimitTripped",
}

EPS = 1e-9
"""Time comparisons tolerate float round-off of summed ``dt_s`` (10 x 0.1 s = 0.9999999)."""


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


# ------------------------------------------------------------------------------ controller


@dataclass(slots=True)
class _RowState:
    count: int = 0
    held_s: float = 0.0
    active: bool = False
    active_s: float = 0.0
    clear_ok: bool = False
    value: float = math.nan


def capacity_ah(pack: PackInfo, i: int, bm: BatteryMeasurement | None) -> float:
    """Nominal capacity from the pack facts, else the battery's reported full capacity, else NaN."""
    if i < len(pack.capacity_ah) and _finite(pack.capacity_ah[i]) and pack.capacity_ah[i] > 0:
        return float(pack.capacity_ah[i])
    if bm is not None and _finite(bm.full_capacity_ah) and bm.full_capacity_ah > 0:
        return float(bm.full_capacity_ah)
    return math.nan


def conducts(pack: PackInfo, i: int, bm: BatteryMeasurement, path: Path) -> bool:
    """Switch feedback says the battery can carry current in ``path``'s direction.

    A relay conducts both ways only when closed; a MOSFET pair conducts discharge while its
    discharge FET is on (the charge FET's body diode passes it) and charge while its charge FET
    is on.
    """
    sw = bm.switch
    kind = pack.switch_kind[i] if i < len(pack.switch_kind) else SwitchKind.RELAY
    if kind == SwitchKind.RELAY:
        return sw.relay_closed
    return sw.chg_on if path == "charge" else sw.dsg_on


def _num(x: float) -> float | None:
    return float(x) if _finite(x) else None


class LimitsController:
    """Evaluates every limit row for every battery each tick; see the module docstring.

    Commands: ``chg_on=False`` while a charge-path trip is active, ``dsg_on=False`` while a
    discharge-path trip is active, otherwise ``None`` (no opinion: after a trip clears, the path
    closes again only when a method controller commands it, e.g. after voltage matching), and
    ``charger=CHARGER_OFF`` while docked with any charge-path trip active.
    """

    def __init__(self, config: LimitsConfig, pack: PackInfo) -> None:
        self.config = config
        self.pack = pack
        self.rows = config.rows
        self.ladders: dict[str, tuple[int, ...]] = {}
        for k, row in enumerate(self.rows):
            self.ladders[row.limit] = (*self.ladders.get(row.limit, ()), k)
        n = pack.n_batteries
        self._state = [[_RowState() for _ in self.rows] for _ in range(n)]
        self._pending: list[Event] = []
        self._limit_chg_a: list[float] = [0.0] * n
        self._limit_dsg_a: list[float] = [0.0] * n
        self._pack_chg_a = 0.0
        self._pack_dsg_a = 0.0
        self._t_s = math.nan

    # -- queries --------------------------------------------------------------------------

    def is_active(self, battery: int, row: int) -> bool:
        return self._state[battery][row].active

    def active_tier(self, battery: int, limit: str) -> str:
        """Highest active tier of one limit for one battery: 'ok', 'warn', 'derate' or 'trip'."""
        best = "ok"
        for k in self.ladders.get(limit, ()):
            tier = self.rows[k].tier
            if self._state[battery][k].active and (
                best == "ok" or TIER_RANK[tier] > TIER_RANK[best]
            ):
                best = tier
        return best

    def tripped(self, battery: int, path: Path) -> bool:
        return any(
            st.active and row.tier == "trip" and row.path == path
            for row, st in zip(self.rows, self._state[battery], strict=True)
        )

    @property
    def limit_chg_a(self) -> tuple[float, ...]:
        """Per-battery charge current limit (A) from the last tick."""
        return tuple(self._limit_chg_a)

    @property
    def limit_dsg_a(self) -> tuple[float, ...]:
        return tuple(self._limit_dsg_a)

    @property
    def pack_limit_chg_a(self) -> float:
        """N x the smallest charge limit of the N batteries that can take charge now (A)."""
        return self._pack_chg_a

    @property
    def pack_limit_dsg_a(self) -> float:
        return self._pack_dsg_a

    def reset_trips(self, battery: int | None = None) -> int:
        """Explicit reset: clear active rows (any latch) whose quantity is past its reset value.

        Returns how many rows cleared; their ``LimitReset`` events come with the next tick.
        """
        n = 0
        targets = range(len(self._state)) if battery is None else (battery,)
        for i in targets:
            if not 0 <= i < len(self._state):
                continue
            for k, st in enumerate(self._state[i]):
                if st.active and st.clear_ok:
                    self._deactivate(
                        i, k, st, math.nan, manual=True, events=self._pending, t_s=self._t_s
                    )
                    n += 1
        return n

    # -- the tick -------------------------------------------------------------------------

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        dt = float(dt_s) if _finite(dt_s) and dt_s > 0.0 else 0.0
        self._t_s = meas.t_s
        events, self._pending = self._pending, []
        fresh: list[Event] = []
        n = self.pack.n_batteries
        docked = bool(meas.docked)
        bms: list[BatteryMeasurement | None] = [
            meas.batteries[i] if i < len(meas.batteries) else None for i in range(n)
        ]
        for i in range(n):
            self._step_battery(i, bms[i], docked, meas.t_s, dt, fresh)
        self._update_limits(bms)
        for ev in fresh:
            data = dict(ev.data)
            data["pack_limit_chg_a"] = _num(self._pack_chg_a)
            data["pack_limit_dsg_a"] = _num(self._pack_dsg_a)
            events.append(Event(ev.t_s, ev.kind, ev.battery, ev.message, data))
        chg: list[bool | None] = [False if self.tripped(i, "charge") else None for i in range(n)]
        dsg: list[bool | None] = [False if self.tripped(i, "discharge") else None for i in range(n)]
        charger = CHARGER_OFF if docked and any(c is False for c in chg) else None
        status: dict[str, Sequence[float | int | str | bool | None]] = {
            f"lim_{name}": [self.active_tier(i, name) for i in range(n)] for name in self.ladders
        }
        status["limit_chg_a"] = list(self._limit_chg_a)
        status["limit_dsg_a"] = list(self._limit_dsg_a)
        status["pack_limit_chg_a"] = [self._pack_chg_a] * n
        status["pack_limit_dsg_a"] = [self._pack_dsg_a] * n
        return ControlOutput(
            commands=Commands(chg_on=tuple(chg), dsg_on=tuple(dsg), charger=charger),
            events=tuple(events),
            status=status,
        )

    # -- internals ------------------------------------------------------------------------

    def _values(self, i: int, bm: BatteryMeasurement | None) -> dict[str, float]:
        if bm is None or not bm.present:
            return dict.fromkeys(QUANTITY_DIRECTION, math.nan)
        cap = capacity_ah(self.pack, i, bm)
        cur = bm.current_a
        coldest = bm.min_temp_c if _finite(bm.min_temp_c) else bm.temp_c
        return {
            "cell_v_max": bm.max_cell_v,
            "cell_v_min": bm.min_cell_v,
            "chg_c_rate": max(0.0, -cur) / cap if _finite(cur) else math.nan,
            "dsg_c_rate": max(0.0, cur) / cap if _finite(cur) else math.nan,
            "temp_max_c": bm.temp_c,
            "temp_min_c": coldest,
        }

    def _contexts(self, i: int, bm: BatteryMeasurement | None, docked: bool) -> dict[str, bool]:
        if bm is None or not bm.present:
            return {"always": True, "charging": docked, "discharging": False}
        cap = capacity_ah(self.pack, i, bm)
        band = self.config.context_current_c * cap if _finite(cap) else 0.0
        cur = bm.current_a
        return {
            "always": True,
            "charging": docked or (_finite(cur) and cur < -band),
            "discharging": _finite(cur) and cur > band and not docked,
        }

    def _step_battery(
        self,
        i: int,
        bm: BatteryMeasurement | None,
        docked: bool,
        t_s: float,
        dt: float,
        events: list[Event],
    ) -> None:
        values = self._values(i, bm)
        ctx = self._contexts(i, bm, docked)
        for k, row in enumerate(self.rows):
            st = self._state[i][k]
            v = values[row.quantity]
            st.value = v
            violating = False
            if not ctx[row.when]:
                st.count, st.held_s = 0, 0.0
                st.clear_ok = True
            elif not _finite(v):
                st.clear_ok = False  # unknown: hold counters and the active state
            else:
                violating = row.violated(v)
                st.clear_ok = row.cleared(v)
                if violating:
                    if st.count >= row.debounce:
                        st.held_s += dt
                    else:
                        st.count += 1
                        st.held_s = 0.0
                else:
                    st.count, st.held_s = 0, 0.0
            if st.active:
                st.active_s += dt
                latch = row.latch_s
                if st.clear_ok and latch is not None and st.active_s >= latch - EPS:
                    self._deactivate(i, k, st, v, manual=False, events=events, t_s=t_s)
            elif violating and st.count >= row.debounce and st.held_s >= row.delay_s - EPS:
                st.active, st.active_s = True, 0.0
                events.append(
                    Event(
                        t_s=t_s,
                        kind=TIER_EVENT[row.tier],
                        battery=i,
                        message=f"{row.limit} {row.tier}: {row.quantity} {v:g} "
                        f"{'>' if row.direction == 'above' else '<'} {row.threshold:g}",
                        data=self._row_data(k, v),
                    )
                )

    def _row_data(self, k: int, value: float) -> dict[str, float | int | str | bool | None]:
        row = self.rows[k]
        return {
            "row": k,
            "limit": row.limit,
            "tier": row.tier,
            "quantity": row.quantity,
            "path": row.path,
            "value": _num(value),
            "threshold": row.threshold,
            "reset": row.reset,
        }

    def _deactivate(
        self,
        i: int,
        k: int,
        st: _RowState,
        value: float,
        *,
        manual: bool,
        events: list[Event],
        t_s: float = math.nan,
    ) -> None:
        st.active, st.active_s, st.count, st.held_s = False, 0.0, 0, 0.0
        row = self.rows[k]
        data = self._row_data(k, st.value if not _finite(value) else value)
        data["manual"] = manual
        events.append(
            Event(
                t_s=t_s,
                kind="LimitReset",
                battery=i,
                message=f"{row.limit} {row.tier} cleared" + (" (explicit reset)" if manual else ""),
                data=data,
            )
        )

    def _update_limits(self, bms: Sequence[BatteryMeasurement | None]) -> None:
        der = self.config.derating
        frac = self.config.derate_fraction
        n = self.pack.n_batteries
        chg_ok: list[int] = []
        dsg_ok: list[int] = []
        for i in range(n):
            bm = bms[i]
            if bm is None or not bm.present:
                self._limit_chg_a[i] = self._limit_dsg_a[i] = 0.0
                continue
            cap = capacity_ah(self.pack, i, bm)
            lim = {"charge": der.charge_c(bm) * cap, "discharge": der.discharge_c(bm) * cap}
            for path in ("charge", "discharge"):
                tiers = {
                    row.tier
                    for row, st in zip(self.rows, self._state[i], strict=True)
                    if st.active and row.path == path
                }
                if "trip" in tiers:
                    lim[path] = 0.0
                elif "derate" in tiers:
                    lim[path] *= frac  # once per path, however many derate rows are active
            self._limit_chg_a[i] = lim["charge"]
            self._limit_dsg_a[i] = lim["discharge"]
            if not self.tripped(i, "charge") and conducts(self.pack, i, bm, "charge"):
                chg_ok.append(i)
            if not self.tripped(i, "discharge") and conducts(self.pack, i, bm, "discharge"):
                dsg_ok.append(i)
        self._pack_chg_a = _pack_limit([self._limit_chg_a[i] for i in chg_ok])
        self._pack_dsg_a = _pack_limit([self._limit_dsg_a[i] for i in dsg_ok])


def _pack_limit(limits: Sequence[float]) -> float:
    """N x the smallest of N parallel batteries' limits (NaN if any of them is unknown)."""
    if not limits:
        return 0.0
    if not all(_finite(x) for x in limits):
        return math.nan
    return len(limits) * min(limits)


__all__ = ["TIER_EVENT", "LimitsController", "capacity_ah", "conducts"]
