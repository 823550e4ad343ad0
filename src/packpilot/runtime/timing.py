"""Loop timing of the runtime: period, jitter, overruns, worst step.

Per period: *jitter* is how late the period started against its deadline (``start - due``),
*work* how long the step took. An *overrun* is a step that ended after the next deadline; the
loop then skips the deadlines it missed (it never bursts to catch up) and counts them.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class LoopTiming:
    """Deadlines and per-period timings of a fixed-period loop (bounded memory)."""

    def __init__(self, period_s: float, keep: int = 1 << 20) -> None:
        self.period_s = period_s
        self.keep = keep
        self.jitter_s: list[float] = []
        self.work_s: list[float] = []
        self.overruns = 0
        self.missed = 0
        self.worst_step = -1
        self.worst_work_s = -1.0
        self.n = 0

    def add(self, due: float, start: float, end: float) -> float:
        """Record one period; returns the next deadline."""
        if len(self.jitter_s) < self.keep:
            self.jitter_s.append(start - due)
            self.work_s.append(end - start)
        if end - start > self.worst_work_s:
            self.worst_work_s, self.worst_step = end - start, self.n
        self.n += 1
        nxt = due + self.period_s
        if end > nxt:
            self.overruns += 1
            skipped = int((end - nxt) // self.period_s) + 1
            self.missed += skipped
            nxt += skipped * self.period_s
        return nxt

    def summary(self) -> dict[str, Any]:
        if not self.work_s:
            return {"period_s": self.period_s, "periods": 0}
        j = np.asarray(self.jitter_s) * 1e3
        w = np.asarray(self.work_s) * 1e3
        return {
            "period_s": self.period_s,
            "periods": self.n,
            "jitter_p50_ms": float(np.percentile(j, 50)),
            "jitter_p99_ms": float(np.percentile(j, 99)),
            "jitter_max_ms": float(j.max()),
            "step_p50_ms": float(np.percentile(w, 50)),
            "step_p99_ms": float(np.percentile(w, 99)),
            "step_max_ms": float(w.max()),
            "worst_step": self.worst_step,
            "overruns": self.overruns,
            "missed_periods": self.missed,
        }


__all__ = ["LoopTiming"]
