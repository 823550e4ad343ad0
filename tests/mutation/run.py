"""``make mutate``: apply each hand-listed mutant (``mutants.py``) to a private copy of the
tree, run its module's behavioural tests interpreted, and report the kill rate per module;
with ``--generated N`` also a seeded random sample of N tool-generated mutants
(``generate.py``, issue #26 item 4), ``--all-generated`` every one of them (``make soak``).

Why a copy: the worktree is never written, so a crash, a Ctrl-C or a hung mutant cannot leave
a mutated rule behind. Why interpreted (``NUMBA_DISABLE_JIT=1``): the same kernel source runs
as plain Python in seconds, where recompiling the fused core per mutant would take minutes.

    python -m tests.mutation.run [--module limits] [--mutant NAME] [--jobs 2] [--out out]
        [--generated 40 --seed 26 | --all-generated] [--no-hand]

Generated mutants that do not compile or whose module no longer imports (pytest cannot collect
the tests) are *invalid*: neither killed nor survived. A generated mutant whose tests run longer
than 3x that module's unmutated time (at least 30 s) is *killed by timeout*, counted as killed
and reported apart; a hand-listed one after the longer of 300 s and that 3x. Hand-listed
results go to out/mutation.json/.md, generated ones to out/mutation_generated.json/.md.

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

from tests.mutation import fast
from tests.mutation.equivalent import EQUIVALENT
from tests.mutation.generate import GenMutant, compiles, generate, iter_targets
from tests.mutation.mutants import MUTANTS, PENDING, TESTS, Mutant

ROOT = Path(__file__).resolve().parents[2]
TIMEOUT_S = 300.0
"""A mutant whose tests run longer than this, and than ``TIMEOUT_FACTOR`` x its module's
unmutated time, counts as killed (a hang is detected)."""
BASELINE_TIMEOUT_S = 1800.0
"""The unmutated run's limit: it measures the module's time, so it must not be cut short (the
sequencing module's tests take ~250 s interpreted, ~300 s on a loaded machine)."""
TIMEOUT_FACTOR, TIMEOUT_MIN_S = 3.0, 30.0
"""A generated mutant's limit: this many times its module's unmutated test time, at least."""
_IGNORE = shutil.ignore_patterns("__pycache__", "*.pyc", "*.nbi", "*.nbc", ".hypothesis")


@dataclass
class Result:
    module: str
    name: str
    why: str
    outcome: str
    """``killed``, ``survived``, ``timeout`` (counted as killed) or ``invalid`` (the mutated
    module does not compile or import: not counted)."""
    seconds: float
    detail: str
    id: str = ""
    line: int = 0
    operator: str = ""
    original: str = ""
    mutated: str = ""


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


def run_tests(
    tree: Path, files: list[str], timeout_s: float = TIMEOUT_S
) -> tuple[str, float, str]:
    """Run ``files`` in ``tree`` interpreted; (passed | failed | timeout | invalid, seconds,
    last line); ``invalid`` when pytest could not even collect them (an import error)."""
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
            cmd, cwd=tree, env=env, capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        return "timeout", time.monotonic() - t0, f"no result after {timeout_s:.0f} s"
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    last = lines[-1] if lines else proc.stderr.strip()[-200:]
    failed = [ln for ln in lines if ln.startswith(("FAILED", "ERROR"))]
    detail = failed[0] if failed else last
    if proc.returncode == 2 and "during collection" in proc.stdout:
        return "invalid", time.monotonic() - t0, detail
    return ("passed" if proc.returncode == 0 else "failed"), time.monotonic() - t0, detail


AnyMutant = Mutant | GenMutant


def run_mutant(tree: Path, mu: AnyMutant, timeout_s: float = TIMEOUT_S) -> Result:
    """Mutate the copy, run the module's tests, restore the copy (the worktree is untouched)."""
    target = tree / mu.path
    original = target.read_text()
    extra = {}
    if isinstance(mu, GenMutant):
        extra = dict(id=mu.id, line=mu.line, operator=mu.operator, original=mu.original,
                     mutated=mu.mutated)  # fmt: skip
        if not compiles(mu, original):
            return Result(mu.module, mu.name, mu.why, "invalid", 0.0, "does not compile",
                          **extra)  # type: ignore[arg-type]  # fmt: skip
        mutated = mu.apply(original)
    else:
        mutated = original.replace(mu.old, mu.new, 1)
    target.write_text(mutated)
    try:
        state, secs, detail = run_tests(tree, TESTS[mu.module], timeout_s)
    finally:
        target.write_text(original)
    outcome = {"passed": "survived", "failed": "killed"}.get(state, state)
    return Result(mu.module, mu.name, mu.why, outcome, round(secs, 1), detail,
                  **extra)  # type: ignore[arg-type]  # fmt: skip


def baseline(tree: Path, modules: list[str]) -> tuple[list[str], dict[str, float]]:
    """Modules whose tests fail without a mutant (their kill rate would mean nothing), and each
    module's unmutated test time (its generated mutants' timeout is a multiple of it)."""
    bad, secs = [], {}
    for mod in modules:
        state, secs[mod], detail = run_tests(tree, TESTS[mod], BASELINE_TIMEOUT_S)
        if state != "passed":
            bad.append(f"{mod}: {detail}")
    return bad, secs


def run_all(mutants: list[AnyMutant], jobs: int, work: Path) -> list[Result]:
    trees = [make_copy(work / f"tree{j}") for j in range(jobs)]
    bad, base_s = baseline(trees[0], sorted({mu.module for mu in mutants}))
    if bad:
        raise SystemExit("mutate: tests fail without a mutant:\n  " + "\n  ".join(bad))
    print("mutate: unmutated test time " + ", ".join(f"{m} {s:.0f} s" for m, s in base_s.items()),
          flush=True)  # fmt: skip
    results: list[Result] = []

    def worker(j: int) -> None:
        for mu in mutants[j::jobs]:
            limit = max(TIMEOUT_S, TIMEOUT_FACTOR * base_s[mu.module])  # a slow module's
            if isinstance(mu, GenMutant):  # tests are not a hang (sequencing: 249 s unmutated)
                limit = min(TIMEOUT_S, max(TIMEOUT_MIN_S, TIMEOUT_FACTOR * base_s[mu.module]))
            res = run_mutant(trees[j], mu, limit)
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


OUTCOMES = ("killed", "timeout", "survived", "equivalent", "invalid", "error")


def gen_summary(results: list[Result]) -> dict[str, dict[str, int]]:
    """Per module (and ``all``): how many mutants ended each way."""
    out: dict[str, dict[str, int]] = {}
    for r in results:
        for key in (r.module, "all"):
            row = out.setdefault(key, dict.fromkeys(OUTCOMES, 0))
            row[r.outcome] += 1
    if "all" in out:
        out["all"] = out.pop("all")  # last
    return out


def kill_rate(row: dict[str, int]) -> float | None:
    """Killed (timeouts included) over valid mutants; invalid ones are not mutants of a rule."""
    valid = row["killed"] + row["timeout"] + row["survived"]
    return None if not valid else 100.0 * (row["killed"] + row["timeout"]) / valid


def gen_table(results: list[Result], how: str) -> str:
    rows = [how, "", "| module | killed | by timeout | survived | equivalent | invalid | error | "
            "kill rate |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for mod, row in gen_summary(results).items():
        rate = kill_rate(row)
        cells = " | ".join(str(row[o]) for o in OUTCOMES)
        rows.append(f"| {mod} | {cells} | {'-' if rate is None else f'{rate:.0f} %'} |")
    survivors = [r for r in results if r.outcome == "survived"]
    if survivors:
        rows += ["", "Survivors (id, module:line, operator: original -> mutated):", ""]
        rows += [f"- `{r.id}` {r.module}:{r.line} {r.operator}: `{r.original.strip()}` -> "
                 f"`{r.mutated.strip()}`" for r in survivors]  # fmt: skip
    return "\n".join(rows)


def write_gen_reports(results: list[Result], out: Path, how: str) -> None:
    out.mkdir(parents=True, exist_ok=True)
    doc = {"how": how, "summary": gen_summary(results), "mutants": [asdict(r) for r in results]}
    (out / "mutation_generated.json").write_text(json.dumps(doc, indent=2) + "\n")
    (out / "mutation_generated.md").write_text(
        "# Generated mutants\n\n" + gen_table(results, how) + "\n"
    )


def from_fast(r: fast.FastResult) -> Result:
    """A generated mutant's result as the reports take it."""
    why = f"{r.original.strip()}  ->  {r.mutated.strip()}"
    outcome, detail = r.outcome, r.detail
    if outcome == "survived" and r.id in EQUIVALENT:  # judged: no test can kill it
        outcome, detail = "equivalent", EQUIVALENT[r.id]
    return Result(r.module, f"{r.operator}@{r.line}#{r.id}", why, outcome, r.seconds,
                  detail, r.id, r.line, r.operator, r.original, r.mutated)  # fmt: skip


def select(modules: list[str], names: list[str]) -> list[Mutant]:
    chosen = [mu for mu in MUTANTS if (not modules or mu.module in modules)]
    return [mu for mu in chosen if not names or mu.name in names]


def choose_generated(args: argparse.Namespace) -> tuple[list[GenMutant], str]:
    """The generated mutants the options ask for, and a line saying how they were chosen."""
    gen = generate(list(iter_targets(args.module)))
    how = f"all {len(gen)} generated mutants"
    if args.id:
        gen = [m for m in gen if m.id in args.id]
        how = f"{len(gen)} generated mutants chosen by id"
    elif not args.all_generated:
        total = len(gen)
        gen = fast.stratified(gen, args.generated, args.seed, args.floor) if args.generated else []
        how = (f"{len(gen)} of {total} generated mutants, stratified by module (at least "
               f"{args.floor} each), seed {args.seed}")
    if args.module:
        how += " (modules: " + ", ".join(args.module) + ")"
    return gen, how


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--module", action="append", default=[], help="only this module (repeat)")
    ap.add_argument("--mutant", action="append", default=[], help="only this mutant (repeat)")
    ap.add_argument("--jobs", type=int, default=1, help="mutants run in parallel")
    ap.add_argument("--out", type=Path, default=ROOT / "out", help="mutation*.json/.md here")
    ap.add_argument("--generated", type=int, default=0, metavar="N",
                    help="also N generated mutants drawn at random (seeded)")
    ap.add_argument("--all-generated", action="store_true", help="every generated mutant")
    ap.add_argument("--seed", type=int, default=26, help="sampling seed for --generated")
    ap.add_argument("--id", action="append", default=[], help="only this generated mutant id")
    ap.add_argument("--no-hand", action="store_true", help="skip the hand-listed mutants")
    ap.add_argument("--floor", type=int, default=1,
                    help="--generated: at least this many mutants of every module")
    ap.add_argument("--resume", action="store_true",
                    help="keep the generated results already in OUT/mutation_generated.jsonl")
    args = ap.parse_args(argv)  # fmt: skip
    mutants = [] if args.no_hand else select(args.module, args.mutant)
    stale = check_snippets(MUTANTS)
    if stale:
        print("mutate: stale mutants (fix the list):\n  " + "\n  ".join(stale), file=sys.stderr)
        return 2
    gen, how = choose_generated(args)
    if not mutants and not gen:
        print("mutate: no mutant selected", file=sys.stderr)
        return 2
    print(f"mutate: {len(mutants)} hand-listed + {len(gen)} generated mutants, tests "
          "interpreted (NUMBA_DISABLE_JIT=1)", flush=True)  # fmt: skip
    results: list[Result] = []
    if mutants:
        with tempfile.TemporaryDirectory(prefix="packpilot-mutate-") as tmp:
            results += run_all(list(mutants), max(1, args.jobs), Path(tmp))
    if gen:  # only the tests that reach each mutant, fail-fast, forked (fast.py)
        log = (args.out / "mutation_generated.jsonl").resolve()
        if not args.resume:
            log.unlink(missing_ok=True)
        ran = fast.run_many(gen, log, (args.out / "mutation_map").resolve(), False,
                            max(1, args.jobs))  # fmt: skip
        results += [from_fast(r) for r in ran]
    hand = [r for r in results if not r.id]
    made = [r for r in results if r.id]
    if hand:
        print("\n" + table(hand))
        write_reports(hand, args.out)
        print(f"\nmutate: wrote {args.out / 'mutation.json'} and {args.out / 'mutation.md'}")
    if made:
        print("\n" + gen_table(made, how))
        write_gen_reports(made, args.out, how)
        print(f"\nmutate: wrote {args.out / 'mutation_generated.json'} and .md")
    return 0 if all(r.outcome != "survived" for r in results) else 1


if __name__ == "__main__":
    raise SystemExit(main())
