"""The whole BMS step in one compiled call: every part, the supervisor, the after-hooks.

:meth:`packpilot.control.core.Core.step_batch` calls :func:`core_step` with the core's arena
(six arrays) and its directory; the kernel rebuilds every part's named tuples as views and runs
each enabled method's ``step_packs`` in the scenario's order, then the supervisor's rules, then
the parts that watch the final commands. Nothing is converted and nothing crosses between
Python and compiled code inside the step, which is what lets one pack step in microseconds.

Each method is one branch here, selected by its id in the directory (``METHOD_IDS``); the rules
themselves live in the method's own package. A core runs :func:`step_for` its own parts: the
branches of the methods it does not have are pruned before numba types them, so a scenario
compiles only the rules it runs (``core_step`` is the variant with every branch).
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.arena import unpack
from packpilot.contract.arrays import (
    CmdArrays,
    EventBuf,
    MeasArrays,
    PackArrays,
    clear_commands,
)
from packpilot.control.charging import rules as charging
from packpilot.control.equalization import rules as equalization
from packpilot.control.limits import rules as limits
from packpilot.control.plausibility import rules as plausibility
from packpilot.control.protection import rules as protection
from packpilot.control.sequencing import rules as sequencing
from packpilot.control.soc import rules as soc
from packpilot.control.supervisor import rules as sup
from packpilot.jit import kernel, kernel_inline

F64 = NDArray[np.float64]


class StatusBuf(NamedTuple):
    """The status channels of every part, (P, B, slots)."""

    values: F64


# Rows of a core's directory: where each bundle's layout starts, and per part its method.
DIR_TP, DIR_M, DIR_CMD, DIR_EV, DIR_STATUS = 0, 1, 2, 3, 4
DIR_N_PARTS, DIR_SUP_PRM, DIR_SUP_ST, DIR_SUP_S0 = 5, 6, 7, 8
DIR_PARTS, DIR_STRIDE = 16, 4
"""Part ``j``: ``directory[16 + 4 j:][:4]`` = (method id, params row, state row, status s0)."""
PROTECTION, SEQUENCING, CHARGING, EQUALIZATION, LIMITS, PLAUSIBILITY, SOC = range(7)
METHOD_IDS: dict[str, int] = {
    name: k
    for k, name in enumerate(
        ("protection", "sequencing", "charging", "equalization", "limits", "plausibility", "soc")
    )
}
COMPILED = frozenset(METHOD_IDS)
"""Methods this step has a branch for (a core with any other part steps part by part)."""


_clear = kernel_inline(clear_commands)
"""The contract's "no opinion anywhere", compiled into the step."""


def _fused(has: tuple[bool, ...]) -> Any:
    """The fused step of a core with these parts (``has``: a flag per method of ``_ORDER``,
    then the supervisor). Each ``has_*`` is a constant of the compiled function (a closure
    variable): numba prunes the branches of absent methods before typing them, so a scenario
    compiles only the rules it runs; every variant is cached on disk under its own key.
    Interpreted, the same function runs with the same flags."""
    has_prot, has_seq, has_chg, has_eq, has_lim, has_pl, has_soc, has_sup = has

    def core_step(f: Any, i: Any, h: Any, c: Any, b: Any, lay: Any, d: Any, dt_s: float) -> int:
        """One step of every pack of the core in the arena; returns the number of events."""
        tp = unpack(PackArrays, f, i, h, c, b, lay, d[DIR_TP])
        m = unpack(MeasArrays, f, i, h, c, b, lay, d[DIR_M])
        cmd = unpack(CmdArrays, f, i, h, c, b, lay, d[DIR_CMD])
        ev = unpack(EventBuf, f, i, h, c, b, lay, d[DIR_EV])
        status = unpack(StatusBuf, f, i, h, c, b, lay, d[DIR_STATUS]).values
        _clear(cmd)
        ev.n[0] = 0
        n_parts = d[DIR_N_PARTS]
        for j in range(n_parts):
            k = DIR_PARTS + DIR_STRIDE * j
            mid, pr, sr, s0 = d[k], d[k + 1], d[k + 2], d[k + 3]
            if has_prot and mid == PROTECTION:
                protection.step_packs(
                    unpack(protection.ProtectionParams, f, i, h, c, b, lay, pr),
                    unpack(protection.ProtectionState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_seq and mid == SEQUENCING:
                sequencing.step_packs(
                    unpack(sequencing.SequencingParams, f, i, h, c, b, lay, pr),
                    unpack(sequencing.SequencingState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_chg and mid == CHARGING:
                charging.step_packs(
                    unpack(charging.ChargingParams, f, i, h, c, b, lay, pr),
                    unpack(charging.ChargingState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_eq and mid == EQUALIZATION:
                equalization.step_packs(
                    unpack(equalization.EqParams, f, i, h, c, b, lay, pr),
                    unpack(equalization.EqState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_lim and mid == LIMITS:
                limits.step_packs(
                    unpack(limits.LimitsParams, f, i, h, c, b, lay, pr),
                    unpack(limits.LimitsState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_pl and mid == PLAUSIBILITY:
                plausibility.step_packs(
                    unpack(plausibility.PlausibilityParams, f, i, h, c, b, lay, pr),
                    unpack(plausibility.PlausibilityState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
            elif has_soc and mid == SOC:
                soc.step_packs(
                    unpack(soc.SocParams, f, i, h, c, b, lay, pr),
                    unpack(soc.SocState, f, i, h, c, b, lay, sr),
                    tp, m, dt_s, cmd, ev, j, status, s0,
                )  # fmt: skip
        if has_sup and d[DIR_SUP_PRM] >= 0:
            sup.supervise_packs(
                unpack(sup.SupParams, f, i, h, c, b, lay, d[DIR_SUP_PRM]),
                unpack(sup.SupState, f, i, h, c, b, lay, d[DIR_SUP_ST]),
                tp, m, dt_s, cmd, ev, 0, n_parts, status, d[DIR_SUP_S0],
            )  # fmt: skip
        for j in range(n_parts):
            k = DIR_PARTS + DIR_STRIDE * j
            # a charge FET never stays on without its discharge FET
            if has_seq and d[k] == SEQUENCING:
                sequencing.close_out_packs(
                    unpack(sequencing.SequencingParams, f, i, h, c, b, lay, d[k + 1]),
                    unpack(sequencing.SequencingState, f, i, h, c, b, lay, d[k + 2]),
                    tp, m, cmd,
                )  # fmt: skip
            # plausibility compares switch feedback with the final commands
            elif has_pl and d[k] == PLAUSIBILITY:
                plausibility.note_commands_packs(
                    unpack(plausibility.PlausibilityParams, f, i, h, c, b, lay, d[k + 1]),
                    unpack(plausibility.PlausibilityState, f, i, h, c, b, lay, d[k + 2]),
                    tp, m, cmd,
                )  # fmt: skip
        return int(ev.n[0])

    return kernel(core_step)


_ORDER = ("protection", "sequencing", "charging", "equalization", "limits", "plausibility", "soc")
assert tuple(METHOD_IDS) == _ORDER


@functools.cache
def step_for(methods: frozenset[str], supervised: bool) -> Any:
    """The fused step of a core whose compiled parts are ``methods`` (names of
    :data:`METHOD_IDS`), with the supervisor's rules when ``supervised``: it compiles (or
    loads from the cache) only those rules. One dispatcher per combination and process."""
    unknown = methods - COMPILED
    if unknown:
        raise ValueError(f"the fused step has no branch for {sorted(unknown)}")
    return _fused((*(name in methods for name in _ORDER), supervised))


core_step = step_for(COMPILED, True)
"""The fused step with every branch (a core of any composition can run it; compiling it
compiles every rule)."""


__all__ = ["COMPILED", "METHOD_IDS", "StatusBuf", "core_step", "step_for"]
