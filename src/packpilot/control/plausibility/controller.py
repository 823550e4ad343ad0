"""The plausibility monitor as a core method, and its one-pack face :class:`PlausibilityMonitor`."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Sequence

import numpy as np

from packpilot.config.plausibility import PlausibilityConfig
from packpilot.contract.arrays import NO_OPINION, cmd_arrays, meas_arrays
from packpilot.contract.bms import Commands, ControlOutput, Measurements
from packpilot.contract.events import Labels, Reason, Source, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.control.plausibility import rules
from packpilot.control.plausibility.rules import (
    FIELDS,
    KINDS,
    N_KINDS,
    NONFINITE_TEXT,
    REACTIONS,
    PlausibilityParams,
    PlausibilityState,
)
from packpilot.errors import ConfigError

_FAULT = "{kind}: {field} = {value} -> {reaction}"


def _fault(battery: str, value: str) -> Reason:
    return Reason(
        "Fault",
        _FAULT,
        fields(battery, "kind:l:kinds", "field:l:fields", value, "reaction:l:reactions"),
    )


def _cleared(battery: str, manual: bool) -> Reason:
    return Reason(
        "FaultCleared",
        "{kind} cleared" + (" (service reset)" if manual else ""),
        fields(battery, "kind:l:kinds", "field:l:fields", "manual:b"),
    )


REASONS = (
    _fault("battery:i", "value"),  # FAULT_FLOAT
    _fault("battery:i", "value:l:nonfinite"),  # FAULT_TEXT
    _fault("battery:i", "value:b"),  # FAULT_BOOL
    _fault("battery:i", "value:i"),  # FAULT_INT
    _fault("battery:o", "value:l:nonfinite"),  # PACK_FAULT (battery None)
    _cleared("battery:i", False),  # CLEARED
    _cleared("battery:i", True),  # CLEARED_MANUAL
    _cleared("battery:o", False),  # PACK_CLEARED
    _cleared("battery:o", True),  # PACK_CLEARED_MANUAL
    Reason(  # RESERVE_ENGAGED
        "ReserveEngaged",
        "reserve brought in (no trusted battery supplies the load; charge path stays off)",
        fields("battery:i"),
    ),
)
STATUS = (StatusChannel("plaus_faults", "l:faultsets"), StatusChannel("plaus_isolated", "b"))


def field_labels(max_groups: int) -> list[str]:
    """Field labels, ``group_voltages_v[g]`` for ``g < max_groups`` included."""
    return [*FIELDS, *(f"group_voltages_v[{g}]" for g in range(max_groups))]


@functools.cache
def fault_sets() -> tuple[str, ...]:
    """The ``plaus_faults`` text of every set of latched kinds (index: bit mask over KINDS)."""
    return tuple(
        ",".join(sorted(KINDS[k] for k in range(N_KINDS) if mask >> k & 1))
        for mask in range(1 << N_KINDS)
    )


def _labels_for(max_groups: int) -> Labels:
    return {
        "kinds": KINDS,
        "fields": field_labels(max_groups),
        "nonfinite": NONFINITE_TEXT,
        "reactions": REACTIONS,
        "faultsets": fault_sets(),
    }


def _labels(prm: PlausibilityParams) -> Labels:
    return _labels_for(prm.max_groups)


def _opt(x: float | None) -> tuple[bool, float]:
    return (x is not None, float(x) if x is not None else math.nan)


def build(
    config: PlausibilityConfig, infos: Sequence[PackInfo]
) -> tuple[PlausibilityParams, PlausibilityState]:
    info = infos[0]
    n = info.n_batteries
    for name in ("groups_per_battery", "cells_per_group", "switch_kind"):
        if len(getattr(info, name)) != n:
            raise ConfigError(f"plausibility: PackInfo.{name} must give one entry per battery")
    groups = max(info.groups_per_battery, default=0)
    stuck_on, stuck_s = _opt(config.stuck_time_s)
    temp_on, temp_s = _opt(config.stuck_temp_time_s)
    prm = PlausibilityParams(
        cell_lo=float(config.cell_v_range[0]),
        cell_hi=float(config.cell_v_range[1]),
        temp_lo=float(config.temp_range_c[0]),
        temp_hi=float(config.temp_range_c[1]),
        cur_lo=float(config.current_range_c[0]),
        cur_hi=float(config.current_range_c[1]),
        soc_lo=float(config.soc_range[0]),
        soc_hi=float(config.soc_range[1]),
        nonfinite_delay_s=float(config.nonfinite_delay_s),
        range_delay_s=float(config.range_delay_s),
        stuck_on=stuck_on,
        stuck_time_s=stuck_s,
        stuck_temp_on=temp_on,
        stuck_temp_time_s=temp_s,
        stuck_current_c=float(config.stuck_current_c),
        max_sample_age_s=float(config.max_sample_age_s),
        sum_tolerance_v_per_group=float(config.sum_tolerance_v_per_group),
        sum_delay_s=float(config.sum_delay_s),
        switch_delay_s=float(config.switch_delay_s),
        clear_after_s=float(config.clear_after_s),
        max_groups=int(groups),
    )
    return prm, allocate(len(infos), n, max(groups, 1))


def allocate(n_packs: int, n_batteries: int, n_groups: int) -> PlausibilityState:
    """Fresh state: nothing latched, no command seen, every stuck track empty."""
    det = (n_packs, n_batteries + 1, N_KINDS)
    bat = (n_packs, n_batteries)
    tracks = (n_packs, n_batteries, rules.T_GROUP0 + n_groups)
    q = (n_packs, n_batteries * N_KINDS + 1)
    return PlausibilityState(
        bad_s=np.zeros(det),
        ok_s=np.zeros(det),
        was_bad=np.zeros(det, np.bool_),
        latched=np.zeros(det, np.bool_),
        field=np.zeros(det, np.int64),
        last=np.full(tracks, np.nan),
        unchanged_s=np.zeros(tracks),
        cmd_chg=np.full(bat, NO_OPINION, np.int8),
        cmd_dsg=np.full(bat, NO_OPINION, np.int8),
        isolated=np.zeros(bat, np.bool_),
        t_s=np.full(n_packs, np.nan),
        pend_n=np.zeros(n_packs, np.int64),
        pend_bat=np.zeros(q, np.int64),
        pend_kind=np.zeros(q, np.int64),
        pend_field=np.zeros(q, np.int64),
        pend_t=np.zeros(q),
    )


def _max_events(info: PackInfo) -> int:
    # every detector may latch or clear once per step, plus the service resets queued before it
    return 2 * (info.n_batteries * N_KINDS + 1) + info.n_batteries  # + ReserveEngaged


METHOD = Method(
    name="plausibility",
    src=5,
    config=PlausibilityConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=_labels,
    max_events=_max_events,
    after=rules.note_commands_packs,
)


class PlausibilityMonitor(CompiledController):
    """Detects implausible measurements and switch failures (one pack); see ``rules``.

    The supervisor tells it the merged commands after every step (:meth:`note_commands`), so
    switch feedback can be compared with what was commanded.
    """

    method = METHOD
    config: PlausibilityConfig
    prm: PlausibilityParams
    st: PlausibilityState

    def __init__(self, config: PlausibilityConfig, pack: PackInfo) -> None:
        super().__init__(config, pack)
        self._note = cmd_arrays(1, pack.n_batteries, 1)

    # -- supervisor interface -------------------------------------------------------------

    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        n = self.pack.n_batteries
        seen = max((len(b.group_voltages_v) for b in meas.batteries[:n]), default=0)
        if seen > self._m.bat.group_v.shape[2]:
            self._grow(seen)
        return super().step(meas, dt_s)

    def _grow(self, n_groups: int) -> None:
        """Room for a battery that reports more group voltages than the pack has groups (a
        misbehaving monitor; the scalar contract allows it, the batch arrays have a fixed
        width): wider measurement arrays, more stuck tracks, more field labels."""
        n = self.pack.n_batteries
        self._m = meas_arrays(1, n, n_groups)
        st = self.st
        extra = rules.T_GROUP0 + n_groups - st.last.shape[2]
        if extra > 0:
            pad = ((0, 0), (0, 0), (0, extra))
            self.st = st._replace(
                last=np.pad(st.last, pad, constant_values=np.nan),
                unchanged_s=np.pad(st.unchanged_s, pad, constant_values=0.0),
            )
        self._source = Source(self.method.reasons, _labels_for(n_groups))

    def note_commands(self, commands: Commands) -> None:
        """Record the merged commands that were applied (``None`` keeps the previous state,
        as the hardware does)."""
        note = self._note
        for i in range(self.pack.n_batteries):
            c = commands.chg_on[i] if i < len(commands.chg_on) else None
            d = commands.dsg_on[i] if i < len(commands.dsg_on) else None
            note.chg_on[0, i] = NO_OPINION if c is None else int(bool(c))
            note.dsg_on[0, i] = NO_OPINION if d is None else int(bool(d))
        rules.note_commands_pack(self.prm, self.st, self.tp, self._m, 0, note)

    def clear_faults(self, battery: int | None = None, kinds: Iterable[str] | None = None) -> int:
        """Service reset: unlatch faults of one battery (or all) and of the given kinds (or all).

        The only way to clear a switch fault. A condition still present re-latches after its
        delay. Returns how many faults were cleared; ``FaultCleared`` events come with the next
        tick.
        """
        wanted = set(KINDS if kinds is None else kinds)
        mask = sum(1 << k for k, name in enumerate(KINDS) if name in wanted)
        every = battery is None
        i = 0 if battery is None else int(battery)
        return int(rules.clear_faults_pack(self.st, 0, every, i, mask))

    def _row(self, battery: int) -> int:
        n = self.pack.n_batteries
        i = int(battery)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"battery {battery} out of range")
        return i

    def faults(self, battery: int) -> frozenset[str]:
        """Latched fault kinds of one battery."""
        lat = self.st.latched[0, self._row(battery)]
        return frozenset(KINDS[k] for k in range(N_KINDS) if lat[k])

    @property
    def pack_fault(self) -> bool:
        """A pack-level measurement (bus voltage, load current) is not finite."""
        return bool(self.st.latched[0, self.pack.n_batteries, rules.K_NONFINITE])

    @property
    def welded(self) -> tuple[bool, ...]:
        """Relays known to be welded: never rely on them to isolate their battery."""
        n = self.pack.n_batteries
        return tuple(bool(x) for x in self.st.latched[0, :n, rules.K_RELAY_WELDED])


__all__ = [
    "METHOD",
    "REASONS",
    "STATUS",
    "PlausibilityMonitor",
    "allocate",
    "build",
    "fault_sets",
    "field_labels",
]
