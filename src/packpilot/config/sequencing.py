"""``[sequencing]``: thresholds of the parallel-discharge sequencing method (spec section 6)."""

from __future__ import annotations

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import (
    DETECT_MAX_A,
    MAX_CURRENT_A,
    OHM_MAX,
    SPREAD_MAX_V,
    Strict,
)

Q_REV_MAX_AS = 3600.0
"""Largest slow reverse-cut charge: 1 Ah (20 % of the 5 Ah reference cell) of circulating
charge in one episode; a larger one never cuts (``q_rev_as = 1e300`` was accepted)."""
T_RULE_MAX_S = 10.0
"""Longest R3/R4 deadline, debounce and mode debounce: a body diode carrying the load for
longer than seconds overheats (energy I x V_f x t), and a mode held back longer is off."""
C_RATE_MAX = 100.0
"""Largest charge limit in C a cell maker states (fast-charge LTO: ~10-20 C)."""


class SequencingConfig(Strict):
    """Thresholds of the parallel-discharge sequencing method (spec section 6 and defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    v_th: float = Field(
        0.5,
        le=SPREAD_MAX_V,
        gt=0.0,
        description=(
            "R1 spread threshold (V). At (re)initialisation the batteries within v_th of the "
            "highest discharge and the others stand by; a spread below v_th means all discharge "
            "together. A hot-inserted battery v_th or more above the bus takes over."
        ),
    )
    v_co: float = Field(
        0.05,
        le=SPREAD_MAX_V,
        gt=0.0,
        description=(
            "R2 co-discharge threshold (V): a standby battery joins once its fast voltage "
            "V + I*R is less than v_co below the highest discharging battery's (the voltages "
            "have met; issue #15). Sets the worst sharing error right after a join "
            "(v_co / R_loop, 1.25 A at 40 mOhm) and the zero-load current into the lower one. "
            "At most v_th."
        ),
    )
    i_det: float = Field(
        0.5,
        le=DETECT_MAX_A,
        gt=0.0,
        description=(
            "Diode-conduction detection threshold (A) for R3/R4: a battery whose FET on that "
            "path is off but which carries more than i_det has its body diode conducting. Also "
            "the dead band for deciding that the pack is being charged."
        ),
    )
    t_on: float = Field(
        0.1,
        le=T_RULE_MAX_S,
        gt=0.0,
        description=(
            "R3/R4 deadline (s): once diode conduction is seen, the FET is commanded on no "
            "later than t_on after the first sample that showed it."
        ),
    )
    t_debounce: float = Field(
        0.02,
        le=T_RULE_MAX_S,
        ge=0.0,
        description=(
            "R3/R4 debounce (s): conduction must persist this long before the FET is switched, "
            "so a single noisy sample does not close it. Capped by the t_on deadline."
        ),
    )
    i_rev: float = Field(
        0.5,
        le=DETECT_MAX_A,
        gt=0.0,
        description=(
            "Reverse cut (A; embodiments 5 and 7: the charge FET is on only while discharge "
            "current flows): an engaged discharging battery taking more than i_rev of charging "
            "current from a sibling has its charge FET opened in that period (it stays "
            "admitted: the engage rule or R3 closes it again once it would discharge); mirrored "
            "for the discharge FET of a charging battery that feeds a sibling."
        ),
    )
    q_rev_as: float = Field(
        0.5,
        le=Q_REV_MAX_AS,
        gt=0.0,
        description=(
            "Slow reverse cut (A s): an engaged battery that siblings keep charging below i_rev "
            "(a circulating current at light load) has its charge FET opened once this much "
            "charge has flowed into it in one uninterrupted episode (0.5 A s = 0.14 mAh)."
        ),
    )
    t_mode: float = Field(
        1.0,
        le=T_RULE_MAX_S,
        ge=0.0,
        description=(
            "Mode debounce (s): a pack current below -i_det sustained for t_mode switches to "
            "charge mode when the shell does not report docking; charge mode ends t_mode after "
            "the dock is gone and the pack current is no longer below -i_det."
        ),
    )

    charge_limit_c: float = Field(
        0.5,
        le=C_RATE_MAX,
        gt=0.0,
        description=(
            "Charge limit of each battery (C; issue #15's invariant): no battery may take more "
            "than charge_limit_c x its capacity. The engage rule closes a charge FET only if, "
            "with it closed, no engaged battery would take more than that if the load vanished."
        ),
    )
    charge_limit_margin: float = Field(
        0.9,
        gt=0.0,
        le=1.0,
        description=(
            "Share of the charge limit the zero-load prediction may reach: the engage rule "
            "closes a charge FET only if no engaged battery's predicted current at zero load "
            "exceeds charge_limit_margin x its limit, and the risk flag (CrossCurrentRisk) is "
            "raised above it. The prediction rests on resistances and EMFs estimated from "
            "current steps (measured errors: 1.6 % at 0.1 s periods, 9 % at 0.5 s, where the "
            "estimate takes in polarization)."
        ),
    )
    risk_clear_ratio: float = Field(
        0.8,
        gt=0.0,
        le=1.0,
        description=(
            "The risk flag, once raised, clears only when the prediction falls below "
            "risk_clear_ratio x the charge limit (hysteresis below charge_limit_margin): a flag "
            "that drops just before the load does is no warning."
        ),
    )
    default_capacity_ah: float = Field(
        5.0,
        le=1e4,
        gt=0.0,
        description=(
            "Capacity (Ah) assumed for the charge limit where the topology does not state a "
            "battery's capacity (replay logs, the scalar API without capacities)."
        ),
    )
    r_batt_ohm: float = Field(
        0.020,
        le=OHM_MAX,
        gt=0.0,
        description=(
            "Initial estimate (ohm) of each battery's ohmic resistance, used until a current "
            "step of at least i_step has been seen on it; then replaced by -dV/dI of that step."
        ),
    )
    i_step: float = Field(
        1.0,
        le=MAX_CURRENT_A,
        gt=0.0,
        description=(
            "Smallest change (A) of a battery's current between two samples that updates its "
            "resistance estimate (-dV/dI), so sensor noise does not dominate the quotient."
        ),
    )

    zero_load_observer: bool = Field(
        True,
        description=(
            "Take the zero-load prediction's resistances from the battery observer ([soc], "
            "issue #28) where it runs and is trusted: fast voltage V + I x R0 and conductance "
            "1 / R0 with the observer's R0, which excludes the polarisation the -dV/dI "
            "estimate takes in over a long period. False (or no trusted observer): the -dV/dI "
            "estimate, as before."
        ),
    )
    zero_load_open: bool = Field(
        False,
        description=(
            "Rule 8b (issue #28), opt-in: open an engaged battery whose trusted zero-load "
            "prediction exceeds zero_load_open_ratio x its charge limit. Off by default: it "
            "holds the charge limit on 490 of 500 randomized load losses (460 without) at the "
            "price of more FET changes (median 3.8 per minute of hold against 0.35) and, on "
            "uav_mission, an A/B hand-over cycle every ~20 s for the first 4 minutes after "
            "the join instead of co-discharge (docs/parallel_discharge.md rule 8b)."
        ),
    )
    zero_load_open_ratio: float = Field(
        0.95,
        gt=0.0,
        le=1.0,
        description=(
            "Rule 8b (issue #28): an engaged battery whose zero-load prediction, from the "
            "trusted observer, exceeds zero_load_open_ratio x its charge limit has its charge "
            "FET opened (not one R3 closed). Below charge_limit_margin it counts as that "
            "margin (the engage rule closes a battery up to the margin: no chatter)."
        ),
    )

    diode_hold_a: float = Field(
        0.0,
        ge=0.0,
        le=MAX_CURRENT_A,
        description=(
            "Rule 8c (issue #28): R3 leaves a battery's charge FET off while its body diode "
            "carries at most diode_hold_a (A) and the trusted zero-load prediction with it "
            "engaged puts it above charge_limit_margin x its charge limit: under a heavy load "
            "the diode of a lower battery conducts, and once closed the others would charge "
            "it past its limit when the load goes. Size it from the diode's continuous "
            "dissipation (diode drop x diode_hold_a). 0 = off: R3 closes on its t_on deadline "
            "(the spec's rule). Meant with zero_load_open (rule 8b opens a battery, its diode "
            "then conducts and R3 closed it again): together, with 10 A, the charge limit held "
            "on 500 of 500 randomized load losses (docs/parallel_discharge.md rule 8c)."
        ),
    )

    @model_validator(mode="after")
    def _check_relations(self) -> SequencingConfig:
        if self.v_co > self.v_th:
            raise ValueError(
                f"v_co ({self.v_co} V) must be <= v_th ({self.v_th} V): a standby battery "
                "more than v_th above the discharging set would otherwise not join (R1 vs R2)"
            )
        if self.t_debounce > self.t_on:
            raise ValueError(
                f"t_debounce ({self.t_debounce} s) must be <= t_on ({self.t_on} s): the debounce "
                "runs inside the R3/R4 deadline"
            )
        if self.risk_clear_ratio > self.charge_limit_margin:
            raise ValueError(
                f"risk_clear_ratio ({self.risk_clear_ratio}) must be <= charge_limit_margin "
                f"({self.charge_limit_margin}): the risk flag clears below where it is raised"
            )
        return self


__all__ = ["C_RATE_MAX", "Q_REV_MAX_AS", "T_RULE_MAX_S", "SequencingConfig"]
