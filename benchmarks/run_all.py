"""``make bench``: run every benchmark module, print its table, and write RESULTS.md.

Each ``benchmarks/bench_*.py`` exposes ``run() -> list[dict]`` (or a dict of figures). Ratios are
always against a reference measured in the same run, so the numbers travel across machines.
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
import os
import platform
import sys
import time
import traceback
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ORDER = [
    "bench_cell",
    "bench_loop",
    "bench_protection",
    "bench_sequencing",
    "bench_charging",
    "bench_equalization",
    "bench_campaign",
]


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _table(rows: list[dict[str, Any]]) -> str:
    cols: list[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(lines)


def main() -> int:
    os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")
    sys.path.insert(0, str(HERE.parent))
    sys.path.insert(0, str(HERE))
    only = set(sys.argv[1:])
    names = [n for n in ORDER if (HERE / f"{n}.py").exists() and (not only or n in only)]
    names += sorted(
        p.stem
        for p in HERE.glob("bench_*.py")
        if p.stem not in ORDER and (not only or p.stem in only)
    )
    sections: list[str] = []
    failed = 0
    for name in names:
        spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
        assert spec is not None and spec.loader is not None
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # worker processes pickle functions by module name
        t0 = time.perf_counter()
        try:
            spec.loader.exec_module(mod)
            out = mod.run()
            rows = out if isinstance(out, list) else [out]
            text = _table(rows)
        except Exception:
            failed += 1
            text = "FAILED:\n```\n" + traceback.format_exc() + "```"
        wall = time.perf_counter() - t0
        section = f"## {name} ({wall:.0f} s)\n\n{text}\n"
        print(section, flush=True)
        sections.append(section)
    header = (
        "# Benchmark results\n\n"
        f"- date: {_dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')}\n"
        f"- machine: {platform.machine()}, {os.cpu_count()} cores, {platform.processor() or '?'},"
        f" Python {platform.python_version()}, {platform.platform()}\n"
        f"- command: `make bench` (`python benchmarks/run_all.py {' '.join(sys.argv[1:])}`)\n\n"
    )
    if not only:
        (HERE / "RESULTS.md").write_text(header + "\n".join(sections))
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
