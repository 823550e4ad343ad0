"""The safety limits as a core method, and their one-pack face :class:`LimitsController`.

The status channels are one ``lim_<limit>`` per limit of the table (its highest active tier)
and the four current limits, so they depend on the config: the core takes the method from
:func:`method_for` (``METHOD`` is the method for the default table).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from packpilot.config.limits import (
    CONTEXTS,
    PATHS,
    QUANTITIES,
    TIER_RANK,
    TIERS,
    LimitsConfig,
    Path,
)
from packpilot.contract.events import Field, Labels, Reason
from packpilot.contract.topology import PackInfo
from packpilot.control.limits import rules
from packpilot.control.limits.rules import F64, I64, LimitsParams, LimitsState
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.errors import ConfigError

TIER_EVENT: Mapping[str, str] = {
    "warn": "LimitWarning",
    "derate": "LimitDerate",
    "trip": "LimitTripped",
}
"""Event kind on entering each tier."""

TIER_STATES = ("ok", *TIERS)
"""Values of a ``lim_<limit>`` status channel."""

_ROW = (
    Field("row", rules.S_ROW, "i"),
    Field("limit", rules.S_LIMIT, "l:limit"),
    Field("tier", rules.S_TIER, "l:tier"),
    Field("quantity", rules.S_QUANTITY, "l:quantity"),
    Field("path", rules.S_PATH, "l:path"),
    Field("value", rules.S_VALUE, "o"),
    Field("threshold", rules.S_THRESHOLD, "f"),
    Field("reset", rules.S_RESET, "f"),
)
_MANUAL = Field("manual", rules.S_MANUAL, "b")
_PACK = (
    Field("pack_limit_chg_a", rules.S_PACK_CHG, "o"),
    Field("pack_limit_dsg_a", rules.S_PACK_DSG, "o"),
)
_OP = Field("op", rules.S_OP, "l:op", in_data=False)
_ENTERED = "{limit} {tier}: {quantity} {value:g} {op} {threshold:g}"

REASONS = (
    Reason(TIER_EVENT["warn"], _ENTERED, (*_ROW, *_PACK, _OP)),  # WARNED
    Reason(TIER_EVENT["derate"], _ENTERED, (*_ROW, *_PACK, _OP)),  # DERATED
    Reason(TIER_EVENT["trip"], _ENTERED, (*_ROW, *_PACK, _OP)),  # TRIPPED
    Reason("LimitReset", "{limit} {tier} cleared", (*_ROW, _MANUAL, *_PACK)),  # CLEARED
    Reason("LimitReset", "{limit} {tier} cleared (explicit reset)", (*_ROW, _MANUAL)),  # RESET
)
assert [r.kind for r in REASONS[: rules.CLEARED]] == [TIER_EVENT[t] for t in TIERS]

LIMIT_STATUS = (
    StatusChannel("limit_chg_a"),
    StatusChannel("limit_dsg_a"),
    StatusChannel("pack_limit_chg_a"),
    StatusChannel("pack_limit_dsg_a"),
)
"""The channels after the ``lim_<limit>`` ones (``rules.ST_*`` order)."""


def ladders(config: LimitsConfig) -> dict[str, tuple[int, ...]]:
    """Row indices of each limit, limits in order of first appearance."""
    out: dict[str, tuple[int, ...]] = {}
    for k, row in enumerate(config.rows):
        out[row.limit] = (*out.get(row.limit, ()), k)
    return out


def status_channels(config: LimitsConfig) -> tuple[StatusChannel, ...]:
    """``lim_<limit>`` per limit (its highest active tier), then the current limits."""
    tiers = tuple(StatusChannel(f"lim_{name}", "l:state") for name in ladders(config))
    return (*tiers, *LIMIT_STATUS)


def _curve_arrays(config: LimitsConfig) -> tuple[F64, F64, I64, F64]:
    d = config.derating
    tables = (
        d.charge_vs_cell_v,
        d.charge_vs_temp_c,
        d.charge_vs_soc,
        d.discharge_vs_cell_v,
        d.discharge_vs_temp_c,
        d.discharge_vs_soc,
    )
    width = max(len(t.x) for t in tables)
    xs = np.zeros((rules.N_CURVES, width))
    ys = np.zeros((rules.N_CURVES, width))
    for c, t in enumerate(tables):
        xs[c, : len(t.x)] = t.x
        ys[c, : len(t.x)] = t.c_rate
    n = np.array([len(t.x) for t in tables], np.int64)
    lowest = np.array([min(t.c_rate) for t in tables], np.float64)
    return xs, ys, n, lowest


def build(config: LimitsConfig, infos: Sequence[PackInfo]) -> tuple[LimitsParams, LimitsState]:
    rows = config.rows
    names = list(ladders(config))
    xs, ys, n_pts, lowest = _curve_arrays(config)
    prm = LimitsParams(
        quantity=np.array([QUANTITIES.index(r.quantity) for r in rows], np.int64),
        above=np.array([r.direction == "above" for r in rows], np.bool_),
        charge_path=np.array([r.path == "charge" for r in rows], np.bool_),
        when=np.array([CONTEXTS.index(r.when) for r in rows], np.int64),
        tier=np.array([TIER_RANK[r.tier] for r in rows], np.int64),
        ladder=np.array([names.index(r.limit) for r in rows], np.int64),
        threshold=np.array([float(r.threshold) for r in rows], np.float64),
        reset=np.array([float(r.reset) for r in rows], np.float64),
        debounce=np.array([int(r.debounce) for r in rows], np.int64),
        delay_s=np.array([float(r.delay_s) for r in rows], np.float64),
        latch_s=np.array(
            [math.nan if r.latch_s is None else float(r.latch_s) for r in rows], np.float64
        ),
        manual=np.array([r.latch_s is None for r in rows], np.bool_),
        n_ladders=len(names),
        curve_x=xs,
        curve_y=ys,
        curve_n=n_pts,
        curve_min=lowest,
        derate_fraction=float(config.derate_fraction),
        context_current_c=float(config.context_current_c),
    )
    n = infos[0].n_batteries
    for pk in infos:
        if pk.n_batteries != n:
            raise ConfigError("limits: every pack of a batch needs the same number of batteries")
    P, R = len(infos), len(rows)
    shape = (P, n, R)
    st = LimitsState(
        seen=np.zeros(shape, np.int64),
        held_s=np.zeros(shape),
        active=np.zeros(shape, np.bool_),
        active_s=np.zeros(shape),
        clear_ok=np.zeros(shape, np.bool_),
        value=np.full(shape, math.nan),
        limit_chg_a=np.zeros((P, n)),
        limit_dsg_a=np.zeros((P, n)),
        pack_chg_a=np.zeros(P),
        pack_dsg_a=np.zeros(P),
        t_s=np.full(P, math.nan),
        pending=np.zeros((P, max(n * R, 1)), np.int64),
        n_pending=np.zeros(P, np.int64),
        values=np.full((P, rules.N_QUANTITIES), math.nan),
        ctx=np.zeros((P, len(CONTEXTS)), np.bool_),
    )
    return prm, st


def method_for(config: LimitsConfig, infos: Sequence[PackInfo] = ()) -> Method:
    """The method for this table (any topology): its status channels, labels and event
    bound."""
    names = tuple(ladders(config))
    n_rows = len(config.rows)
    labels: Labels = {
        "limit": names,
        "tier": TIERS,
        "state": TIER_STATES,
        "quantity": QUANTITIES,
        "path": PATHS,
        "op": (">", "<"),
    }
    return Method(
        name="limits",
        src=4,
        config=LimitsConfig,
        build=build,
        step_packs=rules.step_packs,
        reasons=REASONS,
        status=status_channels(config),
        labels=lambda prm: labels,
        # every row may enter or clear in a step, and may have been reset since the last one
        max_events=lambda info: 2 * info.n_batteries * n_rows,
    )


METHOD = method_for(LimitsConfig())
STATUS = METHOD.status


class LimitsController(CompiledController):
    """Evaluates every limit row for every battery each tick (one pack); see
    :mod:`packpilot.control.limits.rules`.

    Commands: ``chg_on=False`` while a charge-path trip is active, ``dsg_on=False`` while a
    discharge-path trip is active, otherwise ``None`` (no opinion: after a trip clears, the path
    closes again only when a method controller commands it, e.g. after voltage matching), and
    ``charger=CHARGER_OFF`` while docked with any charge-path trip active.
    """

    method = METHOD
    prm: LimitsParams
    st: LimitsState
    config: LimitsConfig

    def __init__(self, config: LimitsConfig | Mapping[str, Any] | None, pack: PackInfo) -> None:
        cfg = config
        if not isinstance(cfg, LimitsConfig):
            cfg = LimitsConfig.model_validate(cfg or {})
        self.method = method_for(cfg)  # type: ignore[misc]  # the channels follow the table
        super().__init__(cfg, pack)
        self.rows = cfg.rows
        self.ladders = ladders(cfg)
        self._tiers = np.zeros((1, pack.n_batteries, max(len(self.ladders), 1)))

    # -- queries --------------------------------------------------------------------------

    def _battery(self, battery: int) -> int:
        n = int(self.st.active.shape[1])
        if not -n <= battery < n:
            raise IndexError(f"battery {battery} out of range (pack of {n})")
        return battery % n

    def is_active(self, battery: int, row: int) -> bool:
        return bool(self.st.active[0, self._battery(battery), row])

    def active_tier(self, battery: int, limit: str) -> str:
        """Highest active tier of one limit for one battery: 'ok', 'warn', 'derate' or 'trip'."""
        if limit not in self.ladders:
            return "ok"
        i = self._battery(battery)
        rules.tiers_into(self.prm, self.st, 0, i, self._tiers, 0)
        return TIER_STATES[int(self._tiers[0, i, list(self.ladders).index(limit)])]

    def tripped(self, battery: int, path: Path) -> bool:
        chg, dsg, _, _ = rules.path_tiers(self.prm, self.st, 0, self._battery(battery))
        return bool(chg if path == "charge" else dsg)

    @property
    def limit_chg_a(self) -> tuple[float, ...]:
        """Per-battery charge current limit (A) from the last tick."""
        return tuple(float(x) for x in self.st.limit_chg_a[0])

    @property
    def limit_dsg_a(self) -> tuple[float, ...]:
        return tuple(float(x) for x in self.st.limit_dsg_a[0])

    @property
    def pack_limit_chg_a(self) -> float:
        """N x the smallest charge limit of the N batteries that can take charge now (A)."""
        return float(self.st.pack_chg_a[0])

    @property
    def pack_limit_dsg_a(self) -> float:
        return float(self.st.pack_dsg_a[0])

    def reset_trips(self, battery: int | None = None) -> int:
        """Explicit reset: clear active rows (any latch) whose quantity is past its reset value.

        Returns how many rows cleared; their ``LimitReset`` events come with the next tick.
        """
        if battery is None:
            return int(rules.reset_trips(self.prm, self.st, 0, -1))
        if not 0 <= battery < self.st.active.shape[1]:
            return 0
        return int(rules.reset_trips(self.prm, self.st, 0, battery))


__all__ = [
    "LIMIT_STATUS",
    "METHOD",
    "REASONS",
    "STATUS",
    "TIER_EVENT",
    "TIER_STATES",
    "LimitsController",
    "build",
    "ladders",
    "method_for",
    "status_channels",
]
