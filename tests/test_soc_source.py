"""Which SOC is shown and where it comes from (issue #28): the one rule
(``contract/soc_source.py``) every view applies to the SOC method's status channels, scalar
and over a run, agree on every combination of present / absent / NaN channels."""

from __future__ import annotations

import itertools
import math

import numpy as np

from packpilot.contract.soc_source import (
    BATTERY,
    COUNTER,
    FALLBACK,
    OBSERVER,
    SOURCES,
    shown_soc,
    soc_source,
    source_codes,
)


def test_the_observer_only_while_trusted_then_its_fallback() -> None:
    assert soc_source(0.61, True, 0.01) == OBSERVER
    assert soc_source(0.61, 1.0, 0.01) == OBSERVER
    # the observer runs (it has a deviation) but is not trusted: settling, or diverged
    assert soc_source(0.58, False, 0.04) == FALLBACK
    assert soc_source(0.58, 0.0, 0.04) == FALLBACK
    # [soc] without the observer (observer = false, or no cell tables): no deviation
    assert soc_source(0.58, False, math.nan) == COUNTER
    assert soc_source(0.58, None, None) == COUNTER
    # no estimator at all: the battery's own report is what there is
    assert soc_source(None, None, None) == BATTERY
    assert soc_source(math.nan, True, 0.01) == BATTERY
    assert shown_soc(0.58, False, 0.04, 0.70) == (0.58, FALLBACK)
    assert shown_soc(None, None, None, 0.70) == (0.70, BATTERY)
    # a bool is not a number: True as an estimate is no estimate
    assert soc_source(True, True, 0.01) == BATTERY


def test_the_run_wide_codes_are_the_same_rule() -> None:
    values = {
        "est": [0.5, math.nan],
        "ok": [1.0, 0.0, math.nan],
        "sigma": [0.02, math.nan],
    }
    combos = list(itertools.product(values["est"], values["ok"], values["sigma"]))
    est, ok, sigma = (np.array(c, np.float64) for c in zip(*combos, strict=True))
    codes = source_codes(est, ok, sigma)
    want = [SOURCES.index(soc_source(e, o if o == o else None, s)) for e, o, s in combos]
    assert codes.tolist() == want
    assert set(codes.tolist()) == set(range(len(SOURCES)))  # every source reached
