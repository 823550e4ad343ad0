"""Many packs in lockstep: one vectorized plant step, batch sensors, a batch controller.

A campaign runs one scenario many times with drawn parameters. Per-pack closed loops spend
almost all their time in Python overhead (sensors, per-step samples, a controller written for
one pack), so they cannot reach thousands of one-hour missions on two cores. Here the packs of
a batch share one :class:`~packpilot.model.pack.Pack` with ``n_packs = P`` (per-pack capacity,
resistance, SOC and ambient from the draws), their sensors are a few array reductions, their
controller is the method's compiled rules stepping all packs at once, and the run metrics are
accumulated step by step instead of from a list of samples.

The contract is :func:`packpilot.sim.runner.compute_metrics`: for every pack, the metrics equal
those of a per-pack :class:`~packpilot.sim.runner.Runner` run with the same draw (summation
order aside; ``tests/test_lockstep.py``). Scenarios the lockstep loop does not cover (see
:func:`unsupported_reason`) run per pack; callers fall back to that path on any exception, so
one bad run never costs the others their result.
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig, validate_section
from packpilot.contract.arrays import (
    clear_commands,
    cmd_arrays,
    event_buf,
    meas_arrays,
    pack_arrays,
)
from packpilot.control.types import Commands
from packpilot.model.pack import Pack
from packpilot.sim.runner import apply_commands, build_controller, load_profile
from packpilot.sim.sensors import measure_all, pack_info, traction_indices

if TYPE_CHECKING:
    from packpilot.control.method import Method

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

BATCH_METHODS: frozenset[str] = frozenset({"sequencing"})
"""Methods run as one compiled call for all packs (their core rules, ``step_packs``). Other
methods run in lockstep too, as one scalar controller per pack fed from the batch sensors
(``controllers()``)."""


class StepHook(Protocol):
    """Called before every control step with the step's time (test knob for failures)."""

    def __call__(self, t_s: float) -> None: ...


def unsupported_reason(cfg: ScenarioConfig) -> str | None:
    """Why ``cfg`` cannot run in lockstep (``None``: it can).

    Covered: any methods without supervisor / safety layers, no charger (its link is a
    per-pack protocol), no fault schedule. Everything else runs per pack, with the same
    results, only slower.
    """
    if cfg.supervised:
        return "supervisor / safety layers run per pack"
    if cfg.charger.present:
        return "charger link runs per pack"
    if cfg.faults:
        return "fault schedules run per pack"
    return None


@dataclass
class _Metrics:
    """Running summaries of P packs: what ``compute_metrics`` derives from the samples."""

    n_packs: int
    n_strings: int
    steps: NDArray[np.int64] = field(init=False)
    energy_out: Array = field(init=False)
    energy_in: Array = field(init=False)
    min_cell_v: Array = field(init=False)
    max_cell_v: Array = field(init=False)
    max_temp_c: Array = field(init=False)
    final_soc: Array = field(init=False)
    peak_abs: Array = field(init=False)
    peak_val: Array = field(init=False)
    peak_cross: Array = field(init=False)
    unsupplied_steps: NDArray[np.int64] = field(init=False)
    events: list[Counter[str]] = field(init=False)

    def __post_init__(self) -> None:
        P, S = self.n_packs, self.n_strings
        self.steps = np.zeros(P, np.int64)
        self.energy_out = np.zeros(P)
        self.energy_in = np.zeros(P)
        self.min_cell_v = np.full(P, np.nan)
        self.max_cell_v = np.full(P, np.nan)
        self.max_temp_c = np.full(P, np.nan)
        self.final_soc = np.full((P, S), np.nan)
        self.peak_abs = np.full((P, S), -1.0)
        self.peak_val = np.zeros((P, S))
        self.peak_cross = np.zeros(P)
        self.unsupplied_steps = np.zeros(P, np.int64)
        self.events = [Counter() for _ in range(P)]


@dataclass
class LockstepResult:
    """Per-pack metrics (``compute_metrics`` layout) of one lockstep batch."""

    metrics: list[dict[str, Any]]
    wall_time_s: float


def controllers(cfg: ScenarioConfig) -> str:
    """How a lockstep batch runs ``cfg``'s methods: ``"twin"`` (a batch twin),
    ``"per-pack controllers"`` (one scalar controller per pack) or ``"none"``."""
    if not cfg.controller:
        return "none"
    if set(cfg.controller) <= BATCH_METHODS and len(cfg.controller) == 1:
        return "twin"
    return "per-pack controllers"


class _Compiled:
    """A compiled core method stepping every pack of the batch at once (``step_packs``)."""

    def __init__(self, method: Method, config: Any, pack: Pack) -> None:
        infos = [pack_info(pack, p) for p in range(pack.n_packs)]
        info = infos[0]
        P, n = pack.n_packs, info.n_batteries
        self.method = method
        self.prm, self.st = method.build(config, infos)
        self.tp = pack_arrays(infos)
        self.m = meas_arrays(P, n, 1)
        self.m.bat.reported.fill(True)
        self.cmd = cmd_arrays(P, n, 1)
        self.ev = event_buf(P * max(method.max_events(info), 1))
        self.status = np.full((P, n, max(len(method.status), 1)), np.nan)
        self.kinds = tuple(r.kind for r in method.reasons)

    def step(
        self, t: float, volts: Array, current: Array, present: BoolArray, docked: BoolArray,
        dt: float,
    ) -> None:  # fmt: skip
        m = self.m
        m.t_s.fill(t)
        m.bat.voltage_v[:] = volts
        m.bat.current_a[:] = current
        m.bat.present[:] = present
        m.docked[:] = docked
        clear_commands(self.cmd)
        self.ev.n[0] = 0
        self.method.step_packs(
            self.prm, self.st, self.tp, m, float(dt), self.cmd, self.ev, 0, self.status, 0
        )


def _twin(cfg: ScenarioConfig, pack: Pack) -> _Compiled:
    from packpilot.control.sequencing import METHOD

    seq_cfg = validate_section("sequencing", cfg.sequencing, "<config>")
    return _Compiled(METHOD, seq_cfg, pack)


def run_lockstep(
    cfg: ScenarioConfig,
    overrides: dict[str, Array],
    hook: StepHook | None = None,
) -> LockstepResult:
    """Run ``P`` packs of ``cfg`` in lockstep; ``overrides`` are ``Pack`` keyword arrays of
    shape (P,) (``capacity_scale``, ``r_scale``, ``soc_offset``, ``ambient_c``).

    Raises ``ValueError`` for a scenario :func:`unsupported_reason` rejects. Any exception
    inside the loop propagates: the caller reruns the batch per pack.
    """
    reason = unsupported_reason(cfg)
    if reason is not None:
        raise ValueError(f"scenario cannot run in lockstep: {reason}")
    sizes = {len(v) for v in overrides.values()}
    if len(sizes) != 1:
        raise ValueError(f"override arrays must share one length, got sizes {sorted(sizes)}")
    n_packs = sizes.pop()
    wall0 = time.perf_counter()
    pack = Pack(cfg, n_packs=n_packs, **overrides)
    P, S = pack.n_packs, pack.n_strings
    traction = traction_indices(pack)
    tr = np.array(traction, dtype=np.intp)
    how = controllers(cfg)
    twin = _twin(cfg, pack) if how == "twin" else None
    scalar = (
        [build_controller(cfg, pack_info(pack, p)) for p in range(P)]
        if how == "per-pack controllers"
        else []
    )
    profile = load_profile(cfg)
    dt = cfg.sim.dt_s
    n_steps = math.ceil(cfg.sim.duration_s / dt - 1e-9)
    stop_s = cfg.sim.stop_when_unsupplied_s
    starts = pack.string_cell_starts
    cap = pack.capacity_ah
    full = np.minimum.reduceat(cap, starts, axis=1)
    m = _Metrics(P, S)
    running = np.ones(P, bool)
    was_supplied = np.ones(P, bool)
    unsupplied_s = np.zeros(P)
    joule = np.zeros(P)
    chg_diode = np.zeros((P, S))
    dsg_diode = np.zeros((P, S))
    kinds = twin.kinds if twin is not None else ()

    def freeze(mask: BoolArray) -> None:
        """Snapshot the plant's ledgers of packs that stop now (the plant steps on)."""
        joule[mask] = pack.joule_j[mask].sum(axis=1)
        chg_diode[mask] = pack.chg_diode_j[mask]
        dsg_diode[mask] = pack.dsg_diode_j[mask]

    for _ in range(n_steps):
        if not running.any():
            break
        t = pack.t_s
        if hook is not None:
            hook(t)
        if twin is not None:
            cell_v = pack.cell_voltage_now()
            volts = np.add.reduceat(cell_v, starts, axis=1)[:, tr]
            current = pack.string_a[:, tr]
            present = pack.present()[:, tr]
            docked = pack.charger_connected(t)
            twin.step(t, volts, current, present, docked, dt)
            chg = pack.chg_on.copy()
            dsg = pack.dsg_on.copy()
            chg[:, tr] = twin.cmd.chg_on == 1
            dsg[:, tr] = twin.cmd.dsg_on == 1
            pack.set_gates(chg, dsg)
            ev = twin.ev
            n_ev = int(ev.n[0])
            for p, code in zip(ev.pack[:n_ev].tolist(), ev.code[:n_ev].tolist(), strict=True):
                if running[p]:
                    m.events[p][kinds[code]] += 1
        elif scalar:
            # Stopped packs are no longer controlled (their metrics are frozen anyway).
            live = np.nonzero(running)[0].tolist()
            meas = measure_all(pack, None, None if len(live) == P else live)
            cmds: list[Commands | None] = [None] * P
            for p, mp in zip(live, meas, strict=True):
                res = scalar[p].step(mp, dt)
                cmds[p] = res.commands
                for e in res.events:
                    m.events[p][e.kind] += 1
            apply_commands(pack, traction, cmds)
        value = profile.at(t - cfg.load.start_s) if t >= cfg.load.start_s else 0.0
        iv = pack.step(dt, profile.kind, np.full(P, value))
        supplied = iv.supplied
        run = running
        for p in np.nonzero(run & (supplied != was_supplied))[0].tolist():
            m.events[p]["LoadResupplied" if supplied[p] else "LoadUnsupplied"] += 1
        was_supplied = np.where(run, supplied, was_supplied)
        unsupplied_s = np.where(supplied, 0.0, unsupplied_s + dt)
        # Metrics of the step just taken (compute_metrics' definitions, per pack).
        m.steps += run
        m.energy_out += np.where(run, iv.bus_v * iv.load_a, 0.0)
        m.energy_in += np.where(run, iv.charger_v * iv.charger_a, 0.0)
        cv = iv.cell_v
        # nanmin / nanmax over the strings, as compute_metrics (fmin/fmax skip NaN).
        lo = np.fmin.reduce(np.minimum.reduceat(cv, starts, axis=1), axis=1)
        hi = np.fmax.reduce(np.maximum.reduceat(cv, starts, axis=1), axis=1)
        m.min_cell_v = np.where(run, np.fmin(m.min_cell_v, lo), m.min_cell_v)
        m.max_cell_v = np.where(run, np.fmax(m.max_cell_v, hi), m.max_cell_v)
        soc, temp = pack.cell_states()
        tmax = np.fmax.reduce(np.maximum.reduceat(temp, starts, axis=1), axis=1)
        m.max_temp_c = np.where(run, np.fmax(m.max_temp_c, tmax), m.max_temp_c)
        rem = np.minimum.reduceat(soc * cap, starts, axis=1)
        m.final_soc = np.where(run[:, None], rem / full, m.final_soc)
        cur = iv.string_a
        # argmax semantics: the first NaN is the peak and stays it (NaN peak_abs never updates).
        a = np.abs(cur)
        bigger = run[:, None] & ~np.isnan(m.peak_abs) & ((a > m.peak_abs) | np.isnan(a))
        m.peak_abs = np.where(bigger, a, m.peak_abs)
        m.peak_val = np.where(bigger, cur, m.peak_val)
        supplying = run & (iv.load_a > 1e-3) & (iv.charger_a < 1e-3)
        into = np.max(np.maximum(-cur[:, tr], 0.0), axis=1, initial=0.0)
        m.peak_cross = np.where(supplying, np.maximum(m.peak_cross, into), m.peak_cross)
        demand = iv.load_demand_a
        short = (demand > 1e-9) & (iv.load_a < demand - 1e-6)
        m.unsupplied_steps += run & short
        if stop_s is not None:
            stopping = run & (unsupplied_s >= stop_s)
            if stopping.any():
                freeze(stopping)
                running = running & ~stopping
    freeze(running)
    wall = time.perf_counter() - wall0
    names = list(pack.names)
    metrics = []
    for p in range(P):
        n = int(m.steps[p])
        metrics.append(
            {
                "sim_time_s": float(n * dt),
                "wall_time_s": wall / P,
                "steps": n,
                "energy_out_wh": float(m.energy_out[p] * dt / 3600.0),
                "energy_in_wh": float(m.energy_in[p] * dt / 3600.0),
                "min_cell_v": float(m.min_cell_v[p]),
                "max_cell_v": float(m.max_cell_v[p]),
                "max_temp_c": float(m.max_temp_c[p]),
                "final_soc": [float(x) for x in m.final_soc[p]],
                "peak_string_current_a": [float(x) for x in m.peak_val[p]],
                "peak_cross_current_a": float(m.peak_cross[p]),
                "joule_heat_j": float(joule[p]),
                "load_unsupplied_s": float(m.unsupplied_steps[p] * dt),
                "chg_diode_energy_j": [float(x) for x in chg_diode[p]],
                "dsg_diode_energy_j": [float(x) for x in dsg_diode[p]],
                "events": dict(m.events[p]),
                "battery_names": names,
            }
        )
    return LockstepResult(metrics, wall)


def stack_overrides(draws: Sequence[dict[str, Array]]) -> dict[str, Array]:
    """Per-run ``Pack`` overrides (arrays of length 1) -> one dict of (P,) arrays."""
    keys = list(draws[0])
    return {
        k: np.concatenate([np.asarray(d[k], np.float64).reshape(1) for d in draws]) for k in keys
    }


__all__ = [
    "BATCH_METHODS",
    "LockstepResult",
    "controllers",
    "run_lockstep",
    "stack_overrides",
    "unsupported_reason",
]
