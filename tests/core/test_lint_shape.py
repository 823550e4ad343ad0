"""The complexity exemption names exactly the modules that define compiled kernels.

``pyproject.toml`` lets the kernels be long (C901, PLR0912, PLR0915 off for their modules). The
exemption is by file name, so it must not drift: a new kernel module is added to it, and a
module that no longer defines a kernel (or never did) leaves it and gets the limits back.
"""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
COMPLEXITY = {"C901", "PLR0912", "PLR0915"}
KERNEL_DECORATORS = {"kernel", "kernel_inline", "_jit", "_jit_inline"}
"""``packpilot.jit.kernel`` / ``kernel_inline`` and the local aliases some modules bind them to
(``_jit = kernel``; ``model/cell/kernels.py`` wraps ``numba.njit`` with the same options)."""


def _decorator_name(node: ast.expr) -> str:
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def _defines_kernel(path: Path) -> bool:
    """A module-level function decorated as a kernel, or a kernel made by calling the decorator
    (``arena``'s generated unpackers, ``kernel_inline(clear_commands)``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    decorated = any(
        isinstance(node, ast.FunctionDef)
        and any(_decorator_name(d) in KERNEL_DECORATORS for d in node.decorator_list)
        for node in tree.body
    )
    called = any(
        isinstance(node, ast.Call) and _decorator_name(node.func) in KERNEL_DECORATORS
        for node in ast.walk(tree)
    )
    return decorated or called


def test_complexity_exemptions_are_exactly_the_kernel_modules() -> None:
    lint = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["ruff"]
    ignores: dict[str, list[str]] = lint["lint"]["per-file-ignores"]
    exempt = {f for f, rules in ignores.items() if COMPLEXITY & set(rules)}
    assert all("*" not in f for f in exempt), "name the kernel modules one by one"
    kernels = {
        p.relative_to(ROOT).as_posix()
        for p in sorted((ROOT / "src").rglob("*.py"))
        if _defines_kernel(p)
    }
    assert kernels, "no kernel module found: has packpilot.jit.kernel been renamed?"
    assert sorted(exempt - kernels) == [], "exempt, but defines no kernel"
    assert sorted(kernels - exempt) == [], "defines a kernel, but is not exempt"
