"""Compiled kernels: one decorator, and an on-disk cache that knows what a kernel imports.

Every rule of the BMS core and every plant kernel is a plain Python function compiled by
numba (``@kernel``): ``cache=True`` (a second process starts in about a second instead of
compiling), ``nogil`` (Dask threads), ``error_model="numpy"`` (a division by zero gives
inf/NaN as NumPy does, no exception in a control loop) and **no fastmath** (IEEE operations
only: results do not depend on the compiler's mood, and are the same under
``NUMBA_DISABLE_JIT=1``, where the same source runs as plain Python).

Why a cache locator of our own: numba keys a cached kernel by the source of the *file that
defines it*, yet the machine code it stores embeds every compiled function it calls and every
module constant it reads. Editing a constant in ``control/sequencing/rules.py`` would leave a
cached caller in another file on the old value (this happened: 139 of 200 steps differed).
:class:`_DepsStamp` makes the stamp the digest of the defining file *and of every module of the
same package it imports, transitively*, so any edit that can change a kernel's code recompiles
it. Functions of other packages keep numba's own locators.
"""

from __future__ import annotations

import ast
import functools
import hashlib
import importlib.util
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar, cast

import numba
from numba.core import caching

_F = TypeVar("_F", bound=Callable[..., Any])

_ROOTS: dict[str, Path] = {"packpilot": Path(__file__).resolve().parent}
"""Package name -> directory whose modules get dependency-aware cache stamps."""


def add_root(package: str, directory: str | os.PathLike[str]) -> None:
    """Give the modules of another package dependency-aware stamps (tests use this)."""
    _ROOTS[package] = Path(directory).resolve()


def _root_of(path: Path) -> str | None:
    for name, root in _ROOTS.items():
        if path.is_relative_to(root):
            return name
    return None


def _module_file(name: str) -> Path | None:
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or spec.origin is None or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin).resolve()


@functools.cache
def _direct_imports(path: Path, mtime_ns: int, size: int) -> tuple[Path, ...]:
    """Files of the same package family that ``path`` imports (``import`` / ``from``)."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    out: set[Path] = set()
    for name in names:
        if name.split(".")[0] not in _ROOTS:
            continue
        f = _module_file(name)
        if f is not None and f != path:
            out.add(f)
    return tuple(sorted(out))


def dependency_files(path: Path) -> list[Path]:
    """``path`` and every file of its package family it imports, transitively, sorted."""
    seen: set[Path] = set()
    todo = [path.resolve()]
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        st = f.stat()
        todo.extend(_direct_imports(f, st.st_mtime_ns, st.st_size))
    return sorted(seen)


def dependency_stamp(path: Path) -> str:
    """Digest of ``path`` and everything it imports from its package family."""
    h = hashlib.sha256()
    for f in dependency_files(path):
        h.update(str(f).encode())
        h.update(f.read_bytes())
    return h.hexdigest()


class _DepsStamp:
    """Mixin for numba's file-backed locators: the stamp covers the file's imports."""

    _py_file: str

    def get_source_stamp(self) -> str:
        return dependency_stamp(Path(self._py_file))

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> Any:
        if _root_of(Path(py_file).resolve()) is None:
            return None
        return super().from_function(py_func, py_file)  # type: ignore[misc]


class _UserDirLocator(_DepsStamp, caching.UserProvidedCacheLocator):
    pass


class _InTreeLocator(_DepsStamp, caching.InTreeCacheLocator):
    pass


class _UserWideLocator(_DepsStamp, caching.UserWideCacheLocator):
    pass


_OURS = [_UserDirLocator, _InTreeLocator, _UserWideLocator]
_impl_locators: list[Any] = caching.CacheImpl._locator_classes
if _impl_locators[0] is not _UserDirLocator:
    _impl_locators[:0] = _OURS


_NO_NRT = ("packpilot.control.", "packpilot.contract.")
"""Modules whose kernels run without numba's reference counting (see :func:`_options`)."""


def _options(fn: Callable[..., Any]) -> dict[str, Any]:
    """The project's numba options for ``fn``.

    The BMS core's kernels (``control``, ``contract``) work only on arena views, which own no
    memory and allocate nothing, so they are compiled without numba's runtime (``_nrt``
    off): numba then emits no reference-count call for an array. With it on, every array a
    rule reads through a named tuple cost a call to ``NRT_incref``/``NRT_decref`` (a null
    check on a view, but thousands per pack-step: ~15 % of the core's time at P = 256).
    A core kernel that allocates fails to compile, which is the check that it does not."""
    opts: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}
    if fn.__module__.startswith(_NO_NRT):
        opts["_nrt"] = False
    return opts


def kernel(fn: _F) -> _F:
    """Compile ``fn`` with the project's options, keeping its Python signature for mypy."""
    return cast(_F, numba.njit(**_options(fn))(fn))


def kernel_inline(fn: _F) -> _F:
    """:func:`kernel`, inlined into its callers at numba IR level (helpers of a rule)."""
    return cast(_F, numba.njit(inline="always", **_options(fn))(fn))


__all__ = ["add_root", "dependency_files", "dependency_stamp", "kernel"]
