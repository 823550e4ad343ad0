"""The contract for P packs at once: measurements, commands, events and status as arrays.

The compiled core (every rule of :mod:`packpilot.control`) reads and writes these named tuples
of NumPy arrays, shaped ``(P, B)`` for P packs of B traction batteries (``(P, B, G)`` for the
per-group values, G = the most series groups of any battery). A single run is P = 1, a
campaign batch P = 256; the same kernels serve both. Named tuples because numba compiles
attribute access on them to a plain load, and the same source runs as Python when the JIT is
off; every field is a contiguous array, so one compiled version serves every topology.

Encodings (the scalar contract's ``None`` has no float): a switch opinion is an ``int8``
(:data:`NO_OPINION` = -1, 0 off, 1 on); a value that may be absent has a ``*_set`` flag; a
sensor that is not reported reads NaN.

The conversions at the bottom turn the scalar :class:`~packpilot.contract.bms.Measurements`
into pack ``p`` of a batch and a batch's commands back into :class:`Commands`: the P = 1
adapters of the controllers use them, so the scalar and the batch form cannot drift.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.bms import (
    BatteryMeasurement,
    Commands,
    Measurements,
    SwitchKind,
    SwitchState,
)
from packpilot.contract.charger import CHARGER_FLAGS, ChargerCommand, ChargerStatus
from packpilot.contract.topology import PackInfo

F64 = NDArray[np.float64]
I8 = NDArray[np.int8]
I32 = NDArray[np.int32]
I64 = NDArray[np.int64]
B1 = NDArray[np.bool_]

NO_OPINION = -1
"""A controller that leaves a switch (or the aux relay) as it is."""


class BatteryArrays(NamedTuple):
    """What each battery reports (``BatteryMeasurement``), shape (P, B) unless noted."""

    voltage_v: F64
    current_a: F64
    temp_c: F64
    min_temp_c: F64
    min_cell_v: F64
    max_cell_v: F64
    soc: F64
    full_capacity_ah: F64
    remaining_capacity_ah: F64
    sample_age_s: F64
    cycle_count: F64
    """Cycles counted by the battery (NaN = not reported)."""
    group_v: F64
    """(P, B, G); NaN beyond ``n_groups``."""
    n_groups: I64
    """Number of group voltages the battery reported (0: none; may differ from the topology
    when a monitor misbehaves)."""
    sw_chg: B1
    sw_dsg: B1
    present: B1
    reported: B1
    """False where the measurement had no entry for this battery at all."""
    sw_explained: B1
    """The switch node explains a disagreement of the feedback with the commands (it opened
    on its command timeout, or has not obeyed our latest command yet): the plausibility layer
    does not judge the switches then. Only the CAN runtime sets it (issue #26)."""


class ChargerArrays(NamedTuple):
    """The charger's status (``ChargerStatus``), shape (P,)."""

    reported: B1
    """False: no status yet (``Measurements.charger is None``)."""
    output_v: F64
    output_a: F64
    flags: B1
    """(P, len(CHARGER_FLAGS))."""
    online: B1


class MeasArrays(NamedTuple):
    """One sample of P packs (``Measurements``)."""

    t_s: F64
    """(P,) time of each pack's sample."""
    bat: BatteryArrays
    aux: BatteryArrays
    """(P, 1): the auxiliary battery, where ``has_aux``."""
    has_aux: B1
    bus_v: F64
    load_current_a: F64
    docked: B1
    charger: ChargerArrays


class CmdArrays(NamedTuple):
    """What the controllers ask of P packs (``Commands``), merged as they write it."""

    chg_on: I8
    """(P, B): NO_OPINION, 0 or 1."""
    dsg_on: I8
    charger_set: B1
    """(P,): some controller commanded the charger."""
    charger_v: F64
    charger_a: F64
    charger_enable: B1
    balancer_set: B1
    balancer_a: F64
    """(P, B, G)."""
    aux_relay: I8
    """(P,): NO_OPINION, 0 or 1."""
    aux_charge_set: B1
    aux_charge_a: F64


class PackArrays(NamedTuple):
    """Static facts of P packs of one topology (``PackInfo``), for the kernels."""

    groups: I64
    """(B,) series groups of each traction battery."""
    cells_per_group: I64
    """(B,)."""
    relay: B1
    """(B,) switched by a relay (else a MOSFET pair)."""
    capacity_ah: F64
    """(P, B) nominal capacity (campaign draws differ per pack)."""
    has_aux: bool
    has_charger: bool
    has_balancers: bool


N_EVENT_VALUES = 24
"""Numbers an event can carry (its data fields, label codes included)."""


class EventBuf(NamedTuple):
    """Events of one step of P packs, in emission order: codes and numbers, no strings.

    A reason table (:mod:`packpilot.contract.events`) turns ``(src, code, val)`` into the
    :class:`~packpilot.contract.bms.Event` a user reads. Row ``capacity`` is a scratch row:
    an emitter that finds the buffer full writes there and counts the loss in ``dropped``.
    """

    n: I64
    """(1,) rows in use."""
    dropped: I64
    """(1,) events lost to a full buffer (never expected: capacity is sized per step)."""
    pack: I32
    src: I32
    """Which controller emitted it (its registry id)."""
    code: I32
    """The controller's reason code."""
    battery: I32
    """Traction index, -1 for the pack."""
    t_s: F64
    val: F64
    """(capacity + 1, N_EVENT_VALUES)."""

    @property
    def capacity(self) -> int:
        return int(self.pack.shape[0]) - 1


# ----------------------------------------------------------------------------- allocation


def battery_arrays(n_packs: int, n_batteries: int, n_groups: int) -> BatteryArrays:
    shape = (n_packs, n_batteries)

    def nan() -> F64:
        return np.full(shape, np.nan)

    return BatteryArrays(
        voltage_v=nan(),
        current_a=nan(),
        temp_c=nan(),
        min_temp_c=nan(),
        min_cell_v=nan(),
        max_cell_v=nan(),
        soc=nan(),
        full_capacity_ah=nan(),
        remaining_capacity_ah=nan(),
        sample_age_s=nan(),
        cycle_count=nan(),
        group_v=np.full((*shape, max(n_groups, 1)), np.nan),
        n_groups=np.zeros(shape, np.int64),
        sw_chg=np.zeros(shape, np.bool_),
        sw_dsg=np.zeros(shape, np.bool_),
        present=np.zeros(shape, np.bool_),
        reported=np.zeros(shape, np.bool_),
        sw_explained=np.zeros(shape, np.bool_),
    )


def meas_arrays(n_packs: int, n_batteries: int, n_groups: int) -> MeasArrays:
    """Measurements of ``n_packs`` packs, every sensor unread (NaN)."""
    P = n_packs
    return MeasArrays(
        t_s=np.zeros(P),
        bat=battery_arrays(P, n_batteries, n_groups),
        aux=battery_arrays(P, 1, n_groups),
        has_aux=np.zeros(P, np.bool_),
        bus_v=np.full(P, np.nan),
        load_current_a=np.zeros(P),
        docked=np.zeros(P, np.bool_),
        charger=ChargerArrays(
            reported=np.zeros(P, np.bool_),
            output_v=np.full(P, np.nan),
            output_a=np.full(P, np.nan),
            flags=np.zeros((P, len(CHARGER_FLAGS)), np.bool_),
            online=np.zeros(P, np.bool_),
        ),
    )


def cmd_arrays(n_packs: int, n_batteries: int, n_groups: int) -> CmdArrays:
    """Commands of ``n_packs`` packs with no opinion anywhere (see :func:`clear_commands`)."""
    P, shape = n_packs, (n_packs, n_batteries)
    cmd = CmdArrays(
        chg_on=np.empty(shape, np.int8),
        dsg_on=np.empty(shape, np.int8),
        charger_set=np.empty(P, np.bool_),
        charger_v=np.empty(P),
        charger_a=np.empty(P),
        charger_enable=np.empty(P, np.bool_),
        balancer_set=np.empty(P, np.bool_),
        balancer_a=np.empty((*shape, max(n_groups, 1))),
        aux_relay=np.empty(P, np.int8),
        aux_charge_set=np.empty(P, np.bool_),
        aux_charge_a=np.empty(P),
    )
    clear_commands(cmd)
    return cmd


def clear_commands(cmd: CmdArrays) -> None:
    """No opinion anywhere: the state every step's merge starts from."""
    cmd.chg_on.fill(NO_OPINION)
    cmd.dsg_on.fill(NO_OPINION)
    cmd.charger_set.fill(False)
    cmd.charger_v.fill(0.0)
    cmd.charger_a.fill(0.0)
    cmd.charger_enable.fill(False)
    cmd.balancer_set.fill(False)
    cmd.balancer_a.fill(0.0)
    cmd.aux_relay.fill(NO_OPINION)
    cmd.aux_charge_set.fill(False)
    cmd.aux_charge_a.fill(0.0)


def pack_arrays(infos: Sequence[PackInfo]) -> PackArrays:
    """The kernels' view of ``infos`` (one per pack, same topology)."""
    first = infos[0]
    return PackArrays(
        groups=np.array(first.groups_per_battery, np.int64),
        cells_per_group=np.array(first.cells_per_group, np.int64),
        relay=np.array([k is SwitchKind.RELAY for k in first.switch_kind], np.bool_),
        capacity_ah=np.array(
            [
                [
                    info.capacity_ah[i] if i < len(info.capacity_ah) else math.nan
                    for i in range(first.n_batteries)
                ]
                for info in infos
            ],
            np.float64,
        ).reshape(len(infos), first.n_batteries),
        has_aux=bool(first.has_aux),
        has_charger=bool(first.has_charger),
        has_balancers=bool(first.has_balancers),
    )


def event_buf(capacity: int) -> EventBuf:
    """An empty event buffer with room for ``capacity`` events (plus the scratch row)."""
    n = capacity + 1
    return EventBuf(
        n=np.zeros(1, np.int64),
        dropped=np.zeros(1, np.int64),
        pack=np.zeros(n, np.int32),
        src=np.zeros(n, np.int32),
        code=np.zeros(n, np.int32),
        battery=np.zeros(n, np.int32),
        t_s=np.zeros(n),
        val=np.zeros((n, N_EVENT_VALUES)),
    )


# ----------------------------------------------------------------------------- scalar <-> batch


def _num(x: Any) -> float:
    """A reading as a float; anything that is not a number reads NaN (a lying sensor)."""
    if isinstance(x, bool):
        return float(x)
    try:
        return float(x)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _put_battery(a: BatteryArrays, p: int, i: int, b: BatteryMeasurement | None) -> None:
    a.reported[p, i] = b is not None
    if b is None:
        for arr in (a.voltage_v, a.current_a, a.temp_c, a.min_temp_c, a.min_cell_v):
            arr[p, i] = math.nan
        for arr in (a.max_cell_v, a.soc, a.full_capacity_ah, a.remaining_capacity_ah):
            arr[p, i] = math.nan
        a.sample_age_s[p, i] = math.nan
        a.cycle_count[p, i] = math.nan
        a.group_v[p, i] = math.nan
        a.n_groups[p, i] = 0
        a.sw_chg[p, i] = a.sw_dsg[p, i] = a.present[p, i] = False
        return
    a.voltage_v[p, i] = _num(b.voltage_v)
    a.current_a[p, i] = _num(b.current_a)
    a.temp_c[p, i] = _num(b.temp_c)
    a.min_temp_c[p, i] = _num(b.min_temp_c)
    a.min_cell_v[p, i] = _num(b.min_cell_v)
    a.max_cell_v[p, i] = _num(b.max_cell_v)
    a.soc[p, i] = _num(b.soc)
    a.full_capacity_ah[p, i] = _num(b.full_capacity_ah)
    a.remaining_capacity_ah[p, i] = _num(b.remaining_capacity_ah)
    a.sample_age_s[p, i] = _num(getattr(b, "sample_age_s", math.nan))
    a.cycle_count[p, i] = _num(getattr(b, "cycle_count", math.nan))
    g = b.group_voltages_v
    a.n_groups[p, i] = len(g)
    row = a.group_v[p, i]
    row.fill(math.nan)
    for k in range(min(len(g), row.shape[0])):
        row[k] = _num(g[k])
    sw = b.switch if isinstance(b.switch, SwitchState) else SwitchState(False, False)
    a.sw_chg[p, i] = bool(sw.chg_on)
    a.sw_dsg[p, i] = bool(sw.dsg_on)
    a.present[p, i] = bool(b.present)


def put_measurements(m: MeasArrays, p: int, meas: Measurements) -> None:
    """Write the scalar ``meas`` into pack ``p`` of ``m`` (batteries beyond ``meas`` unreported;
    extra ones ignored)."""
    m.t_s[p] = _num(meas.t_s)
    n = m.bat.voltage_v.shape[1]
    for i in range(n):
        _put_battery(m.bat, p, i, meas.batteries[i] if i < len(meas.batteries) else None)
    m.has_aux[p] = meas.aux is not None
    _put_battery(m.aux, p, 0, meas.aux)
    m.bus_v[p] = _num(meas.bus_v)
    m.load_current_a[p] = _num(meas.load_current_a)
    m.docked[p] = bool(meas.docked)
    c = meas.charger
    m.charger.reported[p] = c is not None
    if c is None:
        m.charger.output_v[p] = m.charger.output_a[p] = math.nan
        m.charger.flags[p] = False
        m.charger.online[p] = False
        return
    m.charger.output_v[p] = _num(c.output_v)
    m.charger.output_a[p] = _num(c.output_a)
    for k, name in enumerate(CHARGER_FLAGS):
        m.charger.flags[p, k] = bool(getattr(c, name))
    m.charger.online[p] = bool(c.online)


def battery_measurement(a: BatteryArrays, p: int, i: int) -> BatteryMeasurement:
    """Battery ``i`` of pack ``p`` as the scalar contract has it."""
    ng = int(a.n_groups[p, i])
    return BatteryMeasurement(
        voltage_v=float(a.voltage_v[p, i]),
        current_a=float(a.current_a[p, i]),
        temp_c=float(a.temp_c[p, i]),
        min_cell_v=float(a.min_cell_v[p, i]),
        max_cell_v=float(a.max_cell_v[p, i]),
        soc=float(a.soc[p, i]),
        full_capacity_ah=float(a.full_capacity_ah[p, i]),
        remaining_capacity_ah=float(a.remaining_capacity_ah[p, i]),
        group_voltages_v=tuple(float(x) for x in a.group_v[p, i, :ng]),
        switch=SwitchState(bool(a.sw_chg[p, i]), bool(a.sw_dsg[p, i])),
        min_temp_c=float(a.min_temp_c[p, i]),
        present=bool(a.present[p, i]),
        sample_age_s=float(a.sample_age_s[p, i]),
        cycle_count=float(a.cycle_count[p, i]),
    )


def measurements(m: MeasArrays, p: int) -> Measurements:
    """Pack ``p`` of ``m`` as the scalar contract has it (for logs, replay, debugging)."""
    n = m.bat.voltage_v.shape[1]
    c = m.charger
    charger = None
    if c.reported[p]:
        flags = {name: bool(c.flags[p, k]) for k, name in enumerate(CHARGER_FLAGS)}
        charger = ChargerStatus(
            output_v=float(c.output_v[p]),
            output_a=float(c.output_a[p]),
            online=bool(c.online[p]),
            **flags,
        )
    return Measurements(
        t_s=float(m.t_s[p]),
        batteries=tuple(battery_measurement(m.bat, p, i) for i in range(n) if m.bat.reported[p, i]),
        bus_v=float(m.bus_v[p]),
        load_current_a=float(m.load_current_a[p]),
        charger=charger,
        aux=battery_measurement(m.aux, p, 0) if m.has_aux[p] else None,
        docked=bool(m.docked[p]),
    )


def _opinion(x: int) -> bool | None:
    return None if x < 0 else bool(x)


def commands(cmd: CmdArrays, p: int, groups: tuple[int, ...]) -> Commands:
    """Pack ``p`` of ``cmd`` as scalar :class:`Commands` (``groups``: series groups of each
    traction battery, the length of its balancer row)."""
    n = cmd.chg_on.shape[1]
    charger = None
    if cmd.charger_set[p]:
        charger = ChargerCommand(
            voltage_v=float(cmd.charger_v[p]),
            current_a=float(cmd.charger_a[p]),
            enable=bool(cmd.charger_enable[p]),
        )
    balancer = None
    if cmd.balancer_set[p]:
        balancer = tuple(
            tuple(float(x) for x in cmd.balancer_a[p, i, : groups[i]]) for i in range(n)
        )
    return Commands(
        chg_on=tuple(_opinion(int(x)) for x in cmd.chg_on[p]),
        dsg_on=tuple(_opinion(int(x)) for x in cmd.dsg_on[p]),
        charger=charger,
        balancer_a=balancer,
        aux_relay_closed=_opinion(int(cmd.aux_relay[p])),
        aux_charge_a=float(cmd.aux_charge_a[p]) if cmd.aux_charge_set[p] else None,
    )


__all__ = [
    "NO_OPINION",
    "N_EVENT_VALUES",
    "BatteryArrays",
    "ChargerArrays",
    "CmdArrays",
    "EventBuf",
    "MeasArrays",
    "PackArrays",
    "battery_arrays",
    "battery_measurement",
    "clear_commands",
    "cmd_arrays",
    "commands",
    "event_buf",
    "meas_arrays",
    "measurements",
    "pack_arrays",
    "put_measurements",
]
