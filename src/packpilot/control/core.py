"""The BMS core: every enabled method and safety layer, merged, under the supervisor.

One :class:`Core` steps P packs: each part's compiled rules write their opinions into the
shared commands ("off wins", :mod:`packpilot.control.commands`), their events into the shared
buffer and their status channels into the shared status array; then the supervisor's rules
(mode machine, the mode's commands, the join limit) run on the merged result, and parts that
watch the final commands (plausibility compares switch feedback with them) see them. The
simulator loop, a campaign batch and a real-time runtime all call :meth:`Core.step_batch`.

:meth:`Core.step` is the one-pack face, ``step(Measurements, dt_s) -> ControlOutput``; at
P = 1 a part may also be a plain Python controller (a prototype, a test double): its
:class:`Commands` are merged by the same rules, its events join the stream in order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.arena import Arena
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.arrays import (
    CmdArrays,
    EventBuf,
    MeasArrays,
    PackArrays,
    clear_commands,
    cmd_arrays,
    commands,
    event_buf,
    meas_arrays,
    measurements,
    pack_arrays,
    put_measurements,
)
from packpilot.contract.bms import (
    Commands,
    Controller,
    ControlOutput,
    Event,
    Measurements,
    StatusValue,
)
from packpilot.contract.events import Labels, Source, render_one
from packpilot.contract.topology import PackInfo
from packpilot.control import commands as ck
from packpilot.control.core_kernel import (
    DIR_N_PARTS,
    DIR_PARTS,
    DIR_STRIDE,
    DIR_SUP_PRM,
    DIR_SUP_S0,
    DIR_SUP_ST,
    Fusion,
    Kind,
    StatusBuf,
    fused,
    kind_of,
)
from packpilot.control.method import CompiledController, Method, StatusChannel, status_values
from packpilot.control.supervisor import controller as sup_ctl
from packpilot.control.supervisor import rules as sr

F64 = NDArray[np.float64]


@dataclass
class Part:
    """One compiled method inside a core: its parameters, its state, its status slots."""

    method: Method
    prm: Any
    st: Any
    s0: int = 0
    owner: CompiledController | None = None
    """The one-pack controller whose state this is (it follows the state into the arena)."""
    config: Any = None
    """The validated config the state was built from (what a reboot builds it from again)."""

    @classmethod
    def of(cls, ctl: CompiledController) -> Part:
        """Share a one-pack controller's state (its accessors keep working)."""
        return cls(ctl.method, ctl.prm, ctl.st, owner=ctl, config=ctl.config)

    @classmethod
    def build(cls, method: Method, config: Any, infos: Sequence[PackInfo]) -> Part:
        if not isinstance(config, method.config):
            config = method.config.model_validate(config or {})
        prm, st = method.build(config, infos)
        return cls(method, prm, st, config=config)


def _reset_rows(state: Any, fresh: Any, mask: NDArray[np.bool_]) -> None:
    """Copy the packs in ``mask`` of a freshly built state into ``state`` (in place: the
    arrays are views into the core's arena). Per-pack arrays have the packs first."""
    for name in type(state)._fields:
        cur, new = getattr(state, name), getattr(fresh, name)
        if isinstance(cur, np.ndarray):
            if cur.ndim >= 1 and cur.shape[0] == mask.shape[0]:
                cur[mask] = new[mask]
        elif hasattr(cur, "_fields"):
            _reset_rows(cur, new, mask)


@dataclass
class Supervised:
    """The supervisor's parameters, state and status slots inside a core."""

    prm: sr.SupParams
    st: sr.SupState
    s0: int


def put_commands(cmd: CmdArrays, p: int, c: Commands) -> None:
    """Merge scalar ``Commands`` into pack ``p`` by the core's rules."""
    n = cmd.chg_on.shape[1]
    for i, on in enumerate(c.chg_on[:n]):
        if on is not None:
            ck.put_chg(cmd, p, i, bool(on))
    for i, on in enumerate(c.dsg_on[:n]):
        if on is not None:
            ck.put_dsg(cmd, p, i, bool(on))
    if c.charger is not None:
        ch = c.charger
        ck.put_charger(cmd, p, float(ch.voltage_v), float(ch.current_a), bool(ch.enable))
    if c.balancer_a is not None:
        ck.claim_balancer(cmd, p)
        g_max = cmd.balancer_a.shape[2]
        for i, row in enumerate(c.balancer_a[:n]):
            for g, a in enumerate(row[:g_max]):
                ck.put_balancer(cmd, p, i, g, float(a))
    if c.aux_relay_closed is not None:
        ck.put_aux_relay(cmd, p, bool(c.aux_relay_closed))
    if c.aux_charge_a is not None:
        ck.put_aux_charge(cmd, p, float(c.aux_charge_a))


class Core:
    """The supervised (or plainly composed) BMS of P packs of one topology.

    ``parts`` run in order (the methods as the scenario lists them, then the safety layers);
    ``supervisor`` (a config) puts them under the mode machine and the join limit.
    """

    def __init__(
        self,
        infos: Sequence[PackInfo],
        parts: Sequence[Part | Controller],
        supervisor: SupervisorConfig | None = None,
    ) -> None:
        self.infos = list(infos)
        info = self.infos[0]
        self.n_packs = len(self.infos)
        self.parts = list(parts)
        self.supervisor_config = supervisor
        if len(self.parts) >= sr.FOREIGN_SRC:
            raise ValueError(f"a core runs at most {sr.FOREIGN_SRC - 1} parts")
        if self.n_packs > 1 and not all(isinstance(x, Part) for x in self.parts):
            raise ValueError("Python controllers run at one pack only (P = 1)")
        n, g = info.n_batteries, max(info.groups_per_battery, default=1)
        self.tp: PackArrays = pack_arrays(self.infos)
        s0 = 0
        for x in self.compiled:
            x.s0 = s0
            s0 += len(x.method.status)
        self._link_reads()
        self.sources = [
            Source(x.method.reasons, x.method.labels(x.prm)) if isinstance(x, Part)
            else Source((), {})
            for x in self.parts
        ]  # fmt: skip
        self.supervisor: Supervised | None = None
        if supervisor is not None:
            prm, st = sup_ctl.build_supervisor(supervisor, self.infos, self._ev_class())
            self.supervisor = Supervised(prm, st, s0)
            s0 += len(sup_ctl.STATUS)
            self.sources.append(Source(sup_ctl.REASONS, sup_ctl.LABELS))
        self._kinds = [[r.kind for r in x.reasons] for x in self.sources]
        per_pack = sum(x.method.max_events(info) for x in self.compiled)
        per_pack += 0 if supervisor is None else sup_ctl.max_events(info)
        per_pack += 64 * (len(self.parts) - len(self.compiled))
        self._home(
            StatusBuf(np.full((self.n_packs, n, max(s0, 1)), np.nan)),
            event_buf(max(per_pack, 1) * self.n_packs),
            cmd_arrays(self.n_packs, n, g),
            meas_arrays(self.n_packs, n, g),
        )
        self._foreign: list[Event] = []
        self._foreign_status: dict[int, dict[str, list[StatusValue]]] = {}

    def _link_reads(self) -> None:
        """Tell each part that reads another part's status channels (``Method.reads``) where
        they are: their slots into its ``reads_slot`` parameter, -1 where none publishes it."""
        slots = {
            ch.name: x.s0 + j for x in self.compiled for j, ch in enumerate(x.method.status)
        }
        for x in self.compiled:
            for j, name in enumerate(x.method.reads):
                x.prm.reads_slot[j] = slots.get(name, -1)

    def _home(self, status: StatusBuf, ev: EventBuf, cmd: CmdArrays, m: MeasArrays) -> None:
        """Move every array of the core into one arena: Python keeps views, and a kernel gets
        the whole core as six arrays plus ``directory`` (see :mod:`packpilot.arena`)."""
        ar = Arena()
        fixed = [ar.add(x) for x in (self.tp, m, cmd, ev, status)]
        parts = [(ar.add(x.prm), ar.add(x.st)) for x in self.compiled]
        sup = self.supervisor
        sup_rows = (ar.add(sup.prm), ar.add(sup.st)) if sup is not None else None
        self.arenas, views, rows = ar.seal()
        self.tp, self.m, self.cmd, self.ev, status_v = views[: len(fixed)]
        self.status = status_v.values
        d = np.full(DIR_PARTS + DIR_STRIDE * len(self.parts), -1, np.int64)
        d[: len(fixed)] = rows[: len(fixed)]
        d[DIR_N_PARTS] = len(self.parts)
        kinds = self._kinds_of_parts()
        for x, (pr, sr_) in zip(self.compiled, parts, strict=True):
            x.prm, x.st = views[pr], views[sr_]
            if x.owner is not None:
                x.owner.prm, x.owner.st = x.prm, x.st
            j = self.parts.index(x)
            d[DIR_PARTS + DIR_STRIDE * j : DIR_PARTS + DIR_STRIDE * (j + 1)] = (
                -1 if kinds is None else kinds.index(self._kind(x)), rows[pr], rows[sr_], x.s0,
            )  # fmt: skip
        if sup is not None and sup_rows is not None:
            sup.prm, sup.st = views[sup_rows[0]], views[sup_rows[1]]
            d[DIR_SUP_PRM], d[DIR_SUP_ST] = rows[sup_rows[0]], rows[sup_rows[1]]
            d[DIR_SUP_S0] = sup.s0
        self.directory = d
        self.fused = kinds is not None
        """Every part is a compiled method: the core steps in one compiled call (else: part
        by part, from Python)."""
        self.fusion: Fusion | None = None
        self.step_kernel: Any = None
        """The fused step of exactly these parts (compiles only their rules), when fused."""
        if kinds is not None:
            self.fusion = Fusion(tuple(kinds), self.supervisor is not None)
            self.step_kernel = fused(self.fusion)

    @staticmethod
    def _kind(x: Part) -> Kind:
        m = x.method
        return kind_of(m.step_packs, type(x.prm), type(x.st), m.after)

    def _kinds_of_parts(self) -> list[Kind] | None:
        """The distinct methods of the parts, in order of first appearance (the fused step's
        method ids), or None when a part cannot be fused (a Python controller)."""
        kinds: list[Kind] = []
        for x in self.parts:
            if not isinstance(x, Part):
                return None
            kind = self._kind(x)
            if kind not in kinds:
                kinds.append(kind)
        return kinds

    @property
    def compiled(self) -> list[Part]:
        return [x for x in self.parts if isinstance(x, Part)]

    def _ev_class(self) -> NDArray[np.int64]:
        """(sources, codes) class bits of every part's reasons (what the supervisor reads)."""
        rows = [x.method.reasons if isinstance(x, Part) else () for x in self.parts]
        table = np.zeros((max(len(rows), 1), max((len(r) for r in rows), default=1) or 1), np.int64)
        for s, reasons in enumerate(rows):
            for c, r in enumerate(reasons):
                table[s, c] = sr.event_class(r.kind)
        return table

    def reboot(self, mask: NDArray[np.bool_]) -> None:
        """The packs in ``mask`` start afresh, as a BMU does when it powers up again after a
        brown-out (issue #24): every compiled method's and the supervisor's state of those
        packs is built anew from its config; the other packs are untouched. (Python
        controllers run at P = 1 and keep their state: they have no build to redo.)"""
        if not mask.any():
            return
        for x in self.compiled:
            if x.config is None:
                continue
            _, fresh = x.method.build(x.config, self.infos)
            _reset_rows(x.st, fresh, mask)
        sup = self.supervisor
        if sup is not None and self.supervisor_config is not None:
            _, fresh = sup_ctl.build_supervisor(
                self.supervisor_config, self.infos, self._ev_class()
            )
            _reset_rows(sup.st, fresh, mask)

    # ------------------------------------------------------------------ the step
    def step_batch(self, m: MeasArrays, dt_s: float, meas: Measurements | None = None) -> None:
        """One step of every pack: ``cmd``, ``ev`` and ``status`` hold the result.

        ``meas`` (P = 1 only) is what Python parts see; compiled parts read ``m``.
        """
        if self.fused:
            self.step_kernel(*self.arenas, self.directory, dt_s)
            return
        cmd, ev, tp, status = self.cmd, self.ev, self.tp, self.status
        clear_commands(cmd)
        ev.n[0] = 0
        if self._foreign:
            self._foreign.clear()
        if self._foreign_status:
            self._foreign_status.clear()
        for src, x in enumerate(self.parts):
            if isinstance(x, Part):
                x.method.step_packs(x.prm, x.st, tp, m, dt_s, cmd, ev, src, status, x.s0)
            else:
                self._run_python(x, src, m, meas, dt_s)
        sup = self.supervisor
        if sup is not None:
            sr.supervise_packs(sup.prm, sup.st, tp, m, dt_s, cmd, ev, 0, len(self.parts), status,
                               sup.s0)  # fmt: skip
        final: Commands | None = None
        for x in self.parts:
            if isinstance(x, Part):
                if x.method.after is not None:
                    x.method.after(x.prm, x.st, tp, m, cmd)
                continue
            note = getattr(x, "note_commands", None)
            if callable(note):  # a Python safety layer that watches the final commands
                final = final or commands(cmd, 0, self.infos[0].groups_per_battery)
                note(final)

    def _run_python(
        self, part: Controller, src: int, m: MeasArrays, meas: Measurements | None, dt_s: float
    ) -> None:
        out = part.step(measurements(m, 0) if meas is None else meas, dt_s)
        put_commands(self.cmd, 0, out.commands)
        for e in out.events:
            k = ck.emit(self.ev, 0, sr.FOREIGN_SRC, len(self._foreign), -1, m.t_s[0])
            self.ev.val[k, 0] = sr.event_class(e.kind)
            self.ev.battery[k] = -1 if e.battery is None else int(e.battery)
            self._foreign.append(e)
        self._foreign_status[src] = {k: list(v) for k, v in out.status.items()}

    def events(self) -> list[list[Event]]:
        """The last step's events, per pack, in order."""
        out: list[list[Event]] = [[] for _ in range(self.n_packs)]
        ev = self.ev
        for k in range(int(ev.n[0])):
            src = int(ev.src[k])
            if src == sr.FOREIGN_SRC:
                out[0].append(self._foreign[int(ev.code[k])])
                continue
            s = self.sources[src]
            reason = s.reasons[int(ev.code[k])]
            p = int(ev.pack[k])
            names = self.infos[p].names if p < len(self.infos) else ()
            out[p].append(
                render_one(reason, ev.t_s[k], int(ev.battery[k]), ev.val[k], s.labels, names)
            )
        return out

    def event_kinds(self) -> list[list[str]]:
        """The kinds of the last step's events, per pack, in order: what :meth:`events`
        would render, without formatting a message (the metrics count kinds every step)."""
        out: list[list[str]] = [[] for _ in range(self.n_packs)]
        ev, kinds = self.ev, self._kinds
        for k in range(int(ev.n[0])):
            src = int(ev.src[k])
            if src == sr.FOREIGN_SRC:
                out[0].append(self._foreign[int(ev.code[k])].kind)
            else:
                out[int(ev.pack[k])].append(kinds[src][int(ev.code[k])])
        return out

    def status_channels(self) -> list[tuple[int, StatusChannel, Labels]]:
        """(slot, channel, labels) of every compiled status channel, in output order."""
        out: list[tuple[int, StatusChannel, Labels]] = []
        for src, x in enumerate(self.parts):
            if isinstance(x, Part):
                labels = self.sources[src].labels
                out += [(x.s0 + j, ch, labels) for j, ch in enumerate(x.method.status)]
        if self.supervisor is not None:
            labels = self.sources[-1].labels
            out += [(self.supervisor.s0 + j, ch, labels) for j, ch in enumerate(sup_ctl.STATUS)]
        return out

    def python_status(self) -> dict[str, list[StatusValue]] | None:
        """The last step's status of the Python parts (``None`` when there are none)."""
        if self.fused:  # every part compiled: no Python status (asked every step)
            return None
        if len(self.compiled) == len(self.parts):
            return None
        out: dict[str, list[StatusValue]] = {}
        for src in range(len(self.parts)):
            out.update(self._foreign_status.get(src, {}))
        return out

    def status_of(self, p: int) -> dict[str, list[StatusValue]]:
        """Status channels of pack ``p`` as the scalar contract has them."""
        out: dict[str, list[StatusValue]] = {}
        for src, x in enumerate(self.parts):
            if isinstance(x, Part):
                labels = self.sources[src].labels
                out.update(status_values(self.status, p, x.s0, x.method.status, labels))
            elif p == 0:
                out.update(self._foreign_status.get(src, {}))
        sup = self.supervisor
        if sup is not None:
            labels = self.sources[-1].labels
            out.update(status_values(self.status, p, sup.s0, sup_ctl.STATUS, labels))
        return out

    # ------------------------------------------------------------------ one pack
    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        """The one-pack face: scalar measurements in, scalar output out."""
        put_measurements(self.m, 0, meas)
        self.step_batch(self.m, float(dt_s), meas)
        return ControlOutput(
            commands=commands(self.cmd, 0, self.infos[0].groups_per_battery),
            events=tuple(self.events()[0]),
            status=self.status_of(0),
        )


__all__ = ["Core", "Part", "Supervised", "put_commands"]
