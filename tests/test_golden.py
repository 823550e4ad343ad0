"""Behaviour pinned: every example's trace, events and metrics hash as recorded.

A refactor keeps these hashes; a commit that changes one says which behaviour changed and why
and regenerates ``tests/golden/hashes.json`` (``python -m tests.golden.fingerprint --update``).
"""

from __future__ import annotations

import json

import pytest

from tests.golden.fingerprint import HASHES, example_names, fingerprint, run_example

GOLDEN = json.loads(HASHES.read_text())


def test_every_example_is_pinned() -> None:
    assert sorted(GOLDEN) == example_names()


@pytest.mark.parametrize("name", example_names())
def test_example_matches_its_golden_fingerprint(name: str) -> None:
    assert fingerprint(run_example(name)) == GOLDEN[name]
