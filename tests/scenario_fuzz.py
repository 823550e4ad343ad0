"""A scenario fuzzer built from the schema, not from the examples (issue #26 §3).

The base scenarios are made of the config models' own defaults (every section, dumped) on a
small random pack; the mutations are generic -- random types, magnitudes from 1e-300 to
1e300, NaN / inf, deletions, duplicated entries and names, resized and huge lists, unknown
keys, tables swapped for scalars -- and are drawn for any path of the scenario, so no case
knows which value a field wants. A case passes when the file is refused with one ``error``
line naming the file, or accepted with every safety threshold inside the physical range
:data:`PHYSICAL` states (written from docs/safety.md "Physical ranges", independently of the
validators that enforce them).

Used by ``tests/test_fuzz_scenarios.py`` (a few hundred seeded cases in CI) and
``benchmarks/fuzz_scenarios.py`` (the 2,000 of the acceptance, figures in RESULTS.md).
"""

from __future__ import annotations

import copy
import fnmatch
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

POS = 5e-324
"""Lower end of a range that excludes 0 (the smallest positive float)."""

PHYSICAL: dict[str, tuple[float, float]] = {
    # sequencing (docs/parallel_discharge.md): detection thresholds, spreads, rule times
    "sequencing.v_th": (POS, 100.0),
    "sequencing.v_co": (POS, 100.0),
    "sequencing.i_det": (POS, 20.0),
    "sequencing.i_rev": (POS, 20.0),
    "sequencing.q_rev_as": (POS, 3600.0),
    "sequencing.t_on": (POS, 10.0),
    "sequencing.t_debounce": (0.0, 10.0),
    "sequencing.t_mode": (0.0, 10.0),
    "sequencing.charge_limit_c": (POS, 100.0),
    "sequencing.charge_limit_margin": (POS, 1.0),
    "sequencing.r_batt_ohm": (POS, 10.0),
    # equalization
    "equalization.dv_set_v": (POS, 1.0),
    "equalization.n_ah": (0.0, 1.0),
    "equalization.min_current_a": (0.0, 1e5),
    "equalization.equalizer_max_a": (POS, 1e5),
    # charging (battery or cell volts)
    "charging.v_sat_v": (2.0, 1e4),
    "charging.cell_v_limit_v": (2.0, 5.0),
    "charging.overvoltage_margin_v": (POS, 100.0),
    "charging.charger_current_limit_a": (POS, 1e5),
    "charging.termination_current_a": (POS, 1e5),
    "charging.charger_status_timeout_s": (POS, 60.0),
    "charging.r_comp_max_ohm": (POS, 10.0),
    "charging.eps_eq_v": (POS, 100.0),
    "charging.delta_v1_v": (POS, 100.0),
    # protection
    "protection.parameters.*.cutoff_v": (2.0, 4.5),
    "protection.parameters.*.t_max_s": (0.001, 86_400.0),
    "protection.discharge_threshold_a": (0.0, 20.0),
    "protection.charge_threshold_a": (0.0, 20.0),
    "protection.warning_share": (POS, 1.0),
    # limits
    "limits.rows.*.debounce": (1, 100),
    "limits.rows.*.delay_s": (0.0, 60.0),
    "limits.derate_fraction": (0.0, 1.0),
    "limits.context_current_c": (0.0, 10.0),
    "limits.derating.*.c_rate.*": (0.0, 1000.0),
    # plausibility
    "plausibility.nonfinite_delay_s": (0.0, 60.0),
    "plausibility.range_delay_s": (0.0, 60.0),
    "plausibility.switch_delay_s": (0.0, 60.0),
    "plausibility.sum_delay_s": (0.0, 60.0),
    "plausibility.max_sample_age_s": (0.0, 60.0),
    "plausibility.stuck_time_s": (POS, 3600.0),
    "plausibility.stuck_current_c": (0.0, 10.0),
    "plausibility.sum_tolerance_v_per_group": (0.0, 1.0),
    "plausibility.cell_v_range.*": (0.0, 10.0),
    "plausibility.temp_range_c.*": (-100.0, 300.0),
    # soc, supervisor
    "soc.rest_current_a": (POS, 20.0),
    "soc.blend": (0.0, 1.0),
    "supervisor.discharge_current_a": (POS, 20.0),
    "supervisor.join_limit_v": (POS, 100.0),
    "supervisor.init_time_s": (0.0, 60.0),
    # plant and charger
    "charger.current_a": (0.0, 1e5),
    "charger.rated_a": (POS, 1e5),
    "charger.voltage_v": (0.0, 1e4),
    "charger.heartbeat_timeout_s": (POS, 60.0),
    "pack.switch.reverse_trip_a": (POS, 20.0),
    "pack.batteries.*.capacity_ah": (1e-3, 1e4),
    "sim.dt_s": (1e-4, 10.0),
    "sim.duration_s": (1e-4, 1e9),
}
"""Dotted path pattern (``*`` = any list index or key) -> inclusive physical range of every
safety threshold the fuzzer checks in an accepted scenario."""

SECTION_NAMES = ("protection", "sequencing", "charging", "equalization")
SAFETY_NAMES = ("supervisor", "limits", "plausibility", "soc")
EXTREMES: tuple[Any, ...] = (
    0,
    -0.0,
    1e-300,
    -1e-300,
    1e-12,
    1e300,
    -1e300,
    1e308,
    9.2e18,
    2**63,
    -(2**63),
    2**64,
    float("nan"),
    float("inf"),
    float("-inf"),
    True,
    False,
    "",
    "x" * 300,
    [],
    {},
)


def base_scenario(rng: np.random.Generator) -> dict[str, Any]:
    """A valid scenario from the models' defaults on a random pack (1-4 batteries, 1-4
    methods in random order, random safety sections): nothing taken from an example file."""
    from packpilot.config.scenario import SECTIONS

    n = int(rng.integers(1, 5))
    batteries = [
        {"name": f"B{k}", "cells_per_group": int(rng.integers(1, 13)), "soc0": float(rng.random())}
        for k in range(n)
    ]
    cfg: dict[str, Any] = {
        "pack": {"batteries": batteries},
        "sim": {"dt_s": 0.1, "duration_s": 1.0, "progress": False},
    }
    methods = list(rng.permutation(SECTION_NAMES)[: int(rng.integers(0, 5))])
    cfg["controller"] = [str(m) for m in methods]
    for name in [*methods, *SAFETY_NAMES]:
        if name in methods or rng.random() < 0.6:
            cfg[name] = SECTIONS[name]().model_dump(mode="json", exclude_none=True)
    if rng.random() < 0.5:
        cfg["charger"] = {"present": True, "rated_a": 50.0, "current_a": 10.0, "voltage_v": 30.0}
    if rng.random() < 0.5:
        cfg["load"] = {"kind": "current", "value": float(rng.uniform(0, 30))}
    return cfg


def paths(node: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every key path of parsed TOML (tables and list entries, leaves and inner nodes)."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield (*prefix, k)
            yield from paths(v, (*prefix, k))
    elif isinstance(node, list | tuple):
        for i, v in enumerate(node):
            yield (*prefix, i)
            yield from paths(v, (*prefix, i))


def _parent(cfg: Any, path: tuple[Any, ...]) -> Any:
    node = cfg
    for key in path[:-1]:
        node = node[key]
    return node


def _random_value(rng: np.random.Generator, old: Any) -> Any:
    """A value of a random type, or of the old value's type at a random magnitude."""
    pick = int(rng.integers(0, 8))
    if pick == 0:
        return EXTREMES[int(rng.integers(0, len(EXTREMES)))]
    if pick == 1 and isinstance(old, int | float) and not isinstance(old, bool):
        return float(old) * 10.0 ** float(rng.uniform(-300, 300)) * float(rng.choice([-1, 1]))
    if pick == 2:
        return float(rng.uniform(-1e3, 1e3))
    if pick == 3:
        return int(rng.integers(-(2**62), 2**62))
    if pick == 4:
        return "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, int(rng.integers(0, 12))))
    if pick == 5:
        size = int(10 ** rng.uniform(0, 6))  # up to a 10^6-entry list
        return [float(rng.random())] * size
    if pick == 6 and isinstance(old, int | float) and not isinstance(old, bool):
        return old * float(rng.choice([0.0, -1.0, 1e-12, 1e12, 2.0, 0.5]))
    return {"k": float(rng.random())}


def _is_number(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _magnitude(rng: np.random.Generator, old: float) -> float:
    """The same number scaled by 10^-12..10^12 (or to an extreme), possibly negated: the
    values a unit slip, a typo or a hostile file produce, of the type the field wants."""
    pick = rng.random()
    if pick < 0.15:
        return float(rng.choice([1e300, -1e300, 1e-300, 0.0, -0.0, 9.2e18, 1e-12]))
    base = float(old) if old else 1.0
    sign = -1.0 if rng.random() < 0.2 else 1.0
    return sign * base * 10.0 ** float(rng.uniform(-12, 12))


def mutate(rng: np.random.Generator, cfg: dict[str, Any]) -> list[str]:
    """Apply one random mutation in place; returns a short description (for reports)."""
    all_paths = list(paths(cfg))
    if not all_paths:
        return ["empty"]
    numeric = [p for p in all_paths if _is_number(_parent(cfg, p)[p[-1]])]
    if numeric and rng.random() < 0.5:  # half the mutations: a number at a new magnitude
        path = numeric[int(rng.integers(0, len(numeric)))]
        parent = _parent(cfg, path)
        parent[path[-1]] = _magnitude(rng, parent[path[-1]])
        return [f"scale {'.'.join(map(str, path))}"]
    path = all_paths[int(rng.integers(0, len(all_paths)))]
    parent = _parent(cfg, path)
    key = path[-1]
    old = parent[key]
    op = int(rng.integers(0, 7))
    where = ".".join(map(str, path))
    if op == 0:  # delete
        del parent[key]
        return [f"del {where}"]
    if op == 1 and isinstance(parent, list):  # duplicate an entry (names, methods, rows)
        parent.insert(int(key), copy.deepcopy(old))
        return [f"dup {where}"]
    if op == 2 and isinstance(old, list):  # resize a list
        size = int(10 ** rng.uniform(0, 6)) if rng.random() < 0.3 else int(rng.integers(0, 40))
        parent[key] = [copy.deepcopy(old[i % len(old)]) for i in range(size)] if old else []
        return [f"resize {where} to {size}"]
    if op == 3 and isinstance(parent, dict):  # unknown key beside it
        parent[f"{key}_x"] = _random_value(rng, old)
        return [f"unknown {where}_x"]
    if op == 4 and isinstance(old, dict | list):  # a table / array becomes a scalar
        parent[key] = _random_value(rng, None)
        return [f"scalar {where}"]
    parent[key] = _random_value(rng, old)
    return [f"set {where}"]


def values_at(cfg: Any, pattern: str) -> Iterator[tuple[str, Any]]:
    """``(path, value)`` of every entry of a validated config (dumped) matching ``pattern``."""
    for path in paths(cfg):
        dotted = ".".join(map(str, path))
        if fnmatch.fnmatchcase(dotted, pattern):
            yield dotted, _parent(cfg, path)[path[-1]]


def out_of_range(dumped: dict[str, Any]) -> list[str]:
    """Every checked safety threshold of an accepted scenario outside :data:`PHYSICAL`."""
    bad = []
    for pattern, (lo, hi) in PHYSICAL.items():
        for where, value in values_at(dumped, pattern):
            if value is None or isinstance(value, dict | list | str):
                continue
            if not (isinstance(value, int | float) and math.isfinite(value) and lo <= value <= hi):
                bad.append(f"{where} = {value!r} outside {lo:g}..{hi:g}")
    return bad


@dataclass
class Tally:
    """Outcome counts of a fuzz run and the first findings of each kind."""

    cases: int = 0
    refused: int = 0
    accepted: int = 0
    unwritable: int = 0
    simulated: int = 0
    tracebacks: list[str] = field(default_factory=list)
    hangs: list[str] = field(default_factory=list)
    bad_errors: list[str] = field(default_factory=list)
    out_of_range: list[str] = field(default_factory=list)
    slowest_s: float = 0.0

    @property
    def findings(self) -> int:
        return (
            len(self.tracebacks) + len(self.hangs) + len(self.bad_errors) + len(self.out_of_range)
        )


MAX_CASE_S = 5.0
"""A case (write, read, validate) slower than this is a hang."""


def run_case(tmp: Path, seed: int, tally: Tally, simulate_every: int = 0) -> None:
    """One scenario: base + 1-4 mutations, written, loaded, validated and (accepted) built;
    with ``simulate_every = n``, every n-th accepted one also runs 0.2 s through the CLI
    (exit 0, or 2 with one error line)."""
    from packpilot.config import load_config
    from packpilot.errors import ConfigError

    rng = np.random.default_rng(seed)
    cfg = base_scenario(rng)
    what = [m for _ in range(min(1 + int(rng.geometric(0.6)) - 1, 4)) for m in mutate(rng, cfg)]
    tally.cases += 1
    p = tmp / f"fuzz{seed}.toml"
    try:
        text = tomli_w.dumps(cfg)
    except (TypeError, ValueError):
        tally.unwritable += 1
        return
    p.write_text(text)
    t0 = time.perf_counter()
    label = f"seed {seed}: {'; '.join(what)}"
    scenario = None
    try:
        scenario = load_config(p)
    except ConfigError as err:
        tally.refused += 1
        msg = str(err)
        if "\n" in msg or not msg.startswith(str(p)) or len(msg) > 1000:
            tally.bad_errors.append(f"{label}: {msg[:300]!r}")
    except Exception as err:
        tally.tracebacks.append(f"{label}: {type(err).__name__}: {str(err)[:200]}")
    else:
        tally.accepted += 1
        tally.out_of_range += [f"{label}: {b}" for b in out_of_range(scenario.model_dump())]
        _build(scenario, label, tally)
    took = time.perf_counter() - t0
    tally.slowest_s = max(tally.slowest_s, took)
    if took > MAX_CASE_S:
        tally.hangs.append(f"{label}: {took:.1f} s")
    if simulate_every and scenario is not None and tally.accepted % simulate_every == 1:
        _simulate(p, label, tally)
    p.unlink(missing_ok=True)


def _build(scenario: Any, label: str, tally: Tally) -> None:
    """Build what ``simulate`` builds before its first step (plant, BMS core, load profile):
    where the accepted-but-absurd values of issue #26 raised (a repeated method, 15 parts,
    ``t_max_s = 1e-12``). A one-line user error is fine; anything else is a traceback."""
    from packpilot.errors import PackPilotError
    from packpilot.sim.runner import Runner

    try:
        Runner(scenario.model_copy(update={"can": None}), progress=False)
    except PackPilotError:
        pass
    except Exception as err:
        tally.tracebacks.append(f"{label}: build: {type(err).__name__}: {str(err)[:200]}")


def _simulate(p: Path, label: str, tally: Tally) -> None:
    from typer.testing import CliRunner

    from packpilot.cli import app

    res = CliRunner().invoke(app, ["simulate", str(p), "--duration", "0.2", "--json"])
    tally.simulated += 1
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        tally.tracebacks.append(f"{label}: simulate: {type(res.exception).__name__}")
    elif res.exit_code not in (0, 2):
        tally.tracebacks.append(f"{label}: simulate exit {res.exit_code}: {res.stderr[-200:]}")
    elif res.exit_code == 2:
        lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
        if len(lines) != 1 or not lines[0].startswith("error: "):
            tally.bad_errors.append(f"{label}: simulate: {res.stderr[:300]!r}")
