"""``make mutate``: apply each hand-listed mutant (``mutants.py``) to a private copy of the
tree, run its module's behavioural tests interpreted, and report the kill rate per module.

Why a copy: the worktree is never written, so a crash, a Ctrl-C or a hung mutant cannot leave
a mutated rule behind. Why interpreted (``NUMBA_DISABLE_JIT=1``): the same kernel source runs
as plain Python in seconds, where recompiling the fused core per mutant would take minutes.

    python -m tests.mutation.run [--module limits] [--mutant NAME] [--jobs 2] [--out out]

Exit status: 0 when every mutant was killed, 1 when some survived, 2 on a stale mutant (its
snippet no longer occurs exactly once) or when a module's tests fail unmutated.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

from tests.mutation.mutants import MUTANTS, PENDING, TESTS, Mutant

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 300.0
"""A mutant whose tests run longer than this counts as killed (a hang is detected)."""
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc", ".hypothesis")


@dataclass
class Result:
    module: str
    name: str
    why: str
    outcome: str
    """``killed``, ``survived`` or ``timeout`` (counted as killed)."""
    seconds: float
    detail: str


def check_snippets(mutants: Iterable[Mutant]) -> list[str]:
    """Stale mutants: the snippet must occur exactly once, or the mutant tests nothing."""
    stale = []
    for mu in mutants:
        n = (ROOT / mu.path).read_text().count(mu.old)
        if n != 1:
            stale.append(f"{mu.module}/{mu.name}: snippet found {n} times in {mu.path}")
    return stale


def make_copy(base: Path) -> Path:
    """A private copy of what the tests import: src, tests, examples, benchmarks, pyproject."""
    base.mkdir(parents=True)
    for name in ("src", "tests", "examples", "benchmarks"):
        shutil.copytree(ROOT / name, base / name, ignore=_IGNORE)
    shutil.copy2(ROOT / "pyproject.toml", base / "pyproject.toml")
    return base


def run_tests(tree: Path, files: list[str]) -> tuple[str, float, str]:
    """Run ``files`` in ``tree`` interpreted; (passed | failed | timeout, seconds, last line)."""
    env = dict(os.environ)
    env.update(
        NUMBA_DISABLE_JIT="1",
        PYTHONPATH=f"{tree / 'src'}{os.pathsep}{tree}",
        PYBAMM_DISABLE_TELEMETRY="true",
        HYPOTHESIS_PROFILE=os.environ.get("HYPOTHESIS_PROFILE", "ci"),
    )
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *files]
    t0 = time.monotonic()
    try:
        proc = subprocess.run(
            cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return "timeout", time.monotonic() - t0, f"no result after {TIMEOUT_S:.0f} s"
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    last = lines[-1] if lines else proc.stderr.strip()[-200:]
    failed = [ln for ln in lines if ln.startswith(("FAILED", "ERROR"))]
    detail = failed[0] if failed else last
    return ("passed" if proc.returncode == 0 else "failed"), time.monotonic() - t0, detail


def run_mutant(tree: Path, mu: Mutant) -> Result:
    """Mutate the copy, run the module's tests, restore the copy (the worktree is untouched)."""
    target = tree / mu.path
    original = target.read_text()
    target.write_text(original.replace(mu.old, mu.new, 1))
    try:
        state, secs, detail = run_tests(tree, TESTS[mu.module])
    finally:
        target.write_text(original)
    outcome = {"passed": "survived", "failed": "killed"}.get(state, state)
    return Result(mu.module, mu.name, mu.why, outcome, round(secs, 1), detail)


def baseline(tree: Path, modules: list[str]) -> list[str]:
    """Modules whose tests fail without a mutant (their kill rate would mean nothing)."""
    bad = []
    for mod in modules:
        state, _, detail = run_tests(tree, TESTS[mod])
        if state != "passed":
            bad.append(f"{mod}: {detail}")
    return bad


def run_all(mutants: list[Mutant], jobs: int, work: Path) -> list[Result]:
    trees = [make_copy(work / f"tree{j}") for j in range(jobs)]
    bad = baseline(trees[0], sorted({mu.module for mu in mutants}))
    if bad:
        raise SystemExit("mutate: tests fail without a mutant:\n  " + "\n  ".join(bad))
    results: list[Result] = []

    def worker(j: int) -> None:
        for mu in mutants[j::jobs]:
            res = run_mutant(trees[j], mu)
            results.append(res)
            print(f"  {res.outcome:8} {res.module}/{res.name} ({res.seconds} s)", flush=True)

    with ThreadPoolExecutor(jobs) as pool:
        list(pool.map(worker, range(jobs)))
    order = {(mu.module, mu.name): k for k, mu in enumerate(mutants)}
    return sorted(results, key=lambda r: order[(r.module, r.name)])


def summary(results: list[Result]) -> dict[str, tuple[int, int]]:
    """Per module: (killed, total); a timeout counts as killed."""
    out: dict[str, tuple[int, int]] = {}
    for r in results:
        k, n = out.get(r.module, (0, 0))
        out[r.module] = (k + (r.outcome != "survived"), n + 1)
    return out


def table(results: list[Result]) -> str:
    rows = ["| module | killed | mutants | kill rate |", "| --- | --- | --- | --- |"]
    total_k = total_n = 0
    for mod, (k, n) in summary(results).items():
        rows.append(f"| {mod} | {k} | {n} | {100.0 * k / n:.0f} % |")
        total_k, total_n = total_k + k, total_n + n
    for mod, why in PENDING.items():
        rows.append(f"| {mod} | - | - | TODO: {why} |")
    if total_n:
        rows.append(f"| **all** | {total_k} | {total_n} | {100.0 * total_k / total_n:.0f} % |")
    survivors = [r for r in results if r.outcome == "survived"]
    if survivors:
        rows += ["", "Survivors:", ""]
        rows += [f"- {r.module}/{r.name}: {r.why}" for r in survivors]
    return "\n".join(rows)


def write_reports(results: list[Result], out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    doc = {
        "summary": {m: {"killed": k, "total": n} for m, (k, n) in summary(results).items()},
        "pending": PENDING,
        "mutants": [asdict(r) for r in results],
    }
    (out / "mutation.json").write_text(json.dumps(doc, indent=2) + "\n")
    (out / "mutation.md").write_text("# Mutation run\n\n" + table(results) + "\n")


def select(modules: list[str], names: list[str]) -> list[Mutant]:
    chosen = [mu for mu in MUTANTS if (not modules or mu.module in modules)]
    return [mu for mu in chosen if not names or mu.name in names]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--module", action="append", default=[], help="only this module (repeat)")
    ap.add_argument("--mutant", action="append", default=[], help="only this mutant (repeat)")
    ap.add_argument("--jobs", type=int, default=1, help="mutants run in parallel")
    ap.add_argument("--out", type=Path, default=ROOT / "out", help="mutation.json/.md here")
    args = ap.parse_args(argv)
    mutants = select(args.module, args.mutant)
    stale = check_snippets(MUTANTS)
    if stale:
        print("mutate: stale mutants (fix the list):\n  " + "\n  ".join(stale), file=sys.stderr)
        return 2
    if not mutants:
        print("mutate: no mutant selected", file=sys.stderr)
        return 2
    print(f"mutate: {len(mutants)} mutants, tests interpreted (NUMBA_DISABLE_JIT=1)", flush=True)
    with tempfile.TemporaryDirectory(prefix="packpilot-mutate-") as tmp:
        results = run_all(mutants, max(1, args.jobs), Path(tmp))
    print()
    print(table(results))
    write_reports(results, args.out)
    print(f"\nmutate: wrote {args.out / 'mutation.json'} and {args.out / 'mutation.md'}")
    return 0 if all(r.outcome != "survived" for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
