"""The dashboard's state-of-power panel and join view (issue #28 §3, §4): what the pack can
still give for 2 / 10 / 30 s and what closing a waiting battery's switch would cause, from the
state the core had at the step on show.

The figures are ``sim/power_view.py:power_summary``, the function the runtime publishes its
CCL/DCL and 0x231 frame from and the run report draws: same inputs (the core's SOC and its
source, the observer's polarisation and R0 where trusted, the measurements, the switch states,
the limits layer's limits), same prediction. They are not status channels of the core: the
prediction runs at the edge, as in the publisher.

A prediction costs a few milliseconds, and its kernels compile on first use (about 16 s cold,
then cached), so a live page never waits for one: :meth:`PowerPanel.latest` returns the last
result at once and, when it is stale, computes the next in a thread of its own (at most one at
a time, at most every ``min_interval_s`` of wall time). A recording's scrubbed moment is
computed on demand (:meth:`PowerPanel.compute`, off the event loop).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from packpilot.contract.record import StepSample
from packpilot.errors import PackPilotError

MIN_INTERVAL_S = 0.5
"""Wall seconds between two predictions of a live run (the page polls 5 times a second)."""


class PowerPanel:
    """The state of power of one run's steps (its config parsed once)."""

    def __init__(
        self,
        config: Mapping[str, Any] | None,
        names: Sequence[str],
        roles: Sequence[str],
        min_interval_s: float = MIN_INTERVAL_S,
        on_done: Callable[[], None] | None = None,
    ) -> None:
        self.cols = [b for b, r in enumerate(roles) if r != "aux"] if roles else []
        self.names = [names[b] for b in self.cols if b < len(names)]
        self.min_interval_s = min_interval_s
        self.on_done = on_done
        """Called when a background prediction lands (the run's readers then push it)."""
        self.note: str | None = None
        """Why there is no panel (no config, a config that does not read back)."""
        self._cfg: Any = None
        self._prm: Any = None
        self._lock = threading.Lock()
        self._result: dict[str, Any] | None = None
        self._step: int | None = None
        self._busy = False
        self._last_wall = -math.inf
        self._setup(config)

    def _setup(self, config: Mapping[str, Any] | None) -> None:
        if not config:
            self.note = "no scenario: nothing to predict"
            return
        from packpilot.config.scenario import parse_config
        from packpilot.sim.power import params_of

        try:
            self._cfg = parse_config(dict(config), "run config")
            self._prm = params_of(self._cfg)
        except (PackPilotError, ValueError, OSError) as err:
            self.note = f"no state of power: {err}"
            self._cfg = None

    @property
    def available(self) -> bool:
        return self._cfg is not None and len(self.cols) == int(self._prm.series.shape[0])

    def compute(self, s: StepSample) -> dict[str, Any] | None:
        """The panel for step ``s`` (synchronous; a few ms once the kernels are compiled)."""
        if not self.available:
            return None
        from packpilot.sim.power_view import power_summary, view_of_status

        def status(name: str, b: int) -> object:
            vals = s.status.get(name)
            return vals[b] if vals is not None and b < len(vals) else None

        mode = s.status.get("mode")
        view = view_of_status(
            s.battery, status, self.cols, bus_v=s.bus_v, load_a=s.load_a,
            mode=next((m for m in mode if m is not None), None) if mode else None,
        )  # fmt: skip
        try:
            out = power_summary(self._cfg, self._prm, view, self.names)
        except PackPilotError as err:  # a state the prediction refuses: say so, do not crash
            return {"t_s": s.t_s, "step": s.step, "error": str(err)}
        if out is None:
            return {"t_s": s.t_s, "step": s.step, "error": "no battery to predict"}
        return {"t_s": s.t_s, "step": s.step, **out}

    def latest(self, s: StepSample | None, final: bool = False) -> dict[str, Any] | None:
        """The last panel computed (None before the first), and a new one started in the
        background when ``s`` is a newer step and the last is ``min_interval_s`` old (at
        once when ``final``: the run has ended and its last step must be the one shown)."""
        if s is None or not self.available:
            return self._result
        with self._lock:
            now = time.monotonic()
            due = final or now - self._last_wall >= self.min_interval_s
            if self._busy or s.step == self._step or not due:
                return self._result
            self._busy, self._last_wall = True, now
            threading.Thread(target=self._run, args=(s,), name="packpilot-power",
                             daemon=True).start()  # fmt: skip
            return self._result

    def _run(self, s: StepSample) -> None:
        try:
            out = self.compute(s)
        except Exception as err:  # shown on the page; the dashboard keeps serving
            out = {"t_s": s.t_s, "step": s.step, "error": f"{type(err).__name__}: {err}"}
        with self._lock:
            self._result, self._step, self._busy = out, s.step, False
        if self.on_done is not None:
            self.on_done()

    def wait(self, timeout_s: float = 60.0) -> dict[str, Any] | None:
        """Block until no prediction is running (tests, and a finished run's last step)."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self._lock:
                if not self._busy:
                    return self._result
            time.sleep(0.01)
        return self._result


__all__ = ["MIN_INTERVAL_S", "PowerPanel"]
