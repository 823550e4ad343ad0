"""Tool-generated mutants of the rules modules (issue #26 item 4): every place where a small,
classic mutation operator applies, found by walking the module's syntax tree.

Why our own generator and not mutmut / cosmic-ray: the rules are numba kernels whose source
runs as plain Python only under ``NUMBA_DISABLE_JIT=1``, and the runner mutates a *private
copy* of the tree (``run.py``) so the worktree is never written. mutmut rewrites files in
place under its own ``mutants/`` layout and drives pytest itself; cosmic-ray needs a session
database and its own worker; neither knows which behavioural tests belong to a module (the
``TESTS`` map), and both would count an import error as a kill. A ~300-line ``ast`` walker
gives the same operators with ids that stay stable across unrelated edits. See
docs/mutation.md.

Each mutant is one textual splice of the original source (the rest of the file, comments
included, is byte-identical), so its snippet is readable and the mutated file is exactly
"the original with that one change".

    python -m tests.mutation.generate [--module limits] [--count]
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import random
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Target:
    """A module's source file and, optionally, the only functions in it worth mutating."""

    module: str
    """The key of ``TESTS`` (the behavioural tests that must kill its mutants)."""
    path: str
    functions: tuple[str, ...] = ()
    """Empty: the whole file; else only these (methods by bare name)."""


_RULES = ("limits", "plausibility", "charging", "protection", "sequencing", "supervisor", "soc",
          "equalization")  # fmt: skip
_CAN_RULES = ("judge", "_judge_sequence", "_delay", "_fresh", "_present", "_docked",
              "_dock_doubt", "explained")  # fmt: skip
TARGETS: list[Target] = [
    *(Target(m, f"src/packpilot/control/{m}/rules.py") for m in _RULES),
    Target("commands", "src/packpilot/control/commands.py"),
    Target("battery", "src/packpilot/control/battery.py"),
    Target("can", "src/packpilot/io/can/plant.py", _CAN_RULES),
]
"""Every rules module: the eight control methods' rules, the shared command helpers, the
battery facts, and the runtime's freshness / dock judgement (the rest of plant.py is codec
and I/O plumbing, covered by the CAN tests, not a rule)."""


@dataclass(frozen=True)
class GenMutant:
    """One splice: bytes ``[start, end)`` of ``path`` (which read ``old``) become ``new``."""

    module: str
    path: str
    line: int
    operator: str
    start: int
    end: int
    old: str
    new: str
    original: str
    """The whole source line(s) the splice touches, before ..."""
    mutated: str
    """... and after."""
    id: str = field(default="")

    @property
    def name(self) -> str:
        return f"{self.operator}@{self.line}#{self.id}"

    @property
    def why(self) -> str:
        return f"{self.original.strip()}  ->  {self.mutated.strip()}"

    def apply(self, source: str) -> str:
        """The mutated text of ``source``; ValueError when it no longer reads ``old`` there."""
        raw = source.encode()
        if raw[self.start : self.end].decode() != self.old:
            raise ValueError(f"stale generated mutant {self.name} in {self.path}")
        return (raw[: self.start] + self.new.encode() + raw[self.end :]).decode()


# --- operators -------------------------------------------------------------------------------

CMP_SWAPS: dict[type[ast.cmpop], list[tuple[str, str]]] = {
    ast.Lt: [("<", "<="), ("<", ">")],
    ast.LtE: [("<=", "<")],
    ast.Gt: [(">", ">="), (">", "<")],
    ast.GtE: [(">=", ">")],
    ast.Eq: [("==", "!=")],
    ast.NotEq: [("!=", "==")],
}
BIN_SWAPS: dict[type[ast.operator], tuple[str, str]] = {
    ast.Add: ("+", "-"),
    ast.Sub: ("-", "+"),
    ast.Mult: ("*", "/"),
    ast.Div: ("/", "*"),
}
OPERATORS = ("cmp", "boolop", "not", "bool", "num", "arith", "minmax", "stmt-del", "exit-del")
"""Operator names as they appear in a mutant's ``operator`` (``cmp:<->``, ``num:+1`` ...)."""

_Splice = tuple[str, int, int, str, str]
"""(operator, start, end, old, new) in byte offsets of the file."""


class _Finder(ast.NodeVisitor):
    """Collect the splices of every operator in one module's tree."""

    def __init__(self, raw: bytes, starts: list[int], functions: tuple[str, ...]) -> None:
        self.raw, self.starts, self.functions = raw, starts, functions
        self.out: list[_Splice] = []
        self.depth = 0  # > 0 inside a selected function
        self.in_function = 0
        self.no_num = 0  # > 0 inside a subscript index or an annotation

    # positions
    def pos(self, line: int, col: int) -> int:
        return self.starts[line - 1] + col

    def span(self, node: ast.AST) -> tuple[int, int]:
        return (self.pos(node.lineno, node.col_offset),  # type: ignore[attr-defined]
                self.pos(node.end_lineno, node.end_col_offset))  # type: ignore[attr-defined]  # fmt: skip

    def token(self, lo: int, hi: int, tok: str) -> int:
        """Offset of operator ``tok`` between two operands (outside brackets and comments)."""
        seg = self.raw[lo:hi].decode()
        k, depth = 0, 0
        while k < len(seg):
            ch = seg[k]
            if ch == "#":
                k = seg.find("\n", k)
                if k < 0:
                    break
                continue
            if ch in "([{":
                depth += 1
            elif ch in ")]}":
                depth = max(depth - 1, 0)  # a closing bracket of the left operand
            elif depth == 0 and seg.startswith(tok, k):
                after = seg[k + len(tok) : k + len(tok) + 1]
                if tok.isalpha() and after.isalnum():
                    k += 1
                    continue
                if not tok.isalpha() and after in "<>=" and after:
                    k += 1
                    continue
                return lo + len(seg[:k].encode())
            k += 1
        raise LookupError(tok)

    def add(self, op: str, start: int, end: int, new: str) -> None:
        self.out.append((op, start, end, self.raw[start:end].decode(), new))

    @property
    def live(self) -> bool:
        return self.depth > 0 or not self.functions

    # scopes
    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        chosen = not self.functions or node.name in self.functions
        self.depth += chosen
        self.in_function += 1
        self.no_num += 1
        for a in [*node.args.args, *node.args.kwonlyargs]:
            if a.annotation is not None:
                self.visit(a.annotation)
        if node.returns is not None:
            self.visit(node.returns)
        self.no_num -= 1
        for d in node.args.defaults:
            self.visit(d)
        body = node.body
        if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            body = body[1:]  # the docstring
        for stmt in body:
            self.visit(stmt)
        self.depth -= chosen
        self.in_function -= 1

    def visit_ClassDef(self, node: ast.ClassDef) -> None:
        for stmt in node.body:
            self.visit(stmt)

    def visit_AnnAssign(self, node: ast.AnnAssign) -> None:
        if self.depth and node.value is not None:  # a typed local; the annotation is no code
            self.visit(node.value)

    def visit_Subscript(self, node: ast.Subscript) -> None:
        self.visit(node.value)
        self.no_num += 1  # an index names an array slot: 0 -> 1 is a layout crash, not a rule
        self.visit(node.slice)
        self.no_num -= 1

    def visit_Expr(self, node: ast.Expr) -> None:
        if isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            return  # a docstring of an attribute
        self.generic_visit(node)

    def visit_Assign(self, node: ast.Assign) -> None:
        names = [t.id for t in node.targets if isinstance(t, ast.Name)]
        if "__all__" in names:
            return
        v = node.value
        if not self.in_function and isinstance(v, ast.Constant) and type(v.value) is int:
            return  # a module-level code or slot number (ST_SOC = 0): renumbering is no rule
        self.generic_visit(node)

    # operators
    def visit_Compare(self, node: ast.Compare) -> None:
        if self.live:
            left = node.left
            for op, right in zip(node.ops, node.comparators, strict=True):
                lo, hi = self.span(left)[1], self.span(right)[0]
                for old, new in CMP_SWAPS.get(type(op), []):
                    at = self.token(lo, hi, old)
                    self.add("cmp", at, at + len(old), new)
                left = right
        self.generic_visit(node)

    def visit_BoolOp(self, node: ast.BoolOp) -> None:
        if self.live:
            old, new = ("and", "or") if isinstance(node.op, ast.And) else ("or", "and")
            for a, b in zip(node.values, node.values[1:], strict=False):
                at = self.token(self.span(a)[1], self.span(b)[0], old)
                self.add("boolop", at, at + len(old), new)
        self.generic_visit(node)

    def visit_UnaryOp(self, node: ast.UnaryOp) -> None:
        if self.live and isinstance(node.op, ast.Not):
            lo = self.span(node)[0]
            word = self.raw[lo : lo + 3]
            if word == b"not":  # drop the keyword and its blanks, keep any brackets
                end = lo + 3
                while self.raw[end : end + 1] in (b" ", b"\t"):
                    end += 1
                self.add("not", lo, end, "")
        self.generic_visit(node)

    def visit_Constant(self, node: ast.Constant) -> None:
        if not self.live:
            return
        v = node.value
        lo, hi = self.span(node)
        if isinstance(v, bool):
            self.add("bool", lo, hi, str(not v))
        elif isinstance(v, int | float) and not self.no_num:
            if v == 0:
                self.add("num", lo, hi, "1" if isinstance(v, int) else "1.0")
            elif isinstance(v, int):
                self.add("num", lo, hi, str(v + 1))
            else:
                self.add("num", lo, hi, f"{v * 1.1:.6g}")

    def visit_BinOp(self, node: ast.BinOp) -> None:
        swap = BIN_SWAPS.get(type(node.op))
        if self.live and swap:
            at = self.token(self.span(node.left)[1], self.span(node.right)[0], swap[0])
            self.add("arith", at, at + 1, swap[1])
        self.generic_visit(node)

    def visit_AugAssign(self, node: ast.AugAssign) -> None:
        swap = BIN_SWAPS.get(type(node.op))
        if self.live and swap:
            at = self.token(self.span(node.target)[1], self.span(node.value)[0], swap[0] + "=")
            self.add("arith", at, at + 1, swap[1])
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        f = node.func
        if self.live and isinstance(f, ast.Name) and f.id in ("min", "max", "fmin", "fmax"):
            other = {"min": "max", "max": "min", "fmin": "fmax", "fmax": "fmin"}[f.id]
            self.add("minmax", *self.span(f), other)
        self.generic_visit(node)

    def visit_If(self, node: ast.If) -> None:
        if self.live:
            for stmt in [*node.body, *node.orelse]:
                if isinstance(stmt, ast.Assign | ast.AugAssign) or (
                    isinstance(stmt, ast.Expr) and isinstance(stmt.value, ast.Call)
                ):
                    self.add("stmt-del", *self.span(stmt), "pass")
                elif isinstance(stmt, ast.Return | ast.Continue | ast.Break):
                    self.add("exit-del", *self.span(stmt), "pass")
        self.generic_visit(node)


def _line_starts(raw: bytes) -> list[int]:
    starts, k = [0], 0
    while (k := raw.find(b"\n", k) + 1) > 0:
        starts.append(k)
    return starts


def mutants_of_source(source: str, module: str, path: str,
                      functions: tuple[str, ...] = ()) -> list[GenMutant]:  # fmt: skip
    """Every mutant of ``source``; the same text always gives the same list and ids."""
    raw = source.encode()
    starts = _line_starts(raw)
    finder = _Finder(raw, starts, functions)
    finder.visit(ast.parse(source))
    seen: dict[str, int] = {}
    out: list[GenMutant] = []
    for op, start, end, old, new in sorted(set(finder.out), key=lambda s: (s[1], s[2], s[4])):
        line = raw.count(b"\n", 0, start) + 1
        lo = starts[line - 1]
        last = raw.count(b"\n", 0, end)
        hi = starts[last + 1] - 1 if last + 1 < len(starts) else len(raw)
        original = raw[lo:hi].decode()
        mutated = (raw[lo:start] + new.encode() + raw[end:hi]).decode()
        # id: what changes and where inside its line(s), not the line number, so an edit
        # elsewhere in the file keeps every other mutant's id
        key = f"{path}|{op}|{original.strip()}|{start - lo}|{new}"
        n = seen.get(key, 0)
        seen[key] = n + 1
        ident = hashlib.sha1(f"{key}|{n}".encode()).hexdigest()[:10]
        out.append(GenMutant(module, path, line, f"{op}:{old.strip() or 'not'}->{new}",
                             start, end, old, new, original, mutated, ident))  # fmt: skip
    return out


def generate(targets: list[Target] | None = None, root: Path = ROOT) -> list[GenMutant]:
    """Every generated mutant of ``targets`` (default: every rules module)."""
    out: list[GenMutant] = []
    for t in TARGETS if targets is None else targets:
        src = (root / t.path).read_text(encoding="utf-8")
        out += mutants_of_source(src, t.module, t.path, t.functions)
    return out


def sample(mutants: list[GenMutant], n: int, seed: int) -> list[GenMutant]:
    """``n`` mutants drawn at random but reproducibly: the same seed and the same mutants (in
    any order) give the same sample, ordered by id."""
    pool = sorted(mutants, key=lambda m: m.id)
    if n >= len(pool):
        return pool
    return sorted(random.Random(seed).sample(pool, n), key=lambda m: m.id)


def compiles(mu: GenMutant, source: str) -> bool:
    """False when the mutated file is not even valid Python (an *invalid* mutant)."""
    try:
        compile(mu.apply(source), mu.path, "exec")
    except (SyntaxError, ValueError):
        return False
    return True


def iter_targets(modules: list[str]) -> Iterator[Target]:
    yield from (t for t in TARGETS if not modules or t.module in modules)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="list the generated mutants")
    ap.add_argument("--module", action="append", default=[])
    ap.add_argument("--count", action="store_true", help="only the number per module")
    args = ap.parse_args(argv)
    muts = generate(list(iter_targets(args.module)))
    if args.count:
        per: dict[str, int] = {}
        for m in muts:
            per[m.module] = per.get(m.module, 0) + 1
        for mod, n in per.items():
            print(f"{mod:14} {n}")
        print(f"{'all':14} {len(muts)}")
        return 0
    for m in muts:
        print(f"{m.id} {m.module}:{m.line} {m.operator}  {m.why}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
