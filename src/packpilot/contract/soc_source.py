"""Which SOC a person or a peer is shown, and where it comes from (issue #28).

The core's SOC is the SOC method's status channel ``soc_est``: the battery observer's estimate
while the observer runs and is trusted (``soc_observer_ok``), the coulomb counter with its OCV
correction at rest otherwise (the fallback; ``control/soc/rules.py:step_pack``). Without a
``[soc]`` section the core has no estimate, and what is shown is the battery's own report.
The dashboard, the run report, the plots and the CAN frames all show the SOC this one rule
picks, labelled by its source, so that nobody reads the battery's own figure believing it is
the estimate the core acts on.

How the source is told apart, from the status channels alone (so a recording says it too):
``soc_observer_ok`` true: the observer; else, while the observer keeps a state (its
``soc_sigma`` is finite, it runs but is settling or restarting after diverging): the fallback;
else a finite ``soc_est``: the coulomb counter alone (``[soc] observer = false``, or a cell set
without the tables the observer needs); else: the battery's own report.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

OBSERVER = "observer"
FALLBACK = "fallback"
COUNTER = "counter"
BATTERY = "battery"

SOURCES: tuple[str, ...] = (BATTERY, COUNTER, OBSERVER, FALLBACK)
"""The sources, in the order of their codes on the wire (``StateOfCharge.Source``, 0x232)."""

LABELS: dict[str, str] = {
    OBSERVER: "observer estimate",
    FALLBACK: "fallback: coulomb counter (observer not trusted)",
    COUNTER: "coulomb counter + OCV at rest (no observer)",
    BATTERY: "the battery's own report (no SOC estimator)",
}
"""What a page says the SOC it shows is."""


def _num(x: object) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


def soc_source(est: object, ok: object, sigma: object) -> str:
    """The source of the SOC the core uses, from one battery's ``soc_est``,
    ``soc_observer_ok`` and ``soc_sigma`` (any of them None / NaN / absent)."""
    if not math.isfinite(_num(est)):
        return BATTERY
    if ok is True or (not isinstance(ok, bool) and _num(ok) == 1.0):
        return OBSERVER
    if math.isfinite(_num(sigma)):
        return FALLBACK
    return COUNTER


def shown_soc(est: object, ok: object, sigma: object, reported: object) -> tuple[float, str]:
    """(SOC 0..1, source): the core's estimate where it has one, else the battery's own."""
    source = soc_source(est, ok, sigma)
    return (_num(reported) if source == BATTERY else _num(est)), source


def source_codes(
    est: NDArray[np.float64], ok: NDArray[np.float64], sigma: NDArray[np.float64]
) -> NDArray[np.int64]:
    """:func:`soc_source` over a run (NaN for absent values; ``ok`` 1.0 = trusted), as
    indices into :data:`SOURCES`."""
    with np.errstate(invalid="ignore"):
        code = np.where(np.isfinite(sigma), SOURCES.index(FALLBACK), SOURCES.index(COUNTER))
        code = np.where(ok == 1.0, SOURCES.index(OBSERVER), code)
        code = np.where(np.isfinite(est), code, SOURCES.index(BATTERY))
    return np.asarray(code, np.int64)


__all__ = [
    "BATTERY",
    "COUNTER",
    "FALLBACK",
    "LABELS",
    "OBSERVER",
    "SOURCES",
    "shown_soc",
    "soc_source",
    "source_codes",
]
