"""Cheap runs of the generated mutants (issue #26 item 4): each mutant runs only the
behavioural tests that execute the mutated statement, fail-fast, in a forked child of a server
that has the libraries imported already.

Why this is sound: the tests run interpreted and (profile ``mutate``) derandomized, so a test
that never executes the mutated statement on the original code runs exactly the same on the
mutant and cannot kill it. Which test executes which line is recorded once per module by
running its ``TESTS`` with a line tracer (``cover_plugin.py``) on the unmutated tree: the
**map**, cached under ``out/mutation_map/`` and rebuilt when a rules file or a test file
changes. Lines executed at import (module constants, defaults) select every test of the
module; a test that starts a subprocess (the tracer cannot see into it) is selected for every
mutant of its module. A mutant whose statement no test executes *survives* without a run
(``detail`` says so).

Per mutant: the mutated file is written into a private copy of the tree (never the worktree),
the selected tests run fastest first with ``-x``; limit = max(30 s, 3 x their unmutated time
in the map + 10 s); a mutant over the limit is run once more with 3 x that limit and only then
counted **killed by timeout** (killed, reported apart).

    python -m tests.mutation.fast --sample 400 --seed 26 --log out/mutation_sample.jsonl
    python -m tests.mutation.fast --id 3a56847a33 [--full]
    python -m tests.mutation.fast --report out/mutation_sample.jsonl
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import json
import os
import random
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tests.mutation.equivalent import EQUIVALENT
from tests.mutation.generate import GenMutant, compiles, generate, iter_targets
from tests.mutation.mutants import TESTS

ROOT = Path(__file__).resolve().parents[2]
MAP_PROFILE: dict[str, str] = {"sequencing": "dev"}
"""Modules whose map is traced under a smaller Hypothesis budget than the mutant runs (profile
``dev``: a tenth of the examples): sequencing's closed-loop properties are 200 whole plant
simulations, interpreted and traced (the full-budget map did not finish in 41 min on the
loaded box). Sound: every property test of such a map is marked ``partial`` and selected for
every mutant of the module (its traced lines are only a lower bound); the plain tests are
traced in full. Each mutant still runs under ``mutate`` (the full CI budget)."""
PARTIAL_FACTOR = 10.0
"""A partial (``dev``-budget) test's traced time x this is its expected time in a mutant run
(``dev`` runs a tenth of the CI examples, at least 5): its timeout must not be a tenth of it."""
TIMEOUT_MIN_S, TIMEOUT_FACTOR, TIMEOUT_PAD_S, RETRY_FACTOR = 30.0, 3.0, 10.0, 3.0
PYTEST_ARGS = ["-x", "-q", "-p", "no:cacheprovider", "-p", "no:xdist"]


@dataclass
class FastResult:
    id: str
    module: str
    line: int
    operator: str
    original: str
    mutated: str
    outcome: str
    """``killed``, ``timeout`` (killed by timeout), ``survived``, ``invalid`` or ``error``."""
    seconds: float
    detail: str
    tests: int
    """How many tests were selected (0: no test executes the mutated statement)."""


def stratified(mutants: list[GenMutant], n: int, seed: int, floor: int) -> list[GenMutant]:
    """About ``n`` mutants, every module represented: each module gets its share of ``n`` in
    proportion to its size but at least ``floor`` (or all it has), drawn with its own seeded
    generator from its mutants sorted by id (the same seed and code give the same sample)."""
    by: dict[str, list[GenMutant]] = {}
    for m in mutants:
        by.setdefault(m.module, []).append(m)
    total = len(mutants)
    out: list[GenMutant] = []
    for mod, pool in by.items():
        pool = sorted(pool, key=lambda m: m.id)
        k = min(len(pool), max(floor, round(n * len(pool) / total)))
        out += random.Random(f"{seed}:{mod}").sample(pool, k)
    random.Random(seed).shuffle(out)  # run order: modules interleaved, partial runs are fair
    return out


# --- which lines a mutant touches ------------------------------------------------------------


def _stmt_spans(source: str) -> list[tuple[int, int, int, int]]:
    """(start byte, end byte, first line, last header line) of every statement."""
    raw = source.encode()
    starts = [0] + [k + 1 for k in range(len(raw)) if raw[k : k + 1] == b"\n"]
    out = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.stmt):
            continue
        lo = starts[node.lineno - 1] + node.col_offset
        hi = starts[node.end_lineno - 1] + node.end_col_offset  # type: ignore[operator]
        body = getattr(node, "body", None)
        last = node.end_lineno or node.lineno
        if isinstance(body, list) and body:
            last = max(node.lineno, body[0].lineno - 1)  # a compound statement: its header
        out.append((lo, hi, node.lineno, last))
    return out


def mutant_lines(mu: GenMutant, spans: list[tuple[int, int, int, int]]) -> set[int]:
    """The mutated line(s) and the header of the innermost statement holding the splice."""
    lines = set(range(mu.line, mu.line + mu.original.count("\n") + 1))
    inner = [s for s in spans if s[0] <= mu.start and mu.end <= s[1]]
    if inner:
        _, _, first, last = min(inner, key=lambda s: s[1] - s[0])
        lines |= set(range(first, last + 1))
    return lines


# --- the map ----------------------------------------------------------------------------------


def _env(tree: Path) -> dict[str, str]:
    env = dict(os.environ)
    env.update(NUMBA_DISABLE_JIT="1", PYTHONPATH=f"{tree / 'src'}{os.pathsep}{tree}",
               PYBAMM_DISABLE_TELEMETRY="true", HYPOTHESIS_PROFILE="mutate")  # fmt: skip
    return env


def rules_files() -> list[str]:
    return [t.path for t in iter_targets([])]


def _map_key(tree: Path, module: str, paths: list[str]) -> str:
    """A hash of what the map depends on: the traced files, the module's tests, the fixtures."""
    h = hashlib.sha1(module.encode())
    files = {*paths, *(f.split("::")[0] for f in TESTS[module])}
    files |= {"tests/conftest.py", "tests/budget.py", "tests/mutation/cover_plugin.py"}
    for f in sorted(files):
        if (tree / f).exists():
            h.update(f.encode() + (tree / f).read_bytes())
    h.update(repr(TESTS[module]).encode())
    return h.hexdigest()[:16]


def _rel(f: str, tree: Path) -> str:
    base = str(tree.resolve())
    return str(Path(f).relative_to(base)) if f.startswith(base) else f


def build_map(tree: Path, module: str, cache: Path,
              paths: list[str] | None = None) -> dict[str, Any]:  # fmt: skip
    """Which test executes which line of ``paths`` (default: every rules file), for
    ``module``'s tests on the unmutated ``tree`` (cached by content)."""
    paths = rules_files() if paths is None else paths
    profile = MAP_PROFILE.get(module, "mutate")
    key = _map_key(tree, module, paths) + ("" if profile == "mutate" else f"-{profile}")
    path = cache / f"{module}-{key}.json"
    if path.exists():
        return dict(json.loads(path.read_text()))
    cache.mkdir(parents=True, exist_ok=True)
    env = _env(tree)
    env["MUTATE_COVER_FILES"] = os.pathsep.join(str(tree / p) for p in paths)
    env["MUTATE_COVER_OUT"] = str(path.with_suffix(".tmp"))
    if profile != "mutate":
        env.update(HYPOTHESIS_PROFILE=profile, MUTATE_COVER_PARTIAL="1")
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "-p", "tests.mutation.cover_plugin", *TESTS[module]],
                          cwd=tree, env=env, capture_output=True, text=True)  # fmt: skip
    if not path.with_suffix(".tmp").exists():
        raise SystemExit(f"fast: the map run of {module} wrote nothing:\n{proc.stdout[-2000:]}"
                         f"{proc.stderr[-2000:]}")  # fmt: skip
    doc = json.loads(path.with_suffix(".tmp").read_text())
    path.with_suffix(".tmp").unlink()
    # file keys relative to the tree, so the map does not depend on where the copy was
    doc["lines"] = {ctx: {_rel(f, tree): ls for f, ls in per.items()}
                    for ctx, per in doc["lines"].items()}  # fmt: skip
    doc["seconds"] = round(time.monotonic() - t0, 1)
    doc["returncode"] = proc.returncode
    failed = [t for t, d in doc["tests"].items() if d.get("failed")]
    if failed:
        print(f"fast: {module}: {len(failed)} test(s) fail unmutated, left out: {failed[:5]}",
              flush=True)  # fmt: skip
    path.write_text(json.dumps(doc))
    return dict(doc)


def select_tests(cmap: dict[str, Any], path: str, lines: set[int]) -> tuple[list[str], float]:
    """The tests to run against a mutant of ``lines`` of ``path``, fastest first (spawning
    tests last), and their unmutated seconds."""
    tests = {t: d for t, d in cmap["tests"].items() if not d.get("failed") and "seconds" in d}
    at_import = set(cmap["lines"].get("", {}).get(path, ()))
    if lines & at_import:
        chosen = set(tests)
    else:
        chosen = {t for t in tests if lines & set(cmap["lines"].get(t, {}).get(path, ()))}
        if chosen:  # a spawned CLI runs every rule: it might reach the line unseen
            chosen |= {t for t, d in tests.items() if d.get("spawns")}
        chosen |= {t for t, d in tests.items() if d.get("partial")}  # traced on fewer examples
    def secs(t: str) -> float:
        return float(tests[t]["seconds"]) * (PARTIAL_FACTOR if tests[t].get("partial") else 1.0)

    order = sorted(chosen, key=lambda t: (bool(tests[t].get("spawns")), secs(t)))
    return order, sum(secs(t) for t in order)


# --- running ----------------------------------------------------------------------------------


class Server:
    """A fork server (``forkserver.py``) in a private tree."""

    def __init__(self, tree: Path) -> None:
        self.tree = tree
        self.proc = subprocess.Popen([sys.executable, str(tree / "tests/mutation/forkserver.py")],
                                     cwd=tree, env=_env(tree), stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)  # fmt: skip

    def run(self, tests: list[str], timeout_s: float) -> dict[str, Any]:
        req = {"args": [*PYTEST_ARGS, *tests], "timeout": timeout_s,
               "log": str(self.tree / "last_run.log")}  # fmt: skip
        assert self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        return dict(json.loads(self.proc.stdout.readline()))

    def close(self) -> None:
        if self.proc.stdin:
            self.proc.stdin.close()
        try:
            self.proc.wait(120)  # it may still be importing on a loaded box
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


def run_one(server: Server, mu: GenMutant, cmap: dict[str, Any], spans: Any,
            full: bool = False, only: list[str] | None = None) -> FastResult:  # fmt: skip
    target = server.tree / mu.path
    original = target.read_text()
    base: dict[str, Any] = dict(id=mu.id, module=mu.module, line=mu.line, operator=mu.operator,
                original=mu.original, mutated=mu.mutated)  # fmt: skip
    if not compiles(mu, original):
        return FastResult(**base, outcome="invalid", seconds=0.0, detail="does not compile",
                          tests=0)  # fmt: skip
    if only:  # a confirmation: these tests (a new one), no map, the minimum timeout x 10
        tests, base_s = list(only), TIMEOUT_MIN_S * 3
    elif full:
        tests = sorted((t for t, d in cmap["tests"].items() if not d.get("failed")),
                       key=lambda t: cmap["tests"][t].get("seconds", 0.0))  # fmt: skip
        base_s = sum(cmap["tests"][t].get("seconds", 0.0) for t in tests)
    else:
        tests, base_s = select_tests(cmap, mu.path, mutant_lines(mu, spans))
    if not tests:
        return FastResult(**base, outcome="survived", seconds=0.0, tests=0,
                          detail="no behavioural test executes the mutated statement")  # fmt: skip
    limit = max(TIMEOUT_MIN_S, TIMEOUT_FACTOR * base_s + TIMEOUT_PAD_S)
    target.write_text(mu.apply(original))
    try:
        got = server.run(tests, limit)
        secs = got["seconds"]
        if got["state"] == "timeout":  # a loaded box or a hang? once more, 3x longer
            got = server.run(tests, RETRY_FACTOR * limit)
            secs += got["seconds"]
    finally:
        target.write_text(original)
    outcome = {"passed": "survived", "failed": "killed"}.get(got["state"], got["state"])
    return FastResult(**base, outcome=outcome, seconds=round(secs, 2), detail=got["detail"],
                      tests=len(tests))  # fmt: skip


def make_tree(base: Path, root: Path | None = None) -> Path:
    """A private copy of the project (``run.make_copy``) or of any other ``root``."""
    from tests.mutation.run import make_copy

    if root is None:
        return make_copy(base)
    shutil.copytree(root, base, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return base


def _logged(log: Path) -> set[str]:
    """Ids already in ``log`` (another run may append to the same log: two processes, one
    from each end of a sample, share the work without running a mutant twice)."""
    if not log.exists():
        return set()
    return {json.loads(ln)["id"] for ln in log.read_text().splitlines() if ln.strip()}


def run_many(mutants: list[GenMutant], log: Path, cache: Path, full: bool = False,
             jobs: int = 1, root: Path | None = None,
             only: list[str] | None = None) -> list[FastResult]:  # fmt: skip
    """Run ``mutants`` (``jobs`` at a time, each job its own tree and server), appending each
    result to ``log`` (JSON lines) as it ends; ids already in ``log`` are skipped (a stopped
    run resumes where it was)."""
    done: dict[str, FastResult] = {}
    if log.exists():
        for ln in log.read_text().splitlines():
            if ln.strip():
                r = FastResult(**json.loads(ln))
                done[r.id] = r
    todo = [m for m in mutants if m.id not in done]
    print(f"fast: {len(mutants)} mutants, {len(mutants) - len(todo)} already in {log}",
          flush=True)  # fmt: skip
    if not todo:
        return [done[m.id] for m in mutants if m.id in done]
    lock = threading.Lock()
    count = [0]
    log.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="packpilot-fast-") as tmp:
        jobs = max(1, min(jobs, len(todo)))
        trees = [make_tree(Path(tmp) / f"tree{j}", root) for j in range(jobs)]
        paths = sorted({m.path for m in todo})
        spans = {p: _stmt_spans((trees[0] / p).read_text()) for p in paths}
        maps: dict[str, dict[str, Any]] = {}
        mods = list(dict.fromkeys(m.module for m in todo))

        own = {mod: sorted({m.path for m in todo if m.module == mod}) for mod in mods}

        def mapper(j: int) -> None:  # every map before any mutant, ``jobs`` at a time
            for mod in mods[j::jobs]:  # traced: only the module's own file (cheaper)
                maps[mod] = build_map(trees[j], mod, cache, own[mod])
                print(f"fast: map of {mod}: {len(maps[mod]['tests'])} tests, "
                      f"{maps[mod].get('seconds')} s", flush=True)  # fmt: skip

        if not only:
            with ThreadPoolExecutor(jobs) as pool:
                list(pool.map(mapper, range(jobs)))

        def worker(j: int) -> None:
            server = Server(trees[j])
            try:
                for mu in todo[j::jobs]:
                    if mu.id in _logged(log):  # another process sharing the log ran it
                        continue
                    res = run_one(server, mu, maps.get(mu.module, {}), spans[mu.path], full,
                                  only)  # fmt: skip
                    with lock:
                        done[mu.id] = res
                        count[0] += 1
                        with log.open("a") as fh:
                            fh.write(json.dumps(asdict(res)) + "\n")
                        print(f"  [{count[0]}/{len(todo)}] {res.outcome:8} {mu.module}:"
                              f"{mu.line} {mu.id} {res.tests} tests {res.seconds} s",
                              flush=True)  # fmt: skip
            finally:
                server.close()

        with ThreadPoolExecutor(jobs) as pool:
            list(pool.map(worker, range(jobs)))
    return [done[m.id] for m in mutants if m.id in done]


OUTCOMES = ("killed", "timeout", "survived", "invalid", "error")


def report(
    results: list[FastResult],
    equivalent: set[str] = frozenset(),  # type: ignore[assignment]
    later: set[str] = frozenset(),
) -> str:  # type: ignore[assignment]
    """The per-module table of a log. ``later``: ids of survivors that a test added after the
    run kills (confirmed with ``--with-test``, its own log): counted as **killed by a new
    test**. Kill rate = every kill / (run - equivalent - invalid - error)."""
    rows: dict[str, dict[str, float]] = {}
    for r in results:
        for key in (r.module, "all"):
            empty = {**dict.fromkeys(OUTCOMES, 0), "equivalent": 0, "new test": 0, "s": 0.0,
                     "n": 0}  # fmt: skip
            row = rows.setdefault(key, empty)
            o = r.outcome
            if o == "survived" and r.id in equivalent:
                o = "equivalent"
            elif o == "survived" and r.id in later:
                o = "new test"
            row[o] += 1
            row["s"] += r.seconds
            row["n"] += 1
    rows["all"] = rows.pop("all")
    out = ["| module | run | killed | by timeout | killed by a new test | survived | equivalent "
           "| invalid | error | kill rate (equivalents excluded) | s / mutant |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]  # fmt: skip
    for mod, row in rows.items():
        kills = row["killed"] + row["timeout"] + row["new test"]
        valid = kills + row["survived"]
        rate = f"{100 * kills / valid:.1f} %" if valid else "-"
        out.append(f"| {mod} | {row['n']:.0f} | {row['killed']:.0f} | {row['timeout']:.0f} | "
                   f"{row['new test']:.0f} | {row['survived']:.0f} | {row['equivalent']:.0f} | "
                   f"{row['invalid']:.0f} | {row['error']:.0f} | {rate} | "
                   f"{row['s'] / max(row['n'], 1):.1f} |")  # fmt: skip
    return "\n".join(out)


def read_log(path: Path) -> list[FastResult]:
    if not path.exists():
        return []
    return [FastResult(**json.loads(ln)) for ln in path.read_text().splitlines() if ln.strip()]


def read_ids(path: Path) -> list[str]:
    """The ids of a frozen sample file: one per line (``id module``), ``#`` comments."""
    out = []
    for ln in path.read_text().splitlines():
        ln = ln.split("#", 1)[0].strip()
        if ln:
            out.append(ln.split()[0])
    return out


def print_report(log: Path, confirm: Path | None) -> int:
    """The table of ``log``, then every mutant not killed with its judgement: equivalent (the
    reason), killed by a new test (``confirm``, a ``--with-test`` log) or OPEN."""
    res = read_log(log)
    later = {r.id: r for r in read_log(confirm) if r.outcome in ("killed", "timeout")} \
        if confirm else {}  # fmt: skip
    print(report(res, set(EQUIVALENT), set(later)))
    for r in res:
        if r.outcome in ("killed", "timeout"):
            continue
        why = EQUIVALENT.get(r.id, r.detail) if r.outcome == "survived" else r.detail
        if r.id in later:
            why = f"killed by a new test: {later[r.id].detail}"
        elif r.outcome == "survived" and r.id not in EQUIVALENT:
            why = f"OPEN ({r.detail})"
        print(f"- `{r.id}` {r.module}:{r.line} {r.operator} `{r.original.strip()}` -> "
              f"`{r.mutated.strip()}`: {why}")  # fmt: skip
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="cheap generated-mutant runs (see module doc)")
    ap.add_argument("--sample", type=int, default=0, help="about N mutants, stratified")
    ap.add_argument("--floor", type=int, default=12, help="at least this many per module")
    ap.add_argument("--seed", type=int, default=26)
    ap.add_argument("--module", action="append", default=[])
    ap.add_argument("--id", action="append", default=[])
    ap.add_argument("--all", action="store_true", help="every generated mutant")
    ap.add_argument("--full", action="store_true", help="every test of the module, no map")
    ap.add_argument("--log", type=Path, default=ROOT / "out" / "mutation_fast.jsonl")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "mutation_map")
    ap.add_argument("--jobs", type=int, default=1, help="mutants run in parallel")
    ap.add_argument(
        "--reverse",
        action="store_true",
        help="from the end of the sample (a second process sharing --log)",
    )
    ap.add_argument(
        "--ids-file", type=Path, help="a frozen sample: these ids (one per line), in this order"
    )
    ap.add_argument(
        "--with-test",
        action="append",
        default=[],
        help="run only this test (node id) against each chosen mutant, no map: "
        "confirms that a new test kills a survivor",
    )
    ap.add_argument("--report", type=Path, help="only print the table of this log")
    ap.add_argument(
        "--confirm",
        type=Path,
        help="with --report: the --with-test log of survivors a new test kills",
    )
    ap.add_argument("--list", action="store_true", help="only list the chosen mutants")
    args = ap.parse_args(argv)
    if args.report:
        return print_report(args.report, args.confirm)
    gen = generate(list(iter_targets(args.module)))
    if args.ids_file:
        want = read_ids(args.ids_file)
        have = {m.id: m for m in gen}
        gone = [i for i in want if i not in have and not args.module]
        if gone:  # its line changed since the sample was drawn: that mutant no longer exists
            print(f"fast: {len(gone)} id(s) of {args.ids_file} no longer exist: {gone}")
        gen = [have[i] for i in want if i in have]
    if args.id:
        gen = [m for m in gen if m.id in args.id]
    elif not args.all and not args.ids_file:
        gen = stratified(gen, args.sample, args.seed, args.floor)
    if args.reverse:
        gen = gen[::-1]
    if args.list:
        for m in gen:
            print(f"{m.id} {m.module}:{m.line} {m.operator}  {m.why}")
        return 0
    results = run_many(gen, args.log.resolve(), args.cache.resolve(), args.full, args.jobs,
                       only=args.with_test or None)  # fmt: skip
    print(report(results, set(EQUIVALENT)))
    alive = [r for r in results if r.outcome == "survived" and r.id not in EQUIVALENT]
    return 0 if not alive else 1


if __name__ == "__main__":
    raise SystemExit(main())
