"""Hypothesis budgets that a profile can raise (#18 §2).

A budget written as ``@settings(max_examples=60)`` is fixed: no profile can raise it, so a
nightly soak ran the CI budget. Properties instead take ``@budget(n)``: ``n`` examples under
the ``ci`` profile (the default, what ``make test`` runs), ``max(n * NIGHTLY_FACTOR, 10,000)``
under ``nightly`` (``make soak``) and ``max(n // 10, 5)`` under ``dev`` (a quick edit loop).
The profile is chosen by the environment variable ``HYPOTHESIS_PROFILE``; every profile has no
deadline (a closed loop's first example includes a kernel compile).
"""

from __future__ import annotations

import os
from typing import Any

from hypothesis import HealthCheck, settings

PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
CI_MIN = 200
"""The issue's CI floor for a cheap property (a closed loop may take less; it says why)."""
NIGHTLY_MIN = 10_000
NIGHTLY_FACTOR = 50

settings.register_profile("ci", max_examples=CI_MIN, deadline=None)
settings.register_profile(
    "nightly",
    max_examples=NIGHTLY_MIN,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    print_blob=True,
)
settings.register_profile("dev", max_examples=20, deadline=None)
# mutation runs (tests/mutation/fast.py): the CI budget, but the same examples every run and no
# example database, so a mutant is killed or survives reproducibly and the map of which test
# reaches which line (built once) holds for every mutant run
settings.register_profile(
    "mutate", max_examples=CI_MIN, deadline=None, derandomize=True, database=None
)
if PROFILE not in ("ci", "nightly", "dev", "mutate"):
    raise SystemExit(f"HYPOTHESIS_PROFILE={PROFILE!r}: expected ci, nightly, dev or mutate")
settings.load_profile(PROFILE)


def scaled(n: int, profile: str = PROFILE) -> int:
    """The number of examples a property of CI budget ``n`` gets under ``profile``."""
    if profile == "nightly":
        return max(n * NIGHTLY_FACTOR, NIGHTLY_MIN)
    if profile == "dev":
        return max(n // 10, 5)
    return n


def budget(n: int, **kw: Any) -> settings:
    """``settings`` with ``scaled(n)`` examples and no deadline (other settings pass through)."""
    kw.setdefault("deadline", None)
    if PROFILE == "nightly":
        kw.pop("derandomize", None)  # a soak should explore new examples every night
    return settings(max_examples=scaled(n), **kw)
