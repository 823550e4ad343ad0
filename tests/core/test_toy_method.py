"""A method defined here, outside the package, fuses into the core like a shipped one.

This is the walkthrough of docs/architecture.md ("Adding a method"), kept true: a toy method
with its own config model, parameters, state, rule kernel, reason table (one event), status
channel and a command (it opens a battery's discharge path), built into a :class:`Core`
beside a shipped method, under the supervisor, and run in the simulator's closed loop. Nothing
in ``packpilot`` lists it: the fused step is generated from the core's parts.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from packpilot.config import load_config
from packpilot.config.base import Strict
from packpilot.config.supervisor import SupervisorConfig
from packpilot.contract.arrays import CmdArrays, EventBuf, MeasArrays, PackArrays
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.commands import emit, put_dsg
from packpilot.control.core import Core, Part
from packpilot.control.core_kernel import source
from packpilot.control.method import Method, StatusChannel
from packpilot.control.soc import METHOD as SOC
from packpilot.jit import kernel
from packpilot.sim.loop import ClosedLoop
from packpilot.sim.plant_io import SimulatedPlant

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


# 1. The config model: the method's [toy] section.
class ToyConfig(Strict):
    """Open a battery's discharge path once its measured voltage falls below ``cut_v``."""

    cut_v: float = Field(20.0, gt=0, le=1000)


# 2. Parameters and state: named tuples of numbers and arrays (state shaped (P, B)).
class ToyParams(NamedTuple):
    cut_v: float


class ToyState(NamedTuple):
    tripped: I64
    """(P, B): 1 once the battery was cut."""


TOY_CUT = 0  # reason code: row 0 of REASONS
ST_SEEN_V = 0  # status channel 0 of STATUS


# 3. The rule: a kernel over every pack, writing commands, events and status.
@kernel
def toy_step_packs(
    prm: ToyParams, st: ToyState, tp: PackArrays, m: MeasArrays, dt_s: float, cmd: CmdArrays,
    ev: EventBuf, src: int, status: F64, s0: int,
) -> None:  # fmt: skip
    code = TOY_CUT  # an int64 local, not a literal: emit compiles once (docs/kernels.md)
    for p in range(m.bat.voltage_v.shape[0]):
        for i in range(m.bat.voltage_v.shape[1]):
            v = m.bat.voltage_v[p, i]
            status[p, i, s0 + ST_SEEN_V] = v
            if st.tripped[p, i] == 0 and v < prm.cut_v:
                st.tripped[p, i] = 1
                k = emit(ev, p, src, code, i, m.t_s[p])
                ev.val[k, 0] = v
                ev.val[k, 1] = prm.cut_v
            if st.tripped[p, i] != 0:
                put_dsg(cmd, p, i, False)


# 4. build, the reason table, the status channels and the Method the core runs.
def build(config: ToyConfig, infos: Sequence[PackInfo]) -> tuple[ToyParams, ToyState]:
    n = infos[0].n_batteries
    return ToyParams(float(config.cut_v)), ToyState(np.zeros((len(infos), n), np.int64))


REASONS = (Reason("ToyCut", "cut at {v:.2f} V (below {cut_v:g} V)", fields("v", "cut_v")),)
STATUS = (StatusChannel("toy_seen_v"),)


def _labels(prm: ToyParams) -> Labels:
    return {}


TOY = Method(
    name="toy",
    src=0,
    config=ToyConfig,
    build=build,
    step_packs=toy_step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=_labels,
    max_events=lambda info: info.n_batteries,
)


def test_a_method_defined_in_a_test_runs_fused_in_the_closed_loop() -> None:
    cfg = load_config(EXAMPLES / "smart_battery.toml")  # one 6S battery, ~24 V full
    plant = SimulatedPlant(cfg)
    infos = plant.infos
    toy = Part.build(TOY, ToyConfig(cut_v=30.0), infos)  # above the battery: cuts at once
    core = Core(infos, [toy, Part.build(SOC, None, infos)], SupervisorConfig())
    assert core.fused and core.fusion is not None
    text = source(core.fusion)
    assert f"from {__name__} import toy_step_packs as step0" in text
    assert "packpilot.control.soc.rules import step_packs as step1" in text
    loop = ClosedLoop.of(cfg, core=core, plant=plant)
    dt = cfg.sim.dt_s
    events = []
    try:
        for k in range(10):
            rec = loop.step(k, dt)
            events += rec.events[0]
            seen = core.status_of(0)["toy_seen_v"][0]
            assert seen == float(core.m.bat.voltage_v[0, 0])
        toy_events = [e for e in events if e.kind == "ToyCut"]
        assert len(toy_events) == 1  # latched: once
        e = toy_events[0]
        assert e.battery == 0 and e.data["cut_v"] == 30.0 and 20.0 < e.data["v"] < 30.0
        assert e.message.startswith("cut at ") and e.t_s == 0.0
        assert not bool(core.cmd.dsg_on[0, 0])  # the command, merged ("off wins")
        assert not bool(plant.pack.dsg_on[0, 0])  # ... and applied to the plant
        assert math.isfinite(core.status_of(0)["soc_est"][0] or math.nan)
        compiled = getattr(core.step_kernel, "signatures", None)  # None: NUMBA_DISABLE_JIT
        assert compiled is None or len(compiled) == 1  # the generated step ran compiled
    finally:
        loop.close()


def test_the_toy_does_nothing_above_its_cut() -> None:
    """The same core with the cut below the battery: no event, the path stays as it was."""
    cfg = load_config(EXAMPLES / "smart_battery.toml")
    plant = SimulatedPlant(cfg)
    core = Core(plant.infos, [Part.build(TOY, ToyConfig(cut_v=5.0), plant.infos)])
    loop = ClosedLoop.of(cfg, core=core, plant=plant)
    try:
        kinds = [e.kind for k in range(5) for e in loop.step(k, cfg.sim.dt_s).events[0]]
        assert "ToyCut" not in kinds
        assert bool(plant.pack.dsg_on[0, 0])
    finally:
        loop.close()


_SECOND_PROCESS = """
import json, sys
from packpilot.contract.bms import SwitchKind
from packpilot.contract.topology import PackInfo
from packpilot.control.core import Core, Part
from packpilot.control.soc import METHOD as SOC
from tests.core.test_toy_method import TOY, ToyConfig
info = PackInfo(1, (2,), (3,), (SwitchKind.MOSFET_PAIR,), capacity_ah=(5.0,),
                ocv_soc=(0.0, 1.0), ocv_v=(3.0, 4.2))
core = Core([info], [Part.build(TOY, ToyConfig(), [info]), Part.build(SOC, None, [info])])
core.step_batch(core.m, 0.1)
k = core.step_kernel
print(json.dumps({"file": k.py_func.__code__.co_filename, "hits": sum(k.stats.cache_hits.values()),
                  "misses": sum(k.stats.cache_misses.values())}))
"""


def test_the_generated_step_is_compiled_once_and_loaded_from_the_cache(tmp_path: Path) -> None:
    """The fused step of a composition is a file named by its digest: a second process finds
    the same file and loads the compiled step from numba's cache instead of compiling it."""
    import json
    import os
    import subprocess
    import sys

    if os.environ.get("NUMBA_DISABLE_JIT") == "1":
        return  # nothing is compiled, nothing cached
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PACKPILOT_FUSED_DIR=str(tmp_path),
               PYTHONPATH=os.pathsep.join([str(root / "src"), str(root)]))  # fmt: skip
    runs = []
    for _ in range(2):
        out = subprocess.run(
            [sys.executable, "-c", _SECOND_PROCESS], env=env, cwd=root, capture_output=True,
            text=True, timeout=1200, check=True,
        ).stdout  # fmt: skip
        runs.append(json.loads(out.strip().splitlines()[-1]))
    first, second = runs
    assert first["file"] == second["file"] and Path(first["file"]).parent == tmp_path
    assert first["misses"] == 1 and first["hits"] == 0  # compiled in the first process
    assert second["hits"] == 1 and second["misses"] == 0  # loaded in the second
