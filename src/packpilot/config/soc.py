"""``[soc]``: the BMS's own state-of-charge estimate: the battery observer (an extended Kalman
filter on the cell's equivalent circuit, issue #28) with coulomb counting + OCV after a rest as
its fallback."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import (
    DETECT_MAX_A,
    MAX_CURRENT_A,
    MAX_TIME_S,
    Strict,
    load_section_model,
)

VoltageSource = Literal["min", "avg"]


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


class SocConfig(Strict):
    """Settings of the SOC estimator (the OCV table itself comes from the cell set)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rest_current_a: float = Field(
        default=0.1, description="A battery rests while |current| is below this (A, > 0)."
    )
    rest_time_s: float = Field(
        default=600.0,
        description="Rest needed before an OCV correction, and between corrections (s, > 0); "
        "long enough for the RC overpotentials to decay (several time constants).",
    )
    blend: float = Field(
        default=1.0,
        description="Weight of the OCV reading in a correction (0..1; 1 = replace).",
    )
    voltage: VoltageSource = Field(
        default="min",
        description="Cell voltage read against the OCV table: 'min' (the weakest cell, which "
        "empties first in a series string) or 'avg' (battery voltage / series cells).",
    )

    observer: bool = Field(
        default=True,
        description="Run the battery observer (EKF) as the SOC source; false: the coulomb "
        "counter with rest corrections alone (as before issue #28).",
    )
    ekf_voltage_sigma_v: float = Field(
        default=0.01,
        description="Standard deviation of the cell-voltage measurement the observer assumes "
        "(V, > 0): sensor noise plus model error.",
    )
    ekf_current_sigma_a: float = Field(
        default=1.0,
        description="Standard deviation of the battery current it assumes (A, > 0): drives "
        "the SOC and polarisation process noise.",
    )
    ekf_resistance_walk: float = Field(
        default=2e-3,
        description="Random walk of the resistance scale (relative, per sqrt(s)): how fast "
        "R0 may move (temperature, ageing) beyond its table.",
    )
    ekf_capacity_walk: float = Field(
        default=1e-6,
        description="Random walk of the capacity (relative, per sqrt(s)): slow, across cycles.",
    )
    ekf_offset_walk_a: float = Field(
        default=2e-5, description="Random walk of the current-sensor offset (A per sqrt(s))."
    )
    ekf_soc_sigma0: float = Field(
        default=0.15, description="Prior standard deviation of the SOC at (re)start (0..1)."
    )
    ekf_resistance_sigma0: float = Field(
        default=0.1, description="Prior relative standard deviation of the resistance scale."
    )
    ekf_capacity_sigma0: float = Field(
        default=0.1, description="Prior relative standard deviation of the capacity."
    )
    ekf_offset_sigma0_a: float = Field(
        default=0.3,
        description="Prior standard deviation of the current-sensor offset (A); 0: not "
        "estimated (the capacity then absorbs the offset as a direction-dependent effective "
        "capacity). Its bound is 4 of these. Measured (issue #28, h28mis): estimated, the "
        "mission's battery B learns the +0.2 A offset to 0.200 +- 0.01 A across its flight "
        "and dock charge, and the campaign's mission family meets 25 of 25 (23 without).",
    )
    nis_window_s: float = Field(
        default=60.0,
        description="Window of the divergence test (s, > 0): the normalised innovations "
        "squared, exponentially averaged over it; also how long a (re)started observer must "
        "run before it is the SOC source again.",
    )
    nis_limit: float = Field(
        default=25.0,
        description="The observer has diverged when that average exceeds this (> 0; a "
        "consistent filter averages about 1).",
    )
    consistency_sigma: float = Field(
        default=3.0,
        description="The observer is rejected (SocObserverInconsistent, the coulomb counter "
        "shown, the observer restarted) when its SOC is more than this many standard "
        "deviations from the counter's, the counter's own uncertainty grown from its last "
        "OCV reading by the capacity's and the current offset's priors (0: not checked). "
        "Catches a filter whose cell model is wrong yet whose innovations look consistent.",
    )

    load_avg_s: float = Field(
        default=180.0,
        description="Time constant of the recent average load the predictions assume (s, > 0; "
        "3 minutes, as Victron's time to go).",
    )
    cutoff_cell_v: float | None = Field(
        default=None,
        description="Cell voltage whose crossing the time to cut-off predicts (V); default: "
        "the cell set's lower voltage limit. Set it to the protection's cut-off.",
    )
    full_cell_v: float | None = Field(
        default=None,
        description="The charger's constant voltage per cell, where the time to full's CV "
        "phase begins (V); default: the cell set's upper voltage limit. Set it to the "
        "charger's CV setpoint over the series cells.",
    )
    full_current_a: float | None = Field(
        default=None,
        description="The charge current at which the charge counts as full (A, > 0; the time "
        "to full's end point); default: C/20 of each battery's capacity.",
    )
    charge_path_ohm: float | None = Field(
        default=None,
        description="Resistance between the charger's regulation point and each battery's "
        "cells while charging (ohm, >= 0; cable, switch, the charger's output slope): the CV "
        "voltage reaches the cells lowered by it times the current, so the CV phase starts "
        "earlier and tapers slower; default: the pack's switch plus the configured charger's "
        "output slope.",
    )

    @model_validator(mode="after")
    def _check_full(self) -> SocConfig:
        """The time to full's end point: a cell voltage and a positive current."""
        f = self.full_cell_v
        if f is not None and not (_finite(f) and 0.0 < f <= 5.0):
            raise ValueError(f"full_cell_v must be within 0..5 V, got {f}")
        a = self.full_current_a
        if a is not None and not (_finite(a) and 0.0 < a <= MAX_CURRENT_A):
            raise ValueError(f"full_current_a must be > 0 A, got {a}")
        r = self.charge_path_ohm
        if r is not None and not (_finite(r) and 0.0 <= r <= 10.0):
            raise ValueError(f"charge_path_ohm must be within 0..10 ohm, got {r}")
        return self

    @model_validator(mode="after")
    def _check(self) -> SocConfig:
        if not (_finite(self.load_avg_s) and 0.0 < self.load_avg_s <= MAX_TIME_S):
            raise ValueError(f"load_avg_s must be > 0 s, got {self.load_avg_s}")
        c = self.cutoff_cell_v
        if c is not None and not (_finite(c) and 0.0 < c <= 5.0):
            raise ValueError(f"cutoff_cell_v must be within 0..5 V, got {c}")
        for name in (
            "ekf_voltage_sigma_v", "ekf_current_sigma_a", "nis_window_s", "nis_limit",
        ):  # fmt: skip
            v = getattr(self, name)
            if not (_finite(v) and 0.0 < v <= MAX_TIME_S):
                raise ValueError(f"{name} must be > 0, got {v}")
        for name in (
            "ekf_resistance_walk", "ekf_capacity_walk", "ekf_offset_walk_a",
            "ekf_resistance_sigma0", "ekf_capacity_sigma0", "ekf_offset_sigma0_a",
        ):  # fmt: skip
            v = getattr(self, name)
            if not (_finite(v) and 0.0 <= v <= 10.0):
                raise ValueError(f"{name} must be within 0..10, got {v}")
        if not (_finite(self.ekf_soc_sigma0) and 0.0 < self.ekf_soc_sigma0 <= 1.0):
            raise ValueError(f"ekf_soc_sigma0 must be within 0..1, got {self.ekf_soc_sigma0}")
        if not (_finite(self.rest_current_a) and 0.0 < self.rest_current_a <= DETECT_MAX_A):
            raise ValueError(
                f"rest_current_a must be > 0 and <= {DETECT_MAX_A:g} A, got {self.rest_current_a}"
            )
        if not (_finite(self.rest_time_s) and 0.0 < self.rest_time_s <= MAX_TIME_S):
            raise ValueError(f"rest_time_s must be > 0 s, got {self.rest_time_s}")
        if not (_finite(self.consistency_sigma) and 0.0 <= self.consistency_sigma <= 100.0):
            raise ValueError(
                f"consistency_sigma must be within 0..100, got {self.consistency_sigma}"
            )
        if not (_finite(self.blend) and 0.0 <= self.blend <= 1.0):
            raise ValueError(f"blend must be within 0..1, got {self.blend}")
        return self

    @classmethod
    def load(cls, data: Mapping[str, Any] | None, source: str = "<soc>") -> SocConfig:
        return load_section_model(cls, data, "soc", source)


__all__ = ["SocConfig", "VoltageSource"]
