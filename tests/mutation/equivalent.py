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
    "8e12b7adb7": "can _delay: `not (isfinite(now) and ts and isfinite(ts))` -> `... or ...`. "
    "Differs only when the wall clock is finite and the timestamp missing (python-can's 0.0; "
    "never None): then d = now - 0 = time.time() >= 1e6 s and the range check `0 < d < 1e6` "
    "returns 0 as the original does; NaN timestamps give d = NaN, also 0. The two guards "
    "overlap for the only wall clock the plant is given (time.time).",
    "88d28141f5": "can _judge_sequence: `gap >= RESYNC_PERIODS * period_s - 1e-9` -> `>`. The "
    "two differ only when the gap equals RESYNC_PERIODS * period_s - 1e-9 exactly; the 1e-9 is "
    "there so a gap of exactly RESYNC_PERIODS periods (up to float noise) resyncs, which both "
    "do. No frame timestamp difference lands on that one float.",
    "606071d32c": "protection dt_ms: `den <= MAX_DEN_MS` -> `<`: den = 1 << e is a power of two "
    "and MAX_DEN_MS = 1000 is not, so den never equals it.",
    "05f3e364b4": "plausibility `NONE = -1` -> `-2`: a finding state used only by name inside "
    "rules.py (returned by the judge helpers, compared `state == NONE`), never stored in a "
    "status, an event or any array another module reads; OK = 0 and BAD = 1 stay distinct.",
    "4d03f98d8c": "equalization step: `dt_s > 0.0` -> `>= 0.0` in `dt = dt_s if ... else 0.0`: "
    "at dt_s = 0 both give 0 (a -0.0 only ever added to timers: the same sums).",
}
