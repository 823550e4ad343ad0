"""Fingerprint of a closed-loop run: hashes of its trace, events and metrics.

The golden test (``tests/test_golden.py``) runs every example in ``examples/`` for a bounded
window and compares these hashes with ``hashes.json``. A refactor must leave them unchanged; a
commit that changes one says which behaviour changed and why, and regenerates the file with::

    .venv/bin/python -m tests.golden.fingerprint --update

``--dump DIR`` writes each run's events and trace as JSON/NPZ for a diff when a hash moves.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
HASHES = Path(__file__).with_name("hashes.json")

MIN_WINDOW_S = 300.0
"""Every example runs at least this long (or its whole duration, if shorter) ..."""
STEPS = 3000
"""... and up to this many steps, so slow-stepping examples (telecom, eVTOL charging, the
protection trips) reach the behaviour they exist for."""
FULL = frozenset({"uav_mission"})
"""Examples pinned over their whole duration."""


def window_s(name: str, duration_s: float, dt_s: float) -> float:
    if name in FULL:
        return duration_s
    return min(duration_s, max(MIN_WINDOW_S, STEPS * dt_s))


def _norm(x: Any) -> Any:
    """JSON-able value with its kind kept (bool / int / float / str / None / list / dict)."""
    if isinstance(x, bool | np.bool_):
        return bool(x)
    if isinstance(x, int | np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        f = float(x)
        return f if math.isfinite(f) else repr(f)
    if isinstance(x, str) or x is None:
        return x
    if isinstance(x, Mapping):
        return {str(k): _norm(v) for k, v in x.items()}
    if isinstance(x, list | tuple | np.ndarray):
        return [_norm(v) for v in x]
    return repr(x)


def _digest(obj: Any) -> str:
    text = json.dumps(_norm(obj), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _array_digest(arrays: Mapping[str, Any]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = arrays[name]
        if a is None:
            h.update(f"{name}:None".encode())
            continue
        a = np.ascontiguousarray(a)
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()[:16]


def run_example(name: str) -> Any:
    from packpilot.config import load_config
    from packpilot.sim.runner import simulate

    cfg = load_config(EXAMPLES / f"{name}.toml")
    sim = cfg.sim.model_copy(
        update={"duration_s": window_s(name, cfg.sim.duration_s, cfg.sim.dt_s), "progress": False}
    )
    return simulate(cfg.model_copy(update={"sim": sim}))


def events_of(result: Any) -> list[list[Any]]:
    return [[e.t_s, e.kind, e.battery, e.message, dict(e.data)] for e in result.events]


def trace_arrays(result: Any) -> dict[str, Any]:
    tr = result.trace
    return {
        "t_s": tr.t_s,
        "bus_v": tr.bus_v,
        "load_demand_a": tr.load_demand_a,
        "load_a": tr.load_a,
        "charger_v": tr.charger_v,
        "charger_a": tr.charger_a,
        "battery": tr.battery,
        "group_v": tr.group_v,
        "aux": tr.aux,
    }


def fingerprint(result: Any) -> dict[str, Any]:
    metrics = {k: v for k, v in result.metrics.items() if k != "wall_time_s"}
    return {
        "steps": len(result.trace.t_s),
        "events": len(result.events),
        "trace": _array_digest(trace_arrays(result)),
        "status": _digest(result.trace.status),
        "event_hash": _digest(events_of(result)),
        "metrics": _digest(metrics),
    }


def example_names() -> list[str]:
    return sorted(p.stem for p in EXAMPLES.glob("*.toml"))


def dump(name: str, result: Any, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    arrays = {k: v for k, v in trace_arrays(result).items() if v is not None}
    np.savez(out / f"{name}.npz", **arrays)
    doc = {
        "events": _norm(events_of(result)),
        "metrics": _norm({k: v for k, v in result.metrics.items() if k != "wall_time_s"}),
        "status": _norm(result.trace.status),
    }
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1, sort_keys=True))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--update", action="store_true", help="rewrite hashes.json")
    ap.add_argument("--dump", type=Path, help="write events/trace of each run into DIR")
    ap.add_argument("names", nargs="*", help="examples (default: all)")
    args = ap.parse_args(argv)
    names = args.names or example_names()
    current = json.loads(HASHES.read_text()) if HASHES.exists() else {}
    bad = 0
    for name in names:
        res = run_example(name)
        fp = fingerprint(res)
        if args.dump:
            dump(name, res, args.dump)
        same = current.get(name) == fp
        bad += not same
        print(f"{name:28s} {'same' if same else 'DIFFERENT'} {fp}")
        current[name] = fp
    if args.update:
        HASHES.write_text(json.dumps(dict(sorted(current.items())), indent=1) + "\n")
    return 1 if bad and not args.update else 0


if __name__ == "__main__":
    sys.exit(main())
