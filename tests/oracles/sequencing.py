"""ORACLE: the scalar sequencing controller as it was before the compiled core (tests only;
deleted once the golden and equivalence tests pass).

Discharge sequencing of parallel batteries behind charge/discharge MOSFET pairs.

Spec: ``spec/parallel_discharge.md`` (DJI CN 201680002560.8), generalised to N >= 2 batteries.
Each battery sits behind a charge FET (its body diode conducts when the battery *discharges*)
in series with a discharge FET (its diode conducts when the battery is *charged*). The point of
the method is that a battery whose charge FET is off can feed the bus through the diode but can
never be charged by a higher sibling, so directly paralleled batteries at different voltages do
not push tens of amperes into each other.

States (per battery) and the FET pattern each one commands:

* ``DISCHARGING`` - admitted to discharge: discharge FET on; charge FET on once *engaged*.
  Engagement follows R3 (diode conduction seen -> FET on within ``t_on``) or the *level rule*
  (the battery's voltage has reached the bus reference, so closing the FET cannot charge it).
* ``STANDBY`` - discharge FET on, charge FET off (the charge diode blocks any charging); both
  off while the battery is isolated by source isolation ([REC]).
* ``CHARGING`` - charge FET on; discharge FET on once charging current is seen through its
  diode (R4).
* ``OFF`` - both FETs off: the battery is not present.

Rules applied every control period in discharge mode (see ``docs/parallel_discharge.md``):

* R1 at (re)initialisation (power-up, fault recovery, return from charge mode, empty
  discharging set): batteries within ``v_th`` of the highest discharge, the others stand by.
  A hot-inserted battery that is ``v_th`` or more above the bus reference takes over (R1
  re-applied to it); any other inserted battery starts in STANDBY.
* Reverse current: an engaged discharging battery taking more than ``i_rev`` of charge from a
  sibling has its charge FET opened (-> STANDBY).
* R2: a standby battery ``v_co`` or more above the bus reference (the highest discharging
  battery's terminal voltage) joins. At rest (no current anywhere) it takes over instead of
  co-discharging, because rest voltages are open-circuit voltages and co-discharge would push
  about (V_k - V_ref) / R_loop into the others.
* Rest merge ([REC], not in the source text): when every battery has carried at most
  ``i_det`` for ``t_rest``, a standby (or admitted, not yet engaged) battery whose voltage is
  within ``v_merge = i_merge * r_loop_ohm`` of every engaged battery rejoins with its charge FET
  on, like R1 admitting batteries within ``v_th`` at power-up, but with a window sized so the
  circulating current it can cause stays at or below ``i_merge <= i_rev``.
* Load merge ([REC]): under load, a standby or admitted battery whose *fast voltage*
  ``V + I*R`` (R estimated online from current steps) matches the engaged ones' closes its
  charge FET; the level rule (which completes R2) closes one only under the same check.
* R3: a battery with discharge FET on and charge FET off that sources more than ``i_det``
  (its charge diode conducts) gets its charge FET on after a debounce, no later than ``t_on``.
  Only current measured over a period in which the controller held that FET off counts.
* Cross-current guard ([REC]): a sampled controller cannot stop the current that flows between
  co-discharging batteries in the period in which the load falls, so every period it predicts
  that current at zero load from the fast voltages and opens (-> STANDBY) any battery that
  would take more than ``i_guard``, unless R3 needs it closed or the bus needs it above cut-off
  (then ``CrossCurrentRisk``).
* Source isolation ([REC], ``isolate_source``): when the guard predicts more than ``i_guard``
  into a battery that R3 closed at the present load (opening it would only make its diode
  conduct again: the R3 conflict), the battery pushing that current is *isolated* - STANDBY
  with the discharge FET off too (``seq_isolated``) - if the rest carry the load with
  pessimistic resistances. It comes back by take-over, merge, plain STANDBY or, near
  cut-off, forced (``_release_isolated``), after at least ``t_iso_hold``.

Invalid measurements (non-finite or negative voltage, non-finite current, time or period) put
the pack in a fail-safe: every charge FET off, every present battery's discharge FET on (the
pack can discharge only through the charge diodes, nothing can be charged), with one ``Fault``
event. When measurements are valid again the controller re-initialises with R1.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from packpilot.config.sequencing import SequencingConfig
from packpilot.contract.bms import BatteryMeasurement, Commands, ControlOutput, Event, Measurements
from packpilot.contract.topology import PackInfo

_EPS_S = 1e-9
"""Tolerance for comparing accumulated times, so 0.1 + 0.1 + 0.1 counts as 0.3 s."""


class SeqState(enum.StrEnum):
    """Per-battery sequencing state (spec section 3, plus OFF for an absent battery)."""

    DISCHARGING = "DISCHARGING"
    STANDBY = "STANDBY"
    CHARGING = "CHARGING"
    OFF = "OFF"


class SeqMode(enum.StrEnum):
    """Pack-level mode: which set of rules runs this period."""

    DISCHARGE = "discharge"
    CHARGE = "charge"
    FAULT = "fault"


@dataclass(slots=True)
class BatterySeq:
    """Per-battery controller state. ``chg_on``/``dsg_on`` are the commands last issued."""

    state: SeqState = SeqState.OFF
    chg_on: bool = False
    dsg_on: bool = False
    conduct_since_s: float | None = None
    """Time of the first sample of the current diode-conduction episode (R3/R4), if any."""
    r_ohm: float = math.nan
    """Ohmic resistance estimate (-dV/dI of the last current step >= i_step); NaN = none yet."""
    last_v_v: float | None = None
    last_i_a: float | None = None
    """The previous sample's battery-side voltage and current (for the resistance estimate)."""
    hold_load_a: float | None = None
    """Pack current at which R3 last had to close this battery's charge FET: the guard leaves
    it engaged while the pack current stays above 0.9 of that (its diode would conduct)."""
    guard_opened: bool = False
    """The guard opened this battery's charge FET and no rule has closed it since."""
    at_risk: bool = False
    """The guard predicts more than i_guard into this battery but may not open it."""
    isolated_since_s: float | None = None
    """Source isolation: time both FETs were opened (state STANDBY); None = not isolated."""
    released_at_s: float | None = None
    """Source isolation: time this battery last left isolation by a take-over, the standby
    release or a forced release; it is not isolated again within t_iso_hold of that (no
    chatter). A merge sets no hold-off: it needs the fast voltages to agree."""


@dataclass(slots=True)
class SequencingState:
    """Everything the controller remembers between periods (explicit, so it can be inspected)."""

    batteries: list[BatterySeq]
    mode: SeqMode = SeqMode.DISCHARGE
    initialized: bool = False
    last_t_s: float | None = None
    mode_evidence_since_s: float | None = None
    """First sample of the current run of evidence for leaving the current mode."""
    v_ref_v: float | None = None
    """Bus reference of the last period (highest discharging terminal voltage)."""
    fault_reason: str = ""
    rest_since_s: float | None = None
    """First sample of the current run of samples with every battery at or below i_det."""
    zero_load_into_a: list[float] | None = None
    """Guard prediction of the last discharge period: current into each battery at zero load."""


def _pattern(state: SeqState, engaged: bool) -> tuple[bool, bool]:
    """(chg_on, dsg_on) for a state; ``engaged`` is the R3/R4-controlled FET of that state."""
    if state is SeqState.DISCHARGING:
        return engaged, True
    if state is SeqState.STANDBY:
        return False, True
    if state is SeqState.CHARGING:
        return True, engaged
    return False, False


class SequencingController:
    """Parallel-discharge sequencing for ``pack.n_batteries`` MOSFET-pair batteries.

    Deterministic: the only clock is ``meas.t_s`` (for timers) and ``dt_s`` (the control period,
    used to predict whether waiting one more period would miss the ``t_on`` deadline).
    """

    def __init__(self, config: SequencingConfig, pack: PackInfo) -> None:
        if pack.n_batteries < 1:
            raise ValueError("SequencingController needs at least one battery")
        self.config = config
        self.pack = pack
        self.state = SequencingState(batteries=[BatterySeq() for _ in range(pack.n_batteries)])

    # ------------------------------------------------------------------ helpers
    def _set(
        self,
        k: int,
        new: SeqState,
        engaged: bool,
        t_s: float,
        events: list[Event],
        kind: str = "StateChanged",
        reason: str = "",
        data: dict[str, float | int | str | bool | None] | None = None,
    ) -> None:
        """Move battery k to ``new`` and record one event if its state changed."""
        b = self.state.batteries[k]
        old = b.state
        b.state = new
        b.chg_on, b.dsg_on = _pattern(new, engaged)
        b.isolated_since_s = None
        if old is not new:
            payload: dict[str, float | int | str | bool | None] = {
                "from": old.value,
                "to": new.value,
                "reason": reason,
            }
            if data:
                payload.update(data)
            events.append(
                Event(
                    t_s=t_s,
                    kind=kind,
                    battery=k,
                    message=f"battery {k}: {old.value} -> {new.value} ({reason})",
                    data=payload,
                )
            )

    def _validate(self, meas: Measurements, dt_s: float) -> str:
        """Return why the sample is unusable, or ``""`` if it is fine."""
        if len(meas.batteries) != self.pack.n_batteries:
            return (
                f"expected {self.pack.n_batteries} batteries in the measurements, "
                f"got {len(meas.batteries)}"
            )
        if not math.isfinite(meas.t_s):
            return f"t_s is not finite ({meas.t_s})"
        if not math.isfinite(dt_s) or dt_s < 0.0:
            return f"dt_s must be a finite number >= 0 (got {dt_s})"
        last = self.state.last_t_s
        if last is not None and meas.t_s < last:
            return f"time went backwards ({last} -> {meas.t_s})"
        for k, bm in enumerate(meas.batteries):
            if not bm.present:
                continue
            if not math.isfinite(bm.voltage_v) or bm.voltage_v < 0.0:
                return f"battery {k}: voltage {bm.voltage_v} is not a finite value >= 0"
            if not math.isfinite(bm.current_a):
                return f"battery {k}: current {bm.current_a} is not finite"
        return ""

    def _v_ref(self, meas: Measurements) -> float | None:
        """Bus reference for R2: highest terminal voltage of the discharging set.

        Admitted batteries whose charge FET is still open count too, so a standby battery joins
        only above every battery already admitted to discharge (joins go in voltage order).
        """
        admitted = [
            meas.batteries[k].voltage_v
            for k, b in enumerate(self.state.batteries)
            if b.state is SeqState.DISCHARGING
        ]
        return max(admitted) if admitted else None

    # ------------------------------------------------------------------ cross-current guard
    def _update_resistance(self, meas: Measurements) -> None:
        """Resistance estimate per battery: -dV/dI over the last current step >= ``i_step``.

        Voltages are battery-side, so the quotient is the battery's ohmic resistance whatever
        its FETs or diodes did; over one control period OCV and polarisation hardly move.
        """
        for b, bm in zip(self.state.batteries, meas.batteries, strict=True):
            if not bm.present:
                b.last_v_v = b.last_i_a = None
                continue
            if b.last_v_v is not None and b.last_i_a is not None:
                di = bm.current_a - b.last_i_a
                if abs(di) >= self.config.i_step:
                    r = -(bm.voltage_v - b.last_v_v) / di
                    if 0.0 < r <= 20.0 * self.config.r_batt_ohm:
                        b.r_ohm = r
            b.last_v_v, b.last_i_a = bm.voltage_v, bm.current_a

    def _r_est(self, k: int) -> float:
        r = self.state.batteries[k].r_ohm
        return self.config.r_batt_ohm if math.isnan(r) else r

    def _e_fast(self, k: int, meas: Measurements) -> float:
        """Voltage battery k shows the instant its current drops to zero: V + I*R (OCV minus
        the polarisation, which relaxes with a time constant of tens of seconds)."""
        bm = meas.batteries[k]
        return bm.voltage_v + bm.current_a * self._r_est(k)

    def _zero_load_into(self, group: list[int], meas: Measurements) -> dict[int, float]:
        """Current (A, > 0 = charging) into each battery of ``group`` if the load vanished now.

        The engaged batteries then form a loop of voltage sources behind their resistances; the
        lowest ones are charged by the others. Zero load is the worst case: any load current
        only lowers the current into every battery. FET on-resistances are left out, which
        overestimates the current (the safe side).
        """
        if len(group) < 2:
            return dict.fromkeys(group, 0.0)
        e = {k: self._e_fast(k, meas) for k in group}
        g = {k: 1.0 / self._r_est(k) for k in group}
        v0 = sum(e[k] * g[k] for k in group) / sum(g.values())
        return {k: (v0 - e[k]) * g[k] for k in group}

    def _bus_without(
        self, group: list[int], meas: Measurements, load_a: float, r_scale: float = 1.0
    ) -> float:
        """Bus voltage if only ``group`` (engaged, FETs on) carried ``load_a``; ``r_scale``
        multiplies their resistances (> 1: pessimistic, for polarisation and a prior R)."""
        g = {k: 1.0 / (r_scale * self._r_est(k)) for k in group}
        return (sum(self._e_fast(k, meas) * g[k] for k in group) - load_a) / sum(g.values())

    def _merge_candidates(
        self, demoted: set[int], volt: list[float], present: list[bool] | None = None
    ) -> list[int]:
        """Batteries a rest or load merge may close, highest voltage first: standby or admitted
        with the charge FET open, not isolated, not demoted this period (and, for the load
        merge, ``present``)."""
        candidates = [
            k
            for k, b in enumerate(self.state.batteries)
            if k not in demoted
            and (present is None or present[k])
            and not b.chg_on
            and b.isolated_since_s is None
            and b.state in (SeqState.STANDBY, SeqState.DISCHARGING)
        ]
        return sorted(candidates, key=lambda j: -volt[j])

    def _engaged(self) -> list[int]:
        return [
            k
            for k, b in enumerate(self.state.batteries)
            if b.state is SeqState.DISCHARGING and b.chg_on
        ]

    def _safe_to_close(self, k: int, meas: Measurements, limit_a: float) -> bool:
        """Closing battery k's charge FET keeps the zero-load current into it <= ``limit_a``.

        Only k's side is checked: if k would push more than that into an engaged sibling, the
        guard opens the sibling (k takes over), as R2 already does at rest.
        """
        group = sorted({*self._engaged(), k})
        return self._zero_load_into(group, meas)[k] <= limit_a

    def _guard(self, meas: Measurements, t_s: float, keep: set[int], events: list[Event]) -> None:
        """Open, before the load can fall, the charge FET of any engaged battery that would take
        more than ``i_guard`` from its siblings at zero load (worst victim first).

        A sampled controller cannot react within the period in which the load falls; between
        that step and the next sample the plant pushes (E_a - E_b) / (R_a + R_b) into the lower
        battery. Batteries co-discharging on one bus have equal terminal voltages, so their
        fast voltages E = V + I*R differ by their I*R difference (16 vs 30 mOhm at 10 A: 0.14 V,
        3 A). Not opened: a battery in ``keep`` (closed by R3 this period), the last engaged
        one, one whose diode would conduct at the present load (R3 would re-close it), and one
        without which the others would hold the bus less than ``v_reserve`` above cut-off.
        Source isolation [REC] applies to the R3 conflict only: a victim that R3 closed this
        period, or closed earlier at (0.9 of) the present load, cannot be opened (its diode
        would conduct and R3 close it again), so the battery that would push the current is
        isolated instead, if the rest can carry the load (``_isolate_source``). A victim kept
        for any other reason (last engaged, cut-off reserve, a diode that would conduct only
        once opened) stays engaged and is flagged, as before.
        """
        cfg = self.config
        bats = self.state.batteries
        load_a = sum(bm.current_a for bm in meas.batteries if bm.present)
        v_cut = self._v_cut()
        held: set[int] = set()
        diode_held: set[int] = set(keep)
        for k, b in enumerate(bats):
            if b.state is not SeqState.DISCHARGING or not b.chg_on:
                b.hold_load_a = None
                continue
            if k not in keep:
                b.guard_opened = False
            if b.hold_load_a is not None:
                if load_a >= 0.9 * b.hold_load_a:
                    diode_held.add(k)
                else:
                    b.hold_load_a = None
        while True:
            group = self._engaged()
            pred = self._zero_load_into(group, meas)
            victims = sorted(
                (k for k in group if pred[k] > cfg.i_guard and k not in held),
                key=lambda j: -pred[j],
            )
            if not victims:
                break
            k = victims[0]
            others = [j for j in group if j != k]
            v_bus = self._bus_without(others, meas, load_a) if others else -math.inf
            if not others or v_bus < v_cut + cfg.v_reserve:
                held.add(k)
                continue
            if k in diode_held:
                # R3 conflict: R3 closed it because its diode conducted at this load, so opening
                # it would only make the diode conduct again. Take the source away instead.
                if not self._isolate_source(k, group, pred, meas, load_a, t_s, events):
                    held.add(k)
                continue
            if self._e_fast(k, meas) - cfg.v_diode >= v_bus:
                held.add(k)
                continue
            self._set(
                k,
                SeqState.STANDBY,
                False,
                t_s,
                events,
                kind="CrossCurrentGuard",
                reason="would be charged if the load vanished",
                data={
                    "predicted_a": pred[k],
                    "i_guard": cfg.i_guard,
                    "e_fast_v": self._e_fast(k, meas),
                    "r_ohm": self._r_est(k),
                },
            )
            self.state.batteries[k].conduct_since_s = None
            self.state.batteries[k].guard_opened = True
        # What is left above i_guard the controller knowingly keeps (R3, cut-off reserve, last
        # battery): flagged once per episode, so the risk is visible in the event log.
        group = self._engaged()
        pred = self._zero_load_into(group, meas)
        for k, b in enumerate(bats):
            risk = pred.get(k, 0.0) > cfg.i_guard
            if risk and not b.at_risk:
                events.append(
                    Event(
                        t_s=t_s,
                        kind="CrossCurrentRisk",
                        battery=k,
                        message=(
                            f"battery {k}: {pred[k]:.2f} A would flow into it if the load "
                            "vanished, but it must stay engaged"
                        ),
                        data={"predicted_a": pred[k], "i_guard": cfg.i_guard},
                    )
                )
            b.at_risk = risk
        self.state.zero_load_into_a = [pred.get(k, 0.0) for k in range(len(bats))]

    def _v_cut(self) -> float:
        """Pack cut-off voltage (V): ``v_cutoff_cell_v`` times the cells in series."""
        cells = max(self.pack.cells_per_group) if self.pack.cells_per_group else 0
        return self.config.v_cutoff_cell_v * cells

    def _isolate_source(
        self,
        victim: int,
        group: list[int],
        pred: dict[int, float],
        meas: Measurements,
        load_a: float,
        t_s: float,
        events: list[Event],
    ) -> bool:
        """Source isolation [REC]: open *both* FETs of the battery that would charge ``victim``.

        The guard cannot open the victim: its charge diode would conduct and R3 would close it
        again (diode stress). So the battery with the highest fast voltage among its siblings
        (the one pushing the current) is isolated instead: STANDBY with the discharge FET off
        too, because with only its charge FET off it would still discharge through its charge
        diode. Only if the rest (the victim included) hold the bus ``v_reserve`` +
        ``v_iso_margin`` above cut-off at the present load, with pessimistic resistances
        (``_bus_held``), and not within ``t_iso_hold`` of its last release (no chatter).
        Isolating the victim instead (both its FETs off) was tried: it leaves the high battery
        carrying a heavy load alone, which drags the bus under the next battery's diode, and
        did worse in the closed-loop sweeps. Returns whether a battery was isolated.
        """
        cfg = self.config
        if not cfg.isolate_source:
            return False
        bats = self.state.batteries
        sources = [j for j in group if j != victim and pred[j] < 0.0]
        if not sources:
            return False
        src = max(sources, key=lambda j: self._e_fast(j, meas))
        rel = bats[src].released_at_s
        if rel is not None and t_s - rel + _EPS_S < cfg.t_iso_hold:
            return False
        v_rest = self._bus_held(src, [j for j in group if j != src], meas, load_a)
        if v_rest < self._v_cut() + cfg.v_reserve + cfg.v_iso_margin:
            return False
        self._set(
            src,
            SeqState.STANDBY,
            False,
            t_s,
            events,
            kind="SourceIsolated",
            reason=f"would charge battery {victim}, which R3 closed at this load",
            data={
                "victim": victim,
                "predicted_a": pred[victim],
                "e_fast_v": self._e_fast(src, meas),
                "v_rest_v": v_rest,
            },
        )
        b = bats[src]
        b.dsg_on = False
        b.isolated_since_s = t_s
        b.conduct_since_s = None
        b.guard_opened = False
        b.hold_load_a = None
        return True

    def _r_pess(self, j: int) -> float:
        """Pessimistic resistance (ohm) of battery ``j``: 1.25 x the estimate (polarisation
        builds up once the load has moved to it), 2 x the prior before any current step."""
        b = self.state.batteries[j]
        return (2.0 if math.isnan(b.r_ohm) else 1.25) * self._r_est(j)

    def _bus_held(self, iso: int, rest: list[int], meas: Measurements, load_a: float) -> float:
        """Pessimistic bus voltage (V) if battery ``iso`` stopped and ``rest`` (engaged) plus
        every other battery with its discharge FET on (through its diode) carried ``load_a``.

        Resistances are inflated: 1.25 x the estimate (polarisation builds up once the load has
        moved to the rest), 2 x the prior for a battery that has not yet seen a current step.
        Diodes drop ``v_diode + v_iso_margin``, the pessimistic end of the 0.5-0.7 V range.
        """
        cfg = self.config
        bats = self.state.batteries

        g = {j: 1.0 / self._r_pess(j) for j in rest}
        if not g:
            return -math.inf
        num = sum(self._e_fast(j, meas) * g[j] for j in rest)
        v_rest = (num - load_a) / sum(g.values())
        diodes = [
            j
            for j, bj in enumerate(bats)
            if j != iso and j not in rest and meas.batteries[j].present and bj.dsg_on
        ]
        v_drop = cfg.v_diode + cfg.v_iso_margin
        for j in sorted(diodes, key=lambda i: -self._e_fast(i, meas)):
            e_j = self._e_fast(j, meas) - v_drop
            if v_rest >= e_j:
                break
            g[j] = 1.0 / self._r_pess(j)
            num += e_j * g[j]
            v_rest = (num - load_a) / sum(g.values())
        return v_rest

    def _release_isolated(self, meas: Measurements, t_s: float, events: list[Event]) -> None:
        """Bring an isolated battery back when that is safe, or when the load needs it.

        Not before ``t_iso_hold`` (unless forced), then the first that applies:

        * take-over (``_take_over``, not while a charge diode conducts: R3 would then act on a
          current the take-over has just changed): the highest isolated batteries, the fewest
          that suffice and within ``v_co`` of one another, would carry the present load alone
          (pessimistic R) ``v_iso_margin`` above every non-isolated battery's fast voltage minus
          ``v_diode``; they discharge and the discharging ones stand by (R1 on the isolated
          set). This is what keeps a higher isolated battery from waiting while the lower ones
          drain, and its energy from being left behind;
        * merge: with it engaged, the zero-load prediction puts at most ``i_merge`` into it and
          at most ``i_guard`` into anyone (the load merge's test), or at least no more than
          now into anyone (a battery between the engaged ones' fast voltages narrows a risk
          the guard could not open, and then lets the guard open the victim);
        * standby: at the present bus its charge diode stays off with ``v_iso_margin`` to
          spare, so plain STANDBY (diode-OR) is safe and R2 / load merge take it from there;
        * forced: the engaged batteries hold the bus less than ``v_reserve`` above cut-off (or
          none is engaged): plain STANDBY whatever the risk (it feeds the bus through its
          diode and R3 closes it): the load must stay supplied.
        """
        cfg = self.config
        bats = self.state.batteries
        iso = [k for k, b in enumerate(bats) if b.isolated_since_s is not None]
        if not iso:
            return
        present = [bm.present for bm in meas.batteries]
        load_a = sum(bm.current_a for bm, p in zip(meas.batteries, present, strict=True) if p)
        # A diode conducting now (R3 pending) was driven by the present bus; a take-over would
        # leave R3 acting on stale current. Wait until R3 has closed it.
        diode_on = any(
            p and bj.dsg_on and not bj.chg_on and meas.batteries[j].current_a > cfg.i_det
            for j, (bj, p) in enumerate(zip(bats, present, strict=True))
        )
        if not diode_on and self._take_over(iso, meas, load_a, t_s, events):
            return
        for k in sorted(iso, key=lambda j: -self._e_fast(j, meas)):
            b = bats[k]
            since = b.isolated_since_s
            if since is None:
                continue
            engaged = self._engaged()
            # Bus estimate: the lowest engaged battery; with none engaged (R1 has just admitted
            # batteries with their charge FETs open) the highest admitted one less a diode
            # drop; with nobody admitted, nothing supplies the load but the diodes: forced.
            admitted = [
                meas.batteries[j].voltage_v
                for j, bj in enumerate(bats)
                if present[j] and bj.state is SeqState.DISCHARGING
            ]
            if engaged:
                bus_v = min(meas.batteries[j].voltage_v for j in engaged)
            elif admitted:
                bus_v = max(admitted) - cfg.v_diode
            else:
                bus_v = -math.inf
            forced = bus_v < self._v_cut() + cfg.v_reserve
            if not forced and t_s - since + _EPS_S < cfg.t_iso_hold:
                continue
            if engaged:
                pred = self._zero_load_into(sorted({*engaged, k}), meas)
                worst = max(self._zero_load_into(engaged, meas).values())
                if pred[k] <= cfg.i_merge and max(pred.values()) <= max(cfg.i_guard, worst):
                    self._set(
                        k,
                        SeqState.DISCHARGING,
                        True,
                        t_s,
                        events,
                        kind="BatteryJoined",
                        reason="isolation merge",
                        data={"predicted_a": pred[k], "isolated_s": t_s - since},
                    )
                    continue
            e_k = self._e_fast(k, meas)
            quiet = bus_v >= e_k - cfg.v_diode + cfg.v_iso_margin
            if not (quiet or forced):
                continue
            reason = "isolation ended" if quiet else "isolation forced"
            self._set(k, SeqState.STANDBY, False, t_s, events)
            b.released_at_s = t_s
            events.append(
                Event(
                    t_s=t_s,
                    kind="StateChanged",
                    battery=k,
                    message=f"battery {k}: {reason}, discharge FET on (STANDBY)",
                    data={"from": "STANDBY", "to": "STANDBY", "reason": reason},
                )
            )

    def _take_over(
        self, iso: list[int], meas: Measurements, load_a: float, t_s: float, events: list[Event]
    ) -> bool:
        """Isolation take-over: the isolated batteries (highest fast voltage first, the fewest
        that suffice) discharge and everybody else stands by, when that is safe.

        A set ``T`` of isolated batteries held at least ``t_iso_hold`` qualifies when, carrying
        the present load alone with pessimistic resistances (``_r_pess``), it holds the bus
        ``v_iso_margin`` above every other battery's fast voltage minus ``v_diode`` (no charge
        diode outside ``T`` conducts, so R3 cannot pull a lower battery back in under it) and
        ``v_reserve`` above cut-off, and the batteries of ``T`` would not push more than
        ``i_merge`` into one another at zero load. The discharging batteries outside ``T`` go to
        plain STANDBY; the other isolated ones stay isolated until they merge with ``T`` (or
        their diodes would stay off, or the load forces them back). This is R1 applied to the
        isolated set; without it a higher isolated battery would wait
        while the lower ones drain, and be left with its energy at the end.
        """
        cfg = self.config
        bats = self.state.batteries
        present = [bm.present for bm in meas.batteries]
        ready = sorted(
            (
                k
                for k in iso
                if (since := bats[k].isolated_since_s) is not None
                and t_s - since + _EPS_S >= cfg.t_iso_hold
            ),
            key=lambda j: -self._e_fast(j, meas),
        )
        for m in range(1, len(ready) + 1):
            group = ready[:m]
            g = {j: 1.0 / self._r_pess(j) for j in group}
            e = {j: self._e_fast(j, meas) for j in group}
            v_alone = (sum(e[j] * g[j] for j in group) - max(load_a, 0.0)) / sum(g.values())
            e_rest = max(
                (
                    self._e_fast(j, meas)
                    for j in range(len(bats))
                    if present[j] and j not in group and bats[j].isolated_since_s is None
                ),
                default=-math.inf,
            )
            if max(e.values()) - min(e.values()) > cfg.v_co:
                break
            if v_alone < e_rest - cfg.v_diode + cfg.v_iso_margin:
                continue
            if v_alone < self._v_cut() + cfg.v_reserve:
                continue
            for j, bj in enumerate(bats):
                if j in group or not present[j]:
                    continue
                if bj.state is SeqState.DISCHARGING:
                    self._set(j, SeqState.STANDBY, False, t_s, events, reason="isolation take-over")
            for j in group:
                since = bats[j].isolated_since_s
                self._set(
                    j,
                    SeqState.DISCHARGING,
                    True,
                    t_s,
                    events,
                    kind="BatteryJoined",
                    reason="isolation take-over",
                    data={
                        "v_alone_v": v_alone,
                        "e_rest_v": e_rest,
                        "isolated_s": t_s - (since if since is not None else t_s),
                    },
                )
                bats[j].conduct_since_s = None
                bats[j].released_at_s = t_s
            return True
        return False

    def _r1(self, meas: Measurements, t_s: float, events: list[Event], reason: str) -> None:
        """R1: within ``v_th`` of the highest -> DISCHARGING (not yet engaged), else STANDBY."""
        present = [k for k, bm in enumerate(meas.batteries) if bm.present]
        if not present:
            return
        v_max = max(meas.batteries[k].voltage_v for k in present)
        for k in present:
            v = meas.batteries[k].voltage_v
            new = SeqState.DISCHARGING if v_max - v < self.config.v_th else SeqState.STANDBY
            self._set(k, new, False, t_s, events, reason=reason, data={"v": v, "v_max": v_max})
            self.state.batteries[k].conduct_since_s = None

    def _diode_rule(
        self,
        k: int,
        conducting: bool,
        t_s: float,
        dt_s: float,
        events: list[Event],
    ) -> bool:
        """R3/R4 timer for battery k. Returns True when the FET must be switched on now.

        Switches once conduction has lasted ``t_debounce``, or earlier if waiting one more
        period (``dt_s``) would overrun ``t_on``.
        """
        b = self.state.batteries[k]
        if not conducting:
            b.conduct_since_s = None
            return False
        if b.conduct_since_s is None:
            b.conduct_since_s = t_s
        elapsed = t_s - b.conduct_since_s
        cfg = self.config
        due = elapsed + _EPS_S >= cfg.t_debounce or elapsed + dt_s > cfg.t_on + _EPS_S
        if due:
            b.conduct_since_s = None
            path = "chg" if b.state is not SeqState.CHARGING else "dsg"
            events.append(
                Event(
                    t_s=t_s,
                    kind="DiodeBypassed",
                    battery=k,
                    message=f"battery {k}: {path} FET on after {elapsed:.3f} s of diode conduction",
                    data={"path": path, "conduction_s": elapsed},
                )
            )
        return due

    # ------------------------------------------------------------------ modes
    def _update_mode(self, meas: Measurements, events: list[Event]) -> None:
        st = self.state
        pack_i = sum(bm.current_a for bm in meas.batteries if bm.present)
        charging_seen = pack_i < -self.config.i_det
        if st.mode is SeqMode.DISCHARGE:
            # Docking is immediate; charging current alone must persist t_mode.
            evidence = charging_seen
            switch = meas.docked
            new = SeqMode.CHARGE
        else:
            evidence = not (meas.docked or charging_seen)
            switch = False
            new = SeqMode.DISCHARGE
        if not evidence:
            st.mode_evidence_since_s = None
        else:
            if st.mode_evidence_since_s is None:
                st.mode_evidence_since_s = meas.t_s
            persisted = meas.t_s - st.mode_evidence_since_s
            switch = switch or persisted + _EPS_S >= self.config.t_mode
        if not switch:
            return
        events.append(
            Event(
                t_s=meas.t_s,
                kind="ModeChanged",
                message=f"sequencing mode {st.mode.value} -> {new.value}",
                data={
                    "from": st.mode.value,
                    "to": new.value,
                    "docked": meas.docked,
                    "pack_current_a": pack_i,
                },
            )
        )
        st.mode = new
        st.mode_evidence_since_s = None
        st.initialized = False
        for b in st.batteries:
            b.conduct_since_s = None

    def _discharge_tick(
        self,
        meas: Measurements,
        dt_s: float,
        inserted: list[int],
        was: list[tuple[bool, bool]],
        events: list[Event],
    ) -> None:
        cfg = self.config
        st = self.state
        bats = st.batteries
        t = meas.t_s
        cur = [bm.current_a for bm in meas.batteries]
        volt = [bm.voltage_v for bm in meas.batteries]
        present = [bm.present for bm in meas.batteries]

        if not st.initialized:
            self._r1(meas, t, events, "R1 init")
            st.initialized = True
            inserted = []

        # Reverse current: a sibling is charging an engaged discharging battery. Only when some
        # other battery sources current; otherwise the charge comes from outside (mode logic).
        demoted: set[int] = set()
        for k, b in enumerate(bats):
            if b.state is SeqState.DISCHARGING and b.chg_on and cur[k] < -cfg.i_rev:
                feeder = any(cur[j] > cfg.i_det for j in range(len(bats)) if j != k and present[j])
                if feeder:
                    self._set(
                        k,
                        SeqState.STANDBY,
                        False,
                        t,
                        events,
                        kind="ReverseCurrent",
                        reason="charging current from a sibling",
                        data={"current_a": cur[k], "i_rev": cfg.i_rev},
                    )
                    b.conduct_since_s = None
                    demoted.add(k)

        # Hot insertion (R1 re-applied to the newcomer): a battery v_th above the bus takes over
        # and the batteries v_th below it stand by in the same period, so none is charged.
        for k in inserted:
            v_ref = self._v_ref(meas)
            if v_ref is None or volt[k] - v_ref < cfg.v_th:
                continue
            for j, bj in enumerate(bats):
                if bj.state is SeqState.DISCHARGING and volt[k] - volt[j] >= cfg.v_th:
                    self._set(
                        j, SeqState.STANDBY, False, t, events, reason=f"R1 battery {k} inserted"
                    )
            self._set(
                k,
                SeqState.DISCHARGING,
                False,
                t,
                events,
                reason="R1 inserted above bus",
                data={"v": volt[k], "v_ref": v_ref},
            )

        # Source isolation [REC]: an isolated battery merges, takes over or is forced back.
        self._release_isolated(meas, t, events)

        # Nobody admitted to discharge and no diode conducting: start over with R1.
        if not any(b.state is SeqState.DISCHARGING for b in bats) and not any(
            present[k] and cur[k] > cfg.i_det for k in range(len(bats))
        ):
            self._r1(meas, t, events, "R1 no battery discharging")

        # R2: a standby battery v_co above the bus reference joins. Not one demoted for reverse
        # current this period: its terminal voltage still carries the charging I*R rise.
        # At rest (no battery carries more than i_det) terminal voltages are open-circuit
        # voltages, so a joiner v_co above the engaged batteries would push about
        # (V_k - V_ref) / R_loop into them: it takes over instead, and they stay admitted with
        # their charge FETs open until the load brings the bus down to them (level rule).
        v_ref = self._v_ref(meas)
        idle = all(abs(cur[k]) <= cfg.i_det for k in range(len(bats)) if present[k])
        if v_ref is not None:
            standby = [
                k
                for k, b in enumerate(bats)
                if b.state is SeqState.STANDBY and b.isolated_since_s is None
            ]
            for k in sorted(standby, key=lambda j: -volt[j]):
                if k in demoted or volt[k] - v_ref < cfg.v_co:
                    continue
                if idle:
                    for bj in bats:
                        if bj.state is SeqState.DISCHARGING:
                            bj.chg_on = False
                self._set(
                    k,
                    SeqState.DISCHARGING,
                    idle,
                    t,
                    events,
                    kind="BatteryJoined",
                    reason="R2",
                    data={"v": volt[k], "v_ref": v_ref, "dv": volt[k] - v_ref, "idle": idle},
                )
                if idle:
                    v_ref = volt[k]

        # Rest merge [REC]: at rest (every battery at or below i_det for t_rest), a standby or
        # admitted battery whose voltage is within v_merge = i_merge * r_loop_ohm of every
        # engaged battery rejoins with its charge FET on, as R1 admits batteries within v_th at
        # power-up: closing it pushes at most about i_merge between them. Without it a battery
        # demoted by reverse current when the load stopped can only come back by R2 (it is
        # lower, so never) or R3 (its diode needs the bus 0.6 V below it, which the remaining
        # batteries alone may not reach before the load's own under-voltage lock-out cuts it).
        if idle:
            if st.rest_since_s is None:
                st.rest_since_s = t
        else:
            st.rest_since_s = None
        rested = st.rest_since_s is not None and t - st.rest_since_s + _EPS_S >= cfg.t_rest
        engaged_now = [
            volt[k] for k, b in enumerate(bats) if b.state is SeqState.DISCHARGING and b.chg_on
        ]
        if rested and engaged_now:
            lo, hi = min(engaged_now), max(engaged_now)
            for k in self._merge_candidates(demoted, volt):
                new_lo, new_hi = min(lo, volt[k]), max(hi, volt[k])
                if new_hi - new_lo > cfg.v_merge:
                    continue
                self._set(
                    k,
                    SeqState.DISCHARGING,
                    True,
                    t,
                    events,
                    kind="BatteryJoined",
                    reason="rest merge",
                    data={"v": volt[k], "v_lo": lo, "v_hi": hi, "v_merge": cfg.v_merge},
                )
                bats[k].conduct_since_s = None
                lo, hi = new_lo, new_hi

        # Load merge [REC]: under load, a standby (or admitted, not engaged) battery whose fast
        # voltage matches the engaged ones' (zero-load current into any of them <= i_merge and
        # none pushed past i_guard) closes its charge FET: it sources at once and the guard
        # would not open anybody. This is the rest merge with IR-compensated voltages; it brings
        # back a battery the guard opened as soon as the others have come down to it, before
        # R2 (v_co above the loaded bus) or R3 (a diode drop below it) would.
        if not idle and self._engaged():
            for k in self._merge_candidates(demoted, volt, present):
                group = sorted({*self._engaged(), k})
                pred = self._zero_load_into(group, meas)
                if pred[k] > cfg.i_merge or max(pred.values()) > cfg.i_guard:
                    continue
                self._set(
                    k,
                    SeqState.DISCHARGING,
                    True,
                    t,
                    events,
                    kind="BatteryJoined",
                    reason="load merge",
                    data={"v": volt[k], "predicted_a": pred[k], "i_merge": cfg.i_merge},
                )
                bats[k].conduct_since_s = None

        # Level rule: an admitted battery at or above the engaged batteries cannot be charged by
        # them *now*, so its charge FET may close directly (this completes an R2 join at once),
        # provided the cross-current guard agrees: under load a joiner v_co above the loaded
        # bus may still have a lower fast voltage (V + I*R) than an engaged battery, which would
        # charge it if the load vanished. Such a joiner stays admitted with its FET open (it
        # cannot be charged, its diode still lets it feed the bus) until the others have come
        # down to it.
        engaged_v = [
            volt[k] for k, b in enumerate(bats) if b.state is SeqState.DISCHARGING and b.chg_on
        ]
        if engaged_v:
            # Highest first, each compared with everything engaged so far, so two batteries
            # joining in the same period cannot close onto each other.
            v_eng = max(engaged_v)
            waiting = [
                k for k, b in enumerate(bats) if b.state is SeqState.DISCHARGING and not b.chg_on
            ]
            for k in sorted(waiting, key=lambda j: -volt[j]):
                if volt[k] >= v_eng and self._safe_to_close(k, meas, cfg.i_merge):
                    bats[k].chg_on = True
                    bats[k].conduct_since_s = None
                    v_eng = max(v_eng, volt[k])

        # R3: charge diode conducting (charge FET off, discharge FET on, discharge current).
        # Only current measured over a period in which this controller held the charge FET off
        # and the discharge FET on can have flowed through the diode.
        r3_closed: set[int] = set()
        for k, b in enumerate(bats):
            if b.state not in (SeqState.DISCHARGING, SeqState.STANDBY) or b.chg_on:
                b.conduct_since_s = None
                continue
            through_diode = was[k] == (False, True) and cur[k] > cfg.i_det
            if not self._diode_rule(k, through_diode, t, dt_s, events):
                continue
            if b.state is SeqState.STANDBY:
                self._set(
                    k,
                    SeqState.DISCHARGING,
                    True,
                    t,
                    events,
                    kind="BatteryJoined",
                    reason="R3",
                    data={"v": volt[k], "current_a": cur[k]},
                )
            else:
                b.chg_on = True
            r3_closed.add(k)
            if b.guard_opened:
                # The guard opened it and the load made its diode conduct anyway: keep it
                # engaged at this load instead of opening it every other period.
                b.hold_load_a = sum(c for c, p in zip(cur, present, strict=True) if p)
                b.guard_opened = False

        self._guard(meas, t, r3_closed, events)
        st.v_ref_v = self._v_ref(meas)

    def _charge_tick(
        self,
        meas: Measurements,
        dt_s: float,
        was: list[tuple[bool, bool]],
        events: list[Event],
    ) -> None:
        cfg = self.config
        st = self.state
        bats = st.batteries
        t = meas.t_s
        cur = [bm.current_a for bm in meas.batteries]
        present = [bm.present for bm in meas.batteries]
        if not st.initialized:
            for k, b in enumerate(bats):
                if present[k]:
                    self._set(k, SeqState.CHARGING, False, t, events, reason="charge mode")
                    b.conduct_since_s = None
            st.initialized = True
        for k, b in enumerate(bats):
            if present[k] and b.state is not SeqState.CHARGING:
                self._set(k, SeqState.CHARGING, False, t, events, reason="inserted while charging")
        # Mirror of the reverse-current rule: a charging battery feeding a sibling opens its
        # discharge FET, so its discharge diode blocks discharge again.
        for k, b in enumerate(bats):
            if b.state is SeqState.CHARGING and b.dsg_on and cur[k] > cfg.i_rev:
                sink = any(cur[j] < -cfg.i_det for j in range(len(bats)) if j != k and present[j])
                if sink:
                    b.dsg_on = False
                    b.conduct_since_s = None
                    events.append(
                        Event(
                            t_s=t,
                            kind="ReverseCurrent",
                            battery=k,
                            message=f"battery {k}: discharging into a sibling while charging",
                            data={"current_a": cur[k], "i_rev": cfg.i_rev, "path": "dsg"},
                        )
                    )
        # R4: discharge diode conducting (discharge FET off, charging current).
        for k, b in enumerate(bats):
            if b.state is not SeqState.CHARGING or b.dsg_on:
                b.conduct_since_s = None
                continue
            through_diode = was[k] == (True, False) and cur[k] < -cfg.i_det
            if self._diode_rule(k, through_diode, t, dt_s, events):
                b.dsg_on = True
        st.v_ref_v = None
        st.rest_since_s = None
        st.zero_load_into_a = None
        for b in bats:
            b.at_risk = False

    # ------------------------------------------------------------------ step
    def step(self, meas: Measurements, dt_s: float) -> ControlOutput:
        """One control period: validate, track presence and mode, apply the rules."""
        st = self.state
        events: list[Event] = []
        n = self.pack.n_batteries
        t = meas.t_s if math.isfinite(meas.t_s) else (st.last_t_s or 0.0)
        problem = self._validate(meas, dt_s)
        if problem:
            if st.mode is not SeqMode.FAULT:
                events.append(
                    Event(
                        t_s=t,
                        kind="Fault",
                        message=f"sequencing fail-safe: {problem}",
                        data={"reason": problem, "previous_mode": st.mode.value},
                    )
                )
                st.mode = SeqMode.FAULT
                st.fault_reason = problem
            same_n = len(meas.batteries) == n
            for k, b in enumerate(st.batteries):
                present = meas.batteries[k].present if same_n else b.state is not SeqState.OFF
                new = SeqState.STANDBY if present else SeqState.OFF
                self._set(k, new, False, t, events, reason="fail-safe")
                b.conduct_since_s = None
            st.initialized = False
            st.v_ref_v = None
            st.rest_since_s = None
            st.zero_load_into_a = None
            for b in st.batteries:
                b.at_risk = False
            return self._output(events)

        st.last_t_s = meas.t_s
        if st.mode is SeqMode.FAULT:
            events.append(
                Event(
                    t_s=t,
                    kind="FaultCleared",
                    message="sequencing measurements valid again, re-initialising (R1)",
                    data={"reason": st.fault_reason},
                )
            )
            st.mode = SeqMode.DISCHARGE
            st.mode_evidence_since_s = None
            st.initialized = False
            st.fault_reason = ""

        # FETs in force over the period the measurements cover (our previous commands).
        was = [(b.chg_on, b.dsg_on) for b in st.batteries]
        # Presence: removal -> OFF; insertion -> STANDBY (R1/R2 decide when it joins).
        inserted: list[int] = []
        for k, (b, bm) in enumerate(zip(st.batteries, meas.batteries, strict=True)):
            if not bm.present and b.state is not SeqState.OFF:
                self._set(k, SeqState.OFF, False, t, events, reason="removed")
                b.conduct_since_s = None
            elif bm.present and b.state is SeqState.OFF and st.initialized:
                self._set(k, SeqState.STANDBY, False, t, events, reason="inserted")
                inserted.append(k)

        self._update_resistance(meas)
        self._update_mode(meas, events)
        if st.mode is SeqMode.CHARGE:
            self._charge_tick(meas, dt_s, was, events)
        else:
            self._discharge_tick(meas, dt_s, inserted, was, events)
        return self._output(events)

    def _output(self, events: list[Event]) -> ControlOutput:
        st = self.state
        bats = st.batteries
        n = len(bats)
        return ControlOutput(
            commands=Commands(
                chg_on=tuple(b.chg_on for b in bats),
                dsg_on=tuple(b.dsg_on for b in bats),
            ),
            events=tuple(events),
            status={
                "seq_state": [b.state.value for b in bats],
                "seq_chg_on": [b.chg_on for b in bats],
                "seq_dsg_on": [b.dsg_on for b in bats],
                "seq_mode": [st.mode.value] * n,
                "seq_v_ref_v": [st.v_ref_v] * n,
                "seq_zero_load_into_a": list(st.zero_load_into_a or [0.0] * n),
                "seq_at_risk": [b.at_risk for b in bats],
                "seq_isolated": [b.isolated_since_s is not None for b in bats],
                "seq_diode_s": [
                    0.0
                    if b.conduct_since_s is None or st.last_t_s is None
                    else st.last_t_s - b.conduct_since_s
                    for b in bats
                ],
            },
        )


def battery_measurement(
    voltage_v: float, current_a: float, present: bool = True
) -> BatteryMeasurement:
    """A measurement carrying only what sequencing reads; other fields are unknown (NaN)."""
    nan = math.nan
    return BatteryMeasurement(
        voltage_v=voltage_v,
        current_a=current_a,
        temp_c=nan,
        min_cell_v=nan,
        max_cell_v=nan,
        soc=nan,
        full_capacity_ah=nan,
        remaining_capacity_ah=nan,
        present=present,
    )


__all__ = [
    "BatterySeq",
    "SeqMode",
    "SeqState",
    "SequencingConfig",
    "SequencingController",
    "SequencingState",
    "battery_measurement",
]
