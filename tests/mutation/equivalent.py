"""Generated mutants judged **equivalent** (issue #26 item 4): no input a caller can give tells
them from the original, so no behavioural test can kill them. Each entry: the mutant's id
(``python -m tests.mutation.generate`` lists them) and why. Reports count these apart and leave
them out of the kill rate; docs/mutation.md lists them with the survivors. An id that no longer
exists (the code changed) is simply unused.
"""

from __future__ import annotations

EQUIVALENT: dict[str, str] = {
    "af2faa7284": "protection dt_ms: `if not (x > 0.0): return 0, 1` -> pass. The only caller "
    "(step_pack) passes a finite dt >= 0; at x = 0 the fall-through halves n = 0 down to e = 0 "
    "and returns (0 << 0, 1) = (0, 1), the same.",
}
