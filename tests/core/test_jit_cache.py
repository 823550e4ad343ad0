"""The kernel cache is keyed by everything a kernel imports, not only by its own file.

Reproduces the stale-kernel defect: a cached kernel that reads a constant (and calls a
compiled function) from another module kept the old machine code after that module changed.
Each run is a fresh process, as a second ``packpilot`` process would be.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

SCRIPT = """
import sys
sys.path.insert(0, {tmp!r})
import packpilot.jit as jit
if {register}:
    jit.add_root("kdemo", {pkg!r})
import kdemo.rules as r
print(r.step(1.0))
"""


def _write_pkg(tmp: Path, eps: str, gain: str) -> Path:
    pkg = tmp / "kdemo"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "consts.py").write_text(f"EPS = {eps}\n")
    (pkg / "helpers.py").write_text(
        textwrap.dedent(
            f"""
            import numba

            @numba.njit(cache=True)
            def gain(x):
                return x * {gain}
            """
        )
    )
    (pkg / "rules.py").write_text(
        textwrap.dedent(
            """
            import numba
            from kdemo.consts import EPS
            from kdemo.helpers import gain

            @numba.njit(cache=True)
            def step(x):
                return gain(x) + EPS
            """
        )
    )
    return pkg


def _run(tmp: Path, pkg: Path, register: bool) -> float:
    code = SCRIPT.format(tmp=str(tmp), pkg=str(pkg), register=register)
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    )
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("register", [True, False])
def test_editing_an_imported_module_recompiles_the_cached_kernel(
    tmp_path: Path, register: bool
) -> None:
    pkg = _write_pkg(tmp_path, eps="0.5", gain="2.0")
    assert _run(tmp_path, pkg, register) == 2.5
    assert _run(tmp_path, pkg, register) == 2.5  # served from the cache
    _write_pkg(tmp_path, eps="0.25", gain="2.0")  # a constant in another module
    first = _run(tmp_path, pkg, register)
    _write_pkg(tmp_path, eps="0.25", gain="3.0")  # a compiled callee in another module
    second = _run(tmp_path, pkg, register)
    if register:
        assert (first, second) == (2.25, 3.25)
    else:  # numba's own locator: the defect this module exists to prevent
        assert (first, second) == (2.5, 2.5)


def test_core_kernels_run_without_the_numba_runtime() -> None:
    """The core's kernels are compiled with ``_nrt`` off (no reference counting on arena
    views, docs/kernels.md); the plant's, which allocate, keep it."""
    from packpilot.contract.bms import SwitchKind
    from packpilot.contract.topology import PackInfo
    from packpilot.control.core import Core, Part
    from packpilot.control.sequencing import METHOD as SEQUENCING
    from packpilot.control.sequencing import rules as seq
    from packpilot.model import pack_kernel

    info = PackInfo(2, (1, 1), (1, 1), (SwitchKind.MOSFET_PAIR,) * 2)
    core = Core([info], [Part.build(SEQUENCING, None, [info])])
    for dispatcher in (core.step_kernel, seq.step_packs, seq.step_pack):
        assert dispatcher.targetoptions.get("_nrt") is False, dispatcher
    assert "_nrt" not in pack_kernel.segment_sums.targetoptions
