"""The whole BMS step in one compiled call: every part, the supervisor, the after-hooks.

:meth:`packpilot.control.core.Core.step_batch` calls the core's fused step with its arena (six
arrays) and its directory; the kernel rebuilds every part's named tuples as views and runs
each part's ``step_packs`` in the scenario's order, then the supervisor's rules, then the
parts that watch the final commands (``Method.after``). Nothing is converted and nothing
crosses between Python and compiled code inside the step, which is what lets one pack step in
microseconds.

**Generated from the parts, not written per method.** numba cannot loop over a list of
different functions, so a fused step needs one branch per method written out. Rather than a
hand-written branch per registered method (which every new method had to edit), :func:`fused`
writes the source of the step for exactly the methods a core has (their ``step_packs``,
``after`` and named-tuple classes, found through their modules), in a file named by the digest
of that source, and imports it. A file, because numba caches compiled code on disk only for
functions of a real source file; its name is the digest, so the same composition finds its
compiled step again in the next process, and its cache stamp (``packpilot.jit``) covers every
module it imports, so an edit of a rule recompiles it. A scenario therefore compiles only the
rules it runs, and a method defined anywhere (a test, a plugin) fuses like a shipped one.
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from packpilot.contract.arrays import clear_commands
from packpilot.jit import add_root, dependency_stamp, kernel_inline

F64 = NDArray[np.float64]


class StatusBuf(NamedTuple):
    """The status channels of every part, (P, B, slots)."""

    values: F64


# Rows of a core's directory: where each bundle's layout starts, and per part its method.
DIR_TP, DIR_M, DIR_CMD, DIR_EV, DIR_STATUS = 0, 1, 2, 3, 4
DIR_N_PARTS, DIR_SUP_PRM, DIR_SUP_ST, DIR_SUP_S0 = 5, 6, 7, 8
DIR_PARTS, DIR_STRIDE = 16, 4
"""Part ``j``: ``directory[16 + 4 j:][:4]`` = (method id, params row, state row, status s0);
the method id is the method's index in the core's :class:`Fusion` (its distinct methods)."""


_clear = kernel_inline(clear_commands)
"""The contract's "no opinion anywhere", compiled into the step."""


class Kind(NamedTuple):
    """What the fused step needs of one method: where its compiled functions and its named
    tuples live (``module:qualname``), so the generated source can import them."""

    step_packs: str
    params: str
    state: str
    after: str | None


class Fusion(NamedTuple):
    """A composition of a fused step: its distinct methods in order, and the supervisor."""

    kinds: tuple[Kind, ...]
    supervised: bool


def _where(obj: Any) -> str:
    """``module:qualname`` of a function (a numba dispatcher: of its Python function) or a
    class, refusing what an import cannot find again (a function defined inside another)."""
    fn = getattr(obj, "py_func", obj)
    where = f"{fn.__module__}:{fn.__qualname__}"
    if "<" in where or fn.__module__ == "__main__":
        raise ValueError(f"{where}: a fused method's functions and tuples must be module-level")
    return where


def kind_of(step_packs: Any, params: Any, state: Any, after: Any | None) -> Kind:
    """The :class:`Kind` of a method from its functions and its parameter/state classes."""
    return Kind(
        _where(step_packs),
        _where(params),
        _where(state),
        None if after is None else _where(after),
    )


def _imports(kinds: Sequence[Kind]) -> list[str]:
    lines = []
    for k, kind in enumerate(kinds):
        for alias, ref in (("step", kind.step_packs), ("P", kind.params), ("S", kind.state)):
            mod, name = ref.split(":")
            lines.append(f"from {mod} import {name} as {alias}{k}")
        if kind.after is not None:
            mod, name = kind.after.split(":")
            lines.append(f"from {mod} import {name} as after{k}")
    return lines


_ARGS = "f, i, h, c, b, lay"


def source(fusion: Fusion) -> str:
    """The Python source of the fused step of ``fusion`` (one branch per distinct method)."""
    kinds = fusion.kinds
    steps: list[str] = []
    afters: list[str] = []
    for k, kind in enumerate(kinds):
        word = "if" if not steps else "elif"
        steps += [
            f"            {word} mid == {k}:",
            f"                step{k}(unpack(P{k}, {_ARGS}, pr), unpack(S{k}, {_ARGS}, sr),",
            "                       tp, m, dt_s, cmd, ev, j, status, s0)",
        ]
        if kind.after is not None:
            word = "if" if not afters else "elif"
            afters += [
                f"            {word} mid == {k}:",
                f"                after{k}(unpack(P{k}, {_ARGS}, pr), unpack(S{k}, {_ARGS}, sr),",
                "                         tp, m, cmd)",
            ]
    sup = [
        "        if d[DIR_SUP_PRM] >= 0:",
        "            sup.supervise_packs(",
        f"                unpack(sup.SupParams, {_ARGS}, d[DIR_SUP_PRM]),",
        f"                unpack(sup.SupState, {_ARGS}, d[DIR_SUP_ST]),",
        "                tp, m, dt_s, cmd, ev, 0, n_parts, status, d[DIR_SUP_S0])",
    ]
    loop = [
        "        for j in range(n_parts):",
        "            k = DIR_PARTS + DIR_STRIDE * j",
        "            mid, pr, sr, s0 = d[k], d[k + 1], d[k + 2], d[k + 3]",
    ]
    lines = [
        '"""Generated by packpilot.control.core_kernel (do not edit): the fused step of',
        *(f"{k.step_packs}" for k in kinds),
        f'supervised: {fusion.supervised}."""',
        "# ruff: noqa",
        "from packpilot.arena import unpack",
        "from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays",
        "from packpilot.control.core_kernel import (",
        "    DIR_CMD, DIR_EV, DIR_M, DIR_N_PARTS, DIR_PARTS, DIR_STATUS, DIR_STRIDE,",
        "    DIR_SUP_PRM, DIR_SUP_S0, DIR_SUP_ST, DIR_TP, StatusBuf, _clear,",
        ")",
        *(["from packpilot.control.supervisor import rules as sup"] if fusion.supervised else []),
        "from packpilot.jit import kernel",
        *_imports(kinds),
        "",
        "",
        "@kernel",
        "def core_step(f, i, h, c, b, lay, d, dt_s):",
        "        tp = unpack(PackArrays, f, i, h, c, b, lay, d[DIR_TP])",
        "        m = unpack(MeasArrays, f, i, h, c, b, lay, d[DIR_M])",
        "        cmd = unpack(CmdArrays, f, i, h, c, b, lay, d[DIR_CMD])",
        "        ev = unpack(EventBuf, f, i, h, c, b, lay, d[DIR_EV])",
        "        status = unpack(StatusBuf, f, i, h, c, b, lay, d[DIR_STATUS]).values",
        "        _clear(cmd)",
        "        ev.n[0] = 0",
        "        n_parts = d[DIR_N_PARTS]",
        *(loop + steps if steps else []),
        *(sup if fusion.supervised else []),
        *(loop + afters if afters else []),
        "        return int(ev.n[0])",
        "",
    ]
    return "\n".join(lines)


def _directory() -> Path:
    """Where generated steps are written: ``$PACKPILOT_FUSED_DIR``, else beside numba's cache
    (``$NUMBA_CACHE_DIR``), else the user's cache directory."""
    env = os.environ.get("PACKPILOT_FUSED_DIR")
    if env:
        return Path(env)
    numba_dir = os.environ.get("NUMBA_CACHE_DIR")
    if numba_dir:
        return Path(numba_dir) / "packpilot-fused"
    xdg = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(xdg) / "packpilot" / "fused"


def _module_stamps(fusion: Fusion) -> list[str]:
    """Digests of the modules a generated step imports (and of theirs, within the package
    families :mod:`packpilot.jit` knows): part of the file's name, so a step of another
    source tree, or of an edited method outside those families, is another file."""
    mods = {"packpilot.control.core_kernel"}
    for kind in fusion.kinds:
        mods.update(ref.split(":")[0] for ref in kind if ref is not None)
    out = []
    for mod in sorted(mods):
        spec = importlib.util.find_spec(mod)
        origin = None if spec is None else spec.origin
        out.append(f"{mod}={origin}:" + (dependency_stamp(Path(origin)) if origin else ""))
    return out


@functools.cache
def fused(fusion: Fusion) -> Any:
    """The compiled fused step of ``fusion`` (one dispatcher per composition and process):
    its source written once to a file named by its digest, imported, compiled on first call
    or loaded from numba's cache."""
    text = source(fusion)
    digest = hashlib.sha256("\n".join([text, *_module_stamps(fusion)]).encode()).hexdigest()
    name = f"fused_{digest[:20]}"
    directory = _directory()
    add_root("packpilot-fused", directory)  # its cache stamp covers what the file imports
    path = directory / f"{name}.py"
    if not path.exists() or path.read_text() != text:
        directory.mkdir(parents=True, exist_ok=True)
        tmp = directory / f".{name}.{os.getpid()}.tmp"
        tmp.write_text(text)
        os.replace(tmp, path)  # atomic: a concurrent process reads a whole file
    # A module of this package by name (its kernel is compiled as the core's are, without
    # numba's reference counting, packpilot.jit), from a file outside it.
    qualified = f"{__package__}.{name}"
    spec = importlib.util.spec_from_file_location(qualified, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[qualified] = module
    spec.loader.exec_module(module)
    return module.core_step


__all__ = ["Fusion", "Kind", "StatusBuf", "fused", "kind_of", "source"]
