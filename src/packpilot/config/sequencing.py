"""``[sequencing]``: thresholds of the parallel-discharge sequencing method (spec section 6)."""

from __future__ import annotations

from pydantic import ConfigDict, Field, model_validator

from packpilot.config.base import Strict


class SequencingConfig(Strict):
    """Thresholds of the parallel-discharge sequencing method (spec section 6 and defaults)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    v_th: float = Field(
        0.5,
        gt=0.0,
        description=(
            "R1 spread threshold (V). At (re)initialisation the batteries within v_th of the "
            "highest discharge and the others stand by; a spread below v_th means all discharge "
            "together. A hot-inserted battery v_th or more above the bus takes over."
        ),
    )
    v_co: float = Field(
        0.3,
        gt=0.0,
        description=(
            "R2 co-discharge threshold (V): a standby battery joins when its terminal voltage "
            "exceeds the highest discharging battery's terminal voltage by at least v_co. Keep it "
            "at or below the body-diode drop (~0.5-0.7 V) and at or below v_th."
        ),
    )
    i_det: float = Field(
        0.5,
        gt=0.0,
        description=(
            "Diode-conduction detection threshold (A) for R3/R4: a battery whose FET on that "
            "path is off but which carries more than i_det has its body diode conducting. Also "
            "the dead band for deciding that the pack is being charged."
        ),
    )
    t_on: float = Field(
        0.1,
        gt=0.0,
        description=(
            "R3/R4 deadline (s): once diode conduction is seen, the FET is commanded on no "
            "later than t_on after the first sample that showed it."
        ),
    )
    t_debounce: float = Field(
        0.02,
        ge=0.0,
        description=(
            "R3/R4 debounce (s): conduction must persist this long before the FET is switched, "
            "so a single noisy sample does not close it. Capped by the t_on deadline."
        ),
    )
    i_rev: float = Field(
        0.5,
        gt=0.0,
        description=(
            "Reverse-current protection (A): an engaged discharging battery taking more than "
            "i_rev of charging current from a sibling has its charge FET opened (-> STANDBY); "
            "mirrored for the discharge FET of a charging battery that feeds a sibling."
        ),
    )
    t_mode: float = Field(
        1.0,
        ge=0.0,
        description=(
            "Mode debounce (s): a pack current below -i_det sustained for t_mode switches to "
            "charge mode when the shell does not report docking; charge mode ends t_mode after "
            "the dock is gone and the pack current is no longer below -i_det."
        ),
    )

    i_merge: float = Field(
        0.5,
        gt=0.0,
        description=(
            "Rest merge (A, [REC]): the largest circulating current a rest merge may cause. A "
            "standby battery rejoins at rest only if its voltage is within i_merge * r_loop_ohm "
            "of every engaged battery, so closing its charge FET pushes at most about i_merge "
            "between them. Keep it at or below i_rev so a merge never trips reverse-current "
            "protection (which would demote it again and chatter)."
        ),
    )
    r_loop_ohm: float = Field(
        0.0404,
        gt=0.0,
        description=(
            "Lowest resistance (ohm) of the loop between two batteries: both internal "
            "resistances plus the four FET on-resistances (2 x 20 mOhm + 4 x 0.1 mOhm for the "
            "spec's example). Use the lowest expected value: a smaller r_loop_ohm only narrows "
            "the rest-merge window i_merge * r_loop_ohm."
        ),
    )
    t_rest: float = Field(
        0.2,
        ge=0.0,
        description=(
            "Rest debounce (s) for the rest merge: every present battery must carry at most "
            "i_det for t_rest before a standby battery may rejoin, so terminal voltages are "
            "close to open-circuit voltages and a passing load step does not count as rest."
        ),
    )

    i_guard: float = Field(
        0.8,
        gt=0.0,
        description=(
            "Cross-current guard (A, [REC]): the largest current the engaged batteries may push "
            "into one of them if the load vanished within the next control period. Predicted "
            "each period from each engaged battery's ohmic-free voltage V + I*R (R estimated "
            "online); the battery that would take more is opened (-> STANDBY) before it can. "
            "Keep it below the 1 A acceptance limit by the estimation error."
        ),
    )
    r_batt_ohm: float = Field(
        0.020,
        gt=0.0,
        description=(
            "Initial estimate (ohm) of each battery's ohmic resistance, used until a current "
            "step of at least i_step has been seen on it; then replaced by -dV/dI of that step."
        ),
    )
    i_step: float = Field(
        1.0,
        gt=0.0,
        description=(
            "Smallest change (A) of a battery's current between two samples that updates its "
            "resistance estimate (-dV/dI), so sensor noise does not dominate the quotient."
        ),
    )
    v_diode: float = Field(
        0.5,
        gt=0.0,
        description=(
            "Lowest expected charge-diode forward drop (V). The guard does not open a battery "
            "whose diode would then conduct at the present load (R3 would close it again)."
        ),
    )
    v_cutoff_cell_v: float = Field(
        3.3,
        ge=0.0,
        description=(
            "Cell cut-off voltage (V per series cell; the load's under-voltage lock-out divided "
            "by the cells in series). The guard does not open a battery when the others alone "
            "would hold the bus less than v_reserve above cut-off: the load must stay supplied "
            "while any battery is above cut-off, which outranks the cross-current prediction."
        ),
    )
    v_reserve: float = Field(
        0.3,
        ge=0.0,
        description=(
            "Headroom (V) above cut-off the remaining batteries must keep for the guard to open "
            "a battery (covers the polarisation that builds up after the load shifts to them)."
        ),
    )
    isolate_source: bool = Field(
        True,
        description=(
            "Source isolation ([REC]): when the guard predicts more than i_guard into a battery "
            "it may not open because R3 closed it at this load (its diode conducted), turn off "
            "both FETs of "
            "the battery that would push that current (the highest fast voltage), provided the "
            "rest hold the bus v_reserve + v_iso_margin above cut-off. False keeps the victim "
            "engaged and only flags it (CrossCurrentRisk)."
        ),
    )
    t_iso_hold: float = Field(
        1.0,
        ge=0.0,
        description=(
            "Source isolation: shortest time (s) an isolated battery stays isolated before it "
            "may take over, merge or return to standby (a forced release does not wait), and "
            "shortest time after a take-over or release before it may be isolated again (no "
            "chatter at a load that hovers around the take-over limit)."
        ),
    )
    v_iso_margin: float = Field(
        0.2,
        ge=0.0,
        description=(
            "Source isolation hysteresis (V): isolated batteries take over only if, alone at "
            "the present load (pessimistic R), they keep the bus this far above every other "
            "battery's fast voltage minus v_diode (their diodes stay off), and return to "
            "standby only with their own diode this far from conducting; isolating needs the "
            "rest this far "
            "above cut-off + v_reserve, releasing is forced below cut-off + v_reserve."
        ),
    )

    @property
    def v_merge(self) -> float:
        """Rest-merge window (V): i_merge * r_loop_ohm."""
        return self.i_merge * self.r_loop_ohm

    @model_validator(mode="after")
    def _check_relations(self) -> SequencingConfig:
        if self.v_co > self.v_th:
            raise ValueError(
                f"v_co ({self.v_co} V) must be <= v_th ({self.v_th} V): a standby battery "
                "more than v_th above the discharging set would otherwise not join (R1 vs R2)"
            )
        if self.i_merge > self.i_rev:
            raise ValueError(
                f"i_merge ({self.i_merge} A) must be <= i_rev ({self.i_rev} A): a rest merge "
                "pushing more than i_rev would be undone by reverse-current protection at once "
                "and repeat every t_rest (charge FET chatter with cross-charging at rest)"
            )
        if self.i_merge > self.i_guard:
            raise ValueError(
                f"i_merge ({self.i_merge} A) must be <= i_guard ({self.i_guard} A): a merge the "
                "cross-current guard would undo at once would chatter"
            )
        if self.t_debounce > self.t_on:
            raise ValueError(
                f"t_debounce ({self.t_debounce} s) must be <= t_on ({self.t_on} s): the debounce "
                "runs inside the R3/R4 deadline"
            )
        return self


__all__ = ["SequencingConfig"]
