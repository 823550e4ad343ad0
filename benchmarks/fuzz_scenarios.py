"""Issue #26 acceptance: 2,000 scenario mutations by the schema-built fuzzer
(``tests/scenario_fuzz.py``: random types, magnitudes, NaN / inf, deletions, duplicates,
resized and 10^6-entry lists), each written, loaded, validated and -- when accepted -- built
into the BMS; every 20th accepted one also simulates 0.2 s through the CLI. Figures:
tracebacks, hangs (a case over 5 s), malformed error lines, safety thresholds accepted outside
their physical range (all four: goal 0), and the slowest case.

    PYTHONPATH=src python benchmarks/fuzz_scenarios.py [--cases 2000] [--seed 100000]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.scenario_fuzz import Tally, run_case


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=100_000, help="first seed (CI uses 0..299)")
    args = ap.parse_args(argv)
    tally = Tally()
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(args.seed, args.seed + args.cases):
            run_case(Path(tmp), seed, tally, simulate_every=20)
    wall = time.perf_counter() - t0
    print(
        "| cases | refused (one line) | accepted | simulated 0.2 s | tracebacks | hangs > 5 s "
        "| malformed errors | thresholds out of range | slowest case | wall |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {tally.cases} | {tally.refused} | {tally.accepted} | {tally.simulated} "
        f"| {len(tally.tracebacks)} | {len(tally.hangs)} | {len(tally.bad_errors)} "
        f"| {len(tally.out_of_range)} | {tally.slowest_s:.2f} s | {wall:.0f} s |"
    )
    for kind in ("tracebacks", "hangs", "bad_errors", "out_of_range"):
        for line in getattr(tally, kind)[:10]:
            print(f"{kind}: {line[:300]}")
    return 1 if tally.findings else 0


if __name__ == "__main__":
    raise SystemExit(main())
