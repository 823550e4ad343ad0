"""The mutant generator and runner of issue #26 item 4 (tests/mutation/generate.py, run.py),
on a tiny fixture module: no numba, no project kernels, a few seconds."""

from __future__ import annotations

import ast
import shutil
import textwrap
from pathlib import Path

import pytest

from tests.mutation import fast, run
from tests.mutation.generate import (
    GenMutant,
    Target,
    compiles,
    generate,
    mutants_of_source,
    sample,
)
from tests.mutation.mutants import TESTS

TINY = textwrap.dedent('''\
    """A tiny rules module: one of each operator."""

    SCALE = 2.0
    assert SCALE > 1.0  # import-time check: its mutant makes the module fail to import


    def over(x: float, hi: float) -> bool:
        """True strictly above ``hi``."""
        if x > hi:
            return True
        return False


    def band(x: float, lo: float, hi: float, on: bool) -> float:
        if lo <= x and not on:
            x = x + lo * SCALE
        if x >= hi or x == lo:
            x -= 1
        return min(x, max(lo, hi / 2))


    def walk(n: int) -> int:
        k = 0
        while k < n:
            k += 1
            if k == 3:
                continue
        return k
''')

TINY_TESTS = textwrap.dedent("""\
    from tiny import over, walk


    def test_over() -> None:
        assert over(5.0, 3.0)
        assert not over(1.0, 3.0)  # never exactly at hi: '>' -> '>=' survives


    def test_walk() -> None:
        assert walk(5) == 5
""")


def _muts() -> list[GenMutant]:
    return mutants_of_source(TINY, "tiny", "src/tiny.py")


def _one(op: str, line_has: str, new_has: str) -> GenMutant:
    found = [m for m in _muts() if m.operator.startswith(op) and line_has in m.original
             and new_has in m.mutated]  # fmt: skip
    assert len(found) == 1, (op, line_has, new_has, [m.name for m in found])
    return found[0]


@pytest.mark.parametrize(
    ("op", "line_has", "new_line"),
    [
        ("cmp:>->>=", "if x > hi:", "if x >= hi:"),
        ("cmp:>-><", "if x > hi:", "if x < hi:"),
        ("cmp:<=-><", "if lo <= x and", "if lo < x and not on:"),
        ("cmp:>=->>", "if x >= hi", "if x > hi or x == lo:"),
        ("cmp:==->!=", "x == lo", "if x >= hi or x != lo:"),
        ("cmp:<-><=", "while k < n", "while k <= n:"),
        ("boolop:and->or", "lo <= x and", "if lo <= x or not on:"),
        ("boolop:or->and", "x >= hi or", "if x >= hi and x == lo:"),
        ("not:not->", "not on", "if lo <= x and on:"),
        ("bool:True->False", "return True", "return False"),
        ("num:2.0->2.2", "SCALE = 2.0", "SCALE = 2.2"),
        ("num:0->1", "k = 0", "k = 1"),
        ("num:3->4", "k == 3", "if k == 4:"),
        ("arith:+->-", "x = x + lo", "x = x - lo * SCALE"),
        ("arith:*->/", "lo * SCALE", "x = x + lo / SCALE"),
        ("arith:-->+", "x -= 1", "x += 1"),
        ("arith:/->*", "hi / 2", "return min(x, max(lo, hi * 2))"),
        ("minmax:min->max", "return min(", "return max(x, max(lo, hi / 2))"),
        ("minmax:max->min", "return min(", "return min(x, min(lo, hi / 2))"),
        ("stmt-del", "x = x + lo", "pass"),
        ("stmt-del", "x -= 1", "pass"),
        ("exit-del", "return True", "pass"),
        ("exit-del", "continue", "pass"),
    ],
)
def test_each_operator_changes_exactly_its_place(op: str, line_has: str, new_line: str) -> None:
    mu = _one(op, line_has, new_line)
    assert mu.mutated.strip() == new_line
    out = mu.apply(TINY)
    ast.parse(out)  # a valid module
    old_lines, new_lines = TINY.splitlines(), out.splitlines()
    assert len(old_lines) == len(new_lines)
    changed = [k + 1 for k, (a, b) in enumerate(zip(old_lines, new_lines, strict=True)) if a != b]
    assert changed == [mu.line]  # that line and no other
    assert old_lines[mu.line - 1] == mu.original


def test_docstrings_annotations_and_indices_are_not_mutated() -> None:
    src = 'def f(a: "int" = 1) -> bool:\n    """Doc 0."""\n    return a[0] > 2\n'
    kinds = sorted(m.operator for m in mutants_of_source(src, "m", "m.py"))
    assert kinds == ["cmp:>-><", "cmp:>->>=", "num:1->2", "num:2->3"]  # not a[0], not the doc


def test_ids_are_unique_and_survive_an_edit_elsewhere() -> None:
    ids = [m.id for m in _muts()]
    assert len(set(ids)) == len(ids)
    edited = TINY.replace('"""A tiny', '"""Edited: a tiny\n\nrules."""\n"""A tiny', 1)
    again = mutants_of_source(edited, "tiny", "src/tiny.py")
    assert sorted(m.id for m in again) == sorted(ids)
    assert {m.line for m in again} != {m.line for m in _muts()}  # the lines did move


def test_sampling_is_deterministic_for_a_seed() -> None:
    muts = _muts()
    a = [m.id for m in sample(muts, 7, seed=3)]
    assert a == [m.id for m in sample(list(reversed(muts)), 7, seed=3)]
    assert a != [m.id for m in sample(muts, 7, seed=4)]
    assert len(set(a)) == 7
    assert [m.id for m in sample(muts, 10_000, seed=3)] == sorted(m.id for m in muts)


def test_every_rules_module_yields_compiling_mutants() -> None:
    muts = generate()
    assert {m.module for m in muts} >= {"limits", "plausibility", "charging", "protection",
                                        "sequencing", "supervisor", "soc", "equalization",
                                        "commands", "battery", "can"}  # fmt: skip
    assert all(m.module in TESTS for m in muts)
    sources = {m.path: (run.ROOT / m.path).read_text() for m in muts}
    assert all(compiles(m, sources[m.path]) for m in sample(muts, 40, seed=0))  # ~1 s each


def test_a_function_filter_keeps_mutants_inside_those_functions() -> None:
    path = "src/packpilot/io/can/plant.py"
    tree = ast.parse((run.ROOT / path).read_text())
    fn = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == "_present")
    assert fn.end_lineno is not None
    can = generate([Target("can", path, ("_present",))])
    assert len(can) > 5
    assert all(fn.lineno < m.line <= fn.end_lineno for m in can)


@pytest.fixture
def tiny_tree(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    (tmp_path / "src").mkdir()
    (tmp_path / "src" / "tiny.py").write_text(TINY)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_tiny.py").write_text(TINY_TESTS)
    monkeypatch.setitem(TESTS, "tiny", ["tests/test_tiny.py"])
    return tmp_path


def test_runner_classifies_killed_survived_invalid_and_timeout(tiny_tree: Path) -> None:
    base, _ = run.baseline(tiny_tree, ["tiny"])
    assert base == []
    killed = run.run_mutant(tiny_tree, _one("cmp:>-><", "if x > hi:", "x < hi"), 60)
    survived = run.run_mutant(tiny_tree, _one("cmp:>->>=", "if x > hi:", "x >= hi"), 60)
    no_import = run.run_mutant(tiny_tree, _one("cmp:>-><", "SCALE > 1.0", "SCALE < 1.0"), 60)
    hang = run.run_mutant(tiny_tree, _one("arith:+->-", "k += 1", "k -= 1"), 4)
    ok = _one("bool", "return True", "False")
    broken = GenMutant(**{**ok.__dict__, "new": "(", "mutated": "return ("})
    bad = run.run_mutant(tiny_tree, broken, 60)
    assert (killed.outcome, survived.outcome) == ("killed", "survived")
    assert no_import.outcome == "invalid"  # the module does not import: not a kill
    assert hang.outcome == "timeout"
    assert (bad.outcome, bad.detail) == ("invalid", "does not compile")
    assert (tiny_tree / "src" / "tiny.py").read_text() == TINY  # restored every time
    rows = run.gen_summary([killed, survived, no_import, hang, bad])["tiny"]
    assert rows == {"killed": 1, "timeout": 1, "survived": 1, "equivalent": 0, "invalid": 2,
                    "error": 0}  # fmt: skip
    assert run.kill_rate(rows) == pytest.approx(200.0 / 3)
    assert survived.id in run.gen_table([survived], "x")


@pytest.mark.long(cpu_s=35)
def test_fast_runs_a_mutant_against_only_the_tests_that_reach_it(
    tiny_tree: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The map, the selection and the fork server (fast.py) on the tiny module: a mutant of a
    function no test calls survives without a run; the others end as with the plain runner."""
    (tiny_tree / "tests" / "__init__.py").touch()
    (tiny_tree / "tests" / "mutation").mkdir()
    (tiny_tree / "tests" / "mutation" / "__init__.py").touch()
    for name in ("cover_plugin.py", "forkserver.py"):
        shutil.copy(run.ROOT / "tests" / "mutation" / name, tiny_tree / "tests" / "mutation")
    monkeypatch.setattr(fast, "TIMEOUT_MIN_S", 15.0)  # a loaded box: pytest starts slowly
    monkeypatch.setattr(fast, "RETRY_FACTOR", 1.0)
    monkeypatch.setattr(fast, "TIMEOUT_PAD_S", 0.0)
    chosen = {
        "killed": _one("cmp:>-><", "if x > hi:", "x < hi"),
        "survived": _one("cmp:>->>=", "if x > hi:", "x >= hi"),
        "unreached": _one("minmax", "return min(", "return max("),
        "invalid": _one("cmp:>-><", "SCALE > 1.0", "SCALE < 1.0"),
        "timeout": _one("arith:+->-", "k += 1", "k -= 1"),
    }
    log = tmp_path / "log.jsonl"
    got = fast.run_many(list(chosen.values()), log, tmp_path / "map", root=tiny_tree)
    by = {r.id: r for r in got}
    outcome = {k: by[m.id].outcome for k, m in chosen.items()}
    assert outcome == {"killed": "killed", "survived": "survived", "unreached": "survived",
                       "invalid": "invalid", "timeout": "timeout"}  # fmt: skip
    assert by[chosen["unreached"].id].tests == 0  # band() is called by no test: no run
    assert by[chosen["killed"].id].tests == 1  # only test_over reaches `if x > hi`
    assert "test_over" in by[chosen["killed"].id].detail
    assert (tiny_tree / "src" / "tiny.py").read_text() == TINY  # the fixture itself untouched
    assert len(log.read_text().splitlines()) == 5  # one line per mutant, as each ends
    again = fast.run_many(list(chosen.values()), log, tmp_path / "map", root=tiny_tree)
    assert [r.outcome for r in again] == [r.outcome for r in got]  # resumed from the log
    assert len(list((tmp_path / "map").glob("tiny-*.json"))) == 1  # the map built once


def test_a_stratified_sample_holds_every_module_and_is_reproducible() -> None:
    gen = generate()
    a = fast.stratified(gen, 400, 26, 12)
    assert [m.id for m in a] == [m.id for m in fast.stratified(gen, 400, 26, 12)]
    per = {mod: sum(m.module == mod for m in a) for mod in {m.module for m in gen}}
    assert min(per.values()) >= 12 and 400 <= len(a) <= 440
    assert [m.id for m in a] != [m.id for m in fast.stratified(gen, 400, 27, 12)]


def test_a_partial_map_selects_its_property_tests_for_every_mutant() -> None:
    """A map traced under a smaller Hypothesis budget (fast.MAP_PROFILE) marks its property
    tests ``partial``: they are selected for every mutant of the module, even one whose lines
    no traced test reached (their lines are only a lower bound); plain tests by their lines."""
    cmap = {
        "tests": {"t.py::plain": {"seconds": 1.0}, "t.py::prop": {"seconds": 5.0, "partial": True}},
        "lines": {"": {}, "t.py::plain": {"m.py": [3]}, "t.py::prop": {"m.py": [7]}},
    }
    assert fast.select_tests(cmap, "m.py", {3})[0] == ["t.py::plain", "t.py::prop"]
    assert fast.select_tests(cmap, "m.py", {9}) == (["t.py::prop"], 5.0 * fast.PARTIAL_FACTOR)
    del cmap["tests"]["t.py::prop"]["partial"]
    assert fast.select_tests(cmap, "m.py", {9})[0] == []
    assert "sequencing" in fast.MAP_PROFILE
