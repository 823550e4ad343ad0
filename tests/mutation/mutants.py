"""Hand-listed single-point mutants of the safety rules (#18 §1).

Each mutant names its module (``src/packpilot/control/<module>/<file>``), a source snippet that
occurs exactly once in that file, and its replacement: a flipped comparison, a dropped
condition, a skipped timer or latch, a dropped clamp. Snippets, not line numbers, so that a
mutant survives edits around it; a snippet that no longer matches exactly once is reported as
*stale* (the list must follow the code, never silently skip).

``why`` says which rule the mutant breaks: the behavioural test that kills it checks that rule.

"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Mutant:
    module: str
    name: str
    old: str
    new: str
    why: str
    file: str = "rules.py"
    src: str = ""
    """A file under ``src/packpilot`` outside ``control/`` (config validation, publishers)."""

    @property
    def path(self) -> str:
        if self.src:
            return f"src/packpilot/{self.src}"
        if self.file.startswith("src/"):  # a rule outside control/ (the plant's BMU supply)
            return self.file
        return f"src/packpilot/control/{self.module}/{self.file}"


def _m(module: str, name: str, old: str, new: str, why: str) -> Mutant:
    return Mutant(module, name, old, new, why)


# fmt: off
LIMITS = [
    _m("limits", "violated-above-ge", "violating = v > prm.threshold[k]",
       "violating = v >= prm.threshold[k]", "a value exactly at the threshold violates"),
    _m("limits", "violated-below-le", "violating = v < prm.threshold[k]",
       "violating = v <= prm.threshold[k]", "a value exactly at the threshold violates"),
    _m("limits", "cleared-above-lt", "st.clear_ok[p, i, k] = v <= prm.reset[k]",
       "st.clear_ok[p, i, k] = v < prm.reset[k]", "exactly at reset does not clear"),
    _m("limits", "cleared-below-gt", "st.clear_ok[p, i, k] = v >= prm.reset[k]",
       "st.clear_ok[p, i, k] = v > prm.reset[k]", "exactly at reset does not clear"),
    _m("limits", "trip-keeps-chg-limit", "            lim_chg = 0.0\n",
       "            lim_chg = lim_chg\n", "a charge trip does not zero the charge limit"),
    _m("limits", "trip-keeps-dsg-limit", "            lim_dsg = 0.0\n",
       "            lim_dsg = lim_dsg\n", "a discharge trip does not zero the discharge limit"),
    _m("limits", "nan-clears-after-latch", "st.clear_ok[p, i, k] = False  # unknown",
       "st.clear_ok[p, i, k] = True  # unknown",
       "a NaN reading clears an active row once latch_s has passed"),
    _m("limits", "no-delay", "and st.held_s[p, i, k] >= prm.delay_s[k] - EPS",
       "and st.held_s[p, i, k] >= 0.0", "a row fires without its delay"),
    _m("limits", "no-latch", "and st.active_s[p, i, k] >= prm.latch_s[k] - EPS",
       "and st.active_s[p, i, k] >= 0.0", "a row clears before latch_s"),
    _m("limits", "no-debounce-restart",
       "                else:\n                    st.seen[p, i, k] = 0\n",
       "                else:\n                    pass\n",
       "a good sample does not restart the debounce"),
    _m("limits", "dsg-trip-keeps-path", "if dsg_trip:\n            put_dsg(cmd, p, i, False)",
       "if dsg_trip:\n            pass", "a discharge trip does not open the path"),
    _m("limits", "chg-trip-keeps-path", "if chg_trip:\n            put_chg(cmd, p, i, False)",
       "if chg_trip:\n            pass", "a charge trip does not open the path"),
    _m("limits", "charger-off-in-flight", "if docked and any_chg_trip:",
       "if any_chg_trip:", "the charger is commanded off while not docked"),
    _m("limits", "charger-stays-on", "if docked and any_chg_trip:",
       "if False:", "a docked charge trip leaves the charger on"),
    _m("limits", "cross-charge-not-charging",
       "st.ctx[p, W_CHARGING] = docked or (math.isfinite(cur) and cur < -band)",
       "st.ctx[p, W_CHARGING] = docked", "cross-charging by a sibling is not 'charging'"),
    _m("limits", "derate-ignored", "lim_chg *= prm.derate_fraction",
       "lim_chg *= 1.0", "a charge derate row does not scale the limit"),
    _m("limits", "pack-limit-strongest",
       "min_dsg = lim_dsg if n_dsg == 0 else fmin(min_dsg, lim_dsg)",
       "min_dsg = lim_dsg if n_dsg == 0 else fmax(min_dsg, lim_dsg)",
       "the pack discharge limit follows the strongest battery"),
]

PLAUSIBILITY = [
    _m("plausibility", "range-edges-exclusive", "not (lo <= x and x <= hi)",
       "not (lo < x and x < hi)", "a value exactly at a range edge is a fault"),
    _m("plausibility", "load-nan-unchecked",
       "    if not math.isfinite(load_a):\n", "    if False:\n",
       "a NaN load current is never checked"),
    _m("plausibility", "bus-nan-unchecked",
       "    if not math.isfinite(bus_v):\n", "    if False:\n",
       "a NaN bus voltage is never checked"),
    _m("plausibility", "current-nan-unchecked",
       "    if not math.isfinite(cur):\n        return (BAD, F_CURRENT, cur, V_SHOW)",
       "    if False:\n        return (BAD, F_CURRENT, cur, V_SHOW)",
       "a NaN battery current is never checked"),
    _m("plausibility", "stuck-without-load",
       "loaded = math.isfinite(cur) and abs(cur) >= prm.stuck_current_c * scale",
       "loaded = True", "a relaxed voltage at rest counts as stuck"),
    _m("plausibility", "stale-ge", "age > prm.max_sample_age_s",
       "age >= prm.max_sample_age_s", "a sample exactly max_sample_age_s old is stale"),
    _m("plausibility", "stale-switch-judged",
       "elif _stale(prm, m.bat.sample_age_s[p, i])[0] == BAD:", "elif False:",
       "a stale sample's switch feedback latches a switch fault"),
    _m("plausibility", "explained-switch-judged",
       "elif m.bat.sw_explained[p, i]:", "elif False:",
       "#26: a switch disagreement the node explains (its command timeout after lost "
       "commands) latches stuck-open faults that remove both batteries for good"),
    _m("plausibility", "no-persistence", "if not latched and bad_s >= delay - EPS:",
       "if not latched:", "a fault latches on the first bad sample"),
    _m("plausibility", "early-clear", "ok_s >= clear_after_s - EPS",
       "ok_s >= 0.0", "a fault clears on the first good sample"),
    _m("plausibility", "switch-fault-auto-clears", "k < N_SENSOR_KINDS, dt, prm.clear_after_s,",
       "True, dt, prm.clear_after_s,", "a switch fault clears by itself"),
    _m("plausibility", "last-source-isolated",
       "if docked or _other_source(st, tp, m, cmd, p, i):", "if True:",
       "a faulty last source is isolated in flight (drops the load)"),
    _m("plausibility", "reserve-after-the-break",
       "if conducts(tp, m, p, j, False) and _stays_on(tp, cmd, p, j):",
       "if conducts(tp, m, p, j, False):",
       "the reserve is brought in a step after the last trusted source opened (break first)"),
    _m("plausibility", "reserve-relay-opening-unseen",
       "return not (tp.relay[j] and cmd.chg_on[p, j] == 0)", "return True",
       "a relay opened by its charge command still counts as a source"),
    _m("plausibility", "reserve-untold",
       "if st.isolated[p, i] and not isolated and sensor_bad and not docked:", "if False:",
       "the platform is not told that the reserve now supplies the load"),
    _m("plausibility", "charger-into-unknown",
       "if unsafe and can_take_charge and conducts(tp, m, p, i, True):", "if False:",
       "the charger keeps charging into an unknown battery"),
    _m("plausibility", "sum-tolerance-unscaled",
       "abs(diff) > prm.sum_tolerance_v_per_group * groups",
       "abs(diff) > prm.sum_tolerance_v_per_group",
       "the voltage-sum tolerance is not scaled by the group count"),
]

CHARGING = [
    _m("charging", "s20-keeps-higher", "_set_row(st.new_members, p, st.new_first[p])",
       "_set_row(st.new_members, p, st.new_second[p])",
       "S20 connects the higher level instead of the lowest"),
    _m("charging", "s20-exit-on-highest",
       "if keep and stage == S20:\n                    keep = lo < st.vr1_v[p]",
       "if keep and stage == S20:\n                    keep = hi < st.vr1_v[p]",
       "S20 ends when its highest battery reaches Vr1, leaving the lower ones short"),
    _m("charging", "regroup-without-tolerance", "est[i] <= hi + prm.eps_eq",
       "est[i] <= hi", "a battery within eps_eq of the connected level does not regroup"),
    _m("charging", "cell-limit-gt", "if cell >= prm.cell_v_limit_v:",
       "if cell > prm.cell_v_limit_v:", "a cell exactly at the limit keeps charging"),
    _m("charging", "negative-r-accepted", "if 0.0 <= r_step <= prm.r_comp_max_ohm:",
       "if r_step <= prm.r_comp_max_ohm:", "a negative resistance estimate is accepted"),
    _m("charging", "undock-keeps-session", "st.done[p].fill(DONE_NONE)  # the session ends",
       "pass  # the session ends", "undocking keeps the session's full batteries"),
    _m("charging", "no-overvoltage-stop",
       "elif v >= prm.v_sat + prm.overvoltage_margin:", "elif False:",
       "an over-voltage battery keeps charging"),
    _m("charging", "invalid-kept", "        valid[i] = ok\n", "        valid[i] = here\n",
       "a battery with a non-finite reading stays in the sort"),
    _m("charging", "charger-fault-ignored",
       "            go = False\n        elif st.stage[p] == FAULT:",
       "            go = True\n        elif st.stage[p] == FAULT:",
       "a charger fault does not stop charging"),
    _m("charging", "fault-clears-at-once",
       "if st.fault_clear_s[p] < prm.charger_fault_clear_s:", "if False:",
       "charging resumes before the charger reported healthy for fault_clear_s"),
    _m("charging", "no-dock-rest", "st.rested[p] = st.session_s[p] >= prm.dock_rest_s",
       "st.rested[p] = True", "charging starts without the dock rest"),
    Mutant("charging", "fixed-d1-eps-defaults", "out[name] = min(base, share * float(dv1))",
           "out[name] = base", "d1_v / eps_eq_v defaults do not scale: ΔV1 = 0.5 V is refused",
           src="config/charging.py"),
    _m("charging", "join-onto-any-bus", "if top < 0 or hi <= bus:", "if True:",
       "a relay closes although its battery would discharge into the others (issue #24 "
       "item 3)"),
    _m("charging", "join-on-polarized-bus", "if known and g > 0.0:\n",
       "if False:\n",
       "a join trusts the bus measured now, polarization included (issue #24 item 3)"),
    _m("charging", "s30-ends-at-merge",
       "keep = lo < st.vt_v[p] - prm.reach_tol\n",
       "keep = lo < st.vt_v[p] - prm.reach_tol and hi - lo > prm.eps_eq\n",
       "S30 ends when its groups merge, short of Vt (issue #24 item 4)"),
]

QUALITY = [
    Mutant("quality", "held-share-counts-engaged", "    held = sel_f & ~both\n",
           "    held = sel_f\n",
           "the controller is judged on a load split the plant makes with every battery engaged",
           src="sim/quality.py"),
]

PUBLISH = [
    Mutant("publish", "time-to-trip-nan-first", "time_to_trip_s=soonest(ttt),",
           "time_to_trip_s=min(ttt),",
           "a standby battery listed first (NaN) hides the other battery's coming trip",
           src="runtime/publish.py"),
]

POWER = [
    _m("power", "cutoff-ignored",
       "    if cur > 0.0 and cell - inp.low_cell_v[p, s] < prm.cell_v_min[s]:",
       "    if False and cell - inp.low_cell_v[p, s] < prm.cell_v_min[s]:",
       "state of power lets a discharging battery cross its cut-off"),
    _m("power", "lowest-cell-ignored",
       "    if cur > 0.0 and cell - inp.low_cell_v[p, s] < prm.cell_v_min[s]:",
       "    if cur > 0.0 and cell < prm.cell_v_min[s]:",
       "the average cell, not the lowest, is held above the cut-off"),
    _m("power", "cell-max-ignored",
       "    if cur < 0.0 and cell + inp.high_cell_v[p, s] > prm.cell_v_max[s]:",
       "    if False:",
       "a charging battery's highest cell may pass its maximum"),
    _m("power", "share-limit-ignored",
       "        if cur > inp.limit_dsg_a[p, s] or -cur > inp.limit_chg_a[p, s]:\n"
       "            return _fail(wk, p, WHY_CURRENT, s)\n    for s",
       "        if -cur > inp.limit_chg_a[p, s]:\n"
       "            return _fail(wk, p, WHY_CURRENT, s)\n    for s",
       "a battery's share of the pack current may exceed its discharge limit (N x weakest)"),
    _m("power", "no-polarisation-buildup",
       "    wk.v1[p, s] = wk.v1[p, s] * a1 + inp.r1_ohm[p, s] * scale * cur * (1.0 - a1)",
       "    wk.v1[p, s] = wk.v1[p, s] * a1",
       "the RC branch does not charge over the horizon: a 30 s limit as large as a 2 s one"),
    _m("power", "hot-discharge-allowed",
       "    if cur > 0.0 and wk.temp[p, s] > prm.temp_max_dsg_c[s]:",
       "    if False:",
       "a battery above its temperature limit still gets a discharge limit"),
    _m("power", "cold-charge-allowed",
       "    if cur < 0.0 and wk.temp[p, s] < prm.temp_min_chg_c[s]:",
       "    if False:",
       "a battery below its charge temperature still gets a charge limit"),
    _m("power", "diode-drop-ignored",
       "            wk.ddrop[p, s] = 0.0 if chg else prm.diode_drop_v[s]",
       "            wk.ddrop[p, s] = 0.0",
       "a battery discharging through a body diode is predicted without its drop"),
    _m("power", "no-warming",
       "        e = _x(inp.r_per_k[p, s], wk.temp[p, s] - inp.temp_c[p, s])",
       "        e = 0.0",
       "the resistance of a warming battery is held (a cold pack's limit is underestimated "
       "and its split mispredicted)"),
    _m("power", "join-peak-after-first-step",
       "        if abs(cur) > abs(peak):\n            peak = cur",
       "        if k > 0 and abs(cur) > abs(peak):\n            peak = cur",
       "the join's peak (the instant of closing, RC branches as shorts) is missed"),
    _m("power", "join-ignores-other-batteries",
       "        if s != j and (wk.peak_pos[p, s] > inp.limit_dsg_a[p, s]",
       "        if False and (wk.peak_pos[p, s] > inp.limit_dsg_a[p, s]",
       "the admissible dV lets the joining battery overcharge the others"),
    Mutant("power", "dcl-ignores-state-of-power",
           "            dcl = min(dcl, float(self.sop.pack_dsg_a[0, HORIZON_CCL]))",
           "            dcl = dcl",
           "the inverter is told N x weakest although the split allows less",
           src="runtime/publish.py"),
    _m("power", "series-ohm-ignored",
       "        r = wk.r0[p, s] + prm.series_ohm[s]",
       "        r = wk.r0[p, s]",
       "a battery's leads, connectors and shunt are left out of its branch: the split, a "
       "join's peak and the bus are predicted without them (#27)"),
    Mutant("power", "series-ohm-not-told",
           "series_ohm=[battery_series_ohm(b, c) for b, c in zip(bats, sets, strict=True)],",
           "series_ohm=None,",
           "the prediction is not told the batteries' series_ohm the plant has",
           src="sim/power.py"),
    Mutant("power", "stated-resistance-at-ambient",
           "    r0 = cell_rc(prm, min(max(soc, 0.0), 1.0), b.resistance_temp_c, 0.0).r0_ohm",
           "    r0 = cell_rc(prm, min(max(soc, 0.0), 1.0), cfg.pack.ambient_c, 0.0).r0_ohm",
           "the core's cell-set R0 holds a stated resistance at the ambient, not at its "
           "reference temperature (1.8 x too low at 5 degC: a limit too high)",
           src="sim/power.py"),
    Mutant("power", "observer-polarisation-ignored",
           "    if pol is not None and math.isfinite(pol[i]):",
           "    if False:",
           "the limits ignore the polarisation the observer sees after a heavy load",
           src="sim/power.py"),
]

BMU = [
    Mutant("bmu", "no-dock-restart", "back = ~self.bmu_on & (dock | (",
           "back = ~self.bmu_on & (False | (",
           "the dock does not bring a browned-out BMU back (issue #24 item 5)",
           "src/packpilot/model/pack.py"),
    Mutant("bmu", "aux-below-empty", "out = self.bmu_on & ~dock & ((v < cut) | empty)",
           "out = self.bmu_on & ~dock & (v < cut)",
           "an empty aux battery keeps the BMU up (issue #24 item 5)",
           "src/packpilot/model/pack.py"),
    Mutant("bmu", "bmu-runs-while-down", "        if powered.all():\n",
           "        if True:\n",
           "a browned-out BMU still decides and logs stages (issue #24 item 5)",
           "src/packpilot/sim/loop.py"),
]

PROTECTION = [
    _m("protection", "trip-keeps-path",
       "if st.tripped[p, i]:\n            put_dsg(cmd, p, i, False)",
       "if st.tripped[p, i]:\n            pass", "a trip does not open the discharge path"),
    _m("protection", "counts-while-not-discharging", "if below and st.discharging[p, i]:",
       "if below:", "time below the cut-off counts without discharge"),
    _m("protection", "le-ignored", "return v_chk <= cut if prm.voltage_le else v_chk < cut",
       "return v_chk < cut", "exactly at the cut-off is not 'below' under voltage_le"),
    _m("protection", "trip-ge-ignored", "if an > m_den or (prm.trip_ge and an == m_den):",
       "if an > m_den:", "reaching exactly m does not trip under trip_ge"),
    _m("protection", "recovery-no-reset", "elif not below and prm.reset_on_recovery:",
       "elif False:", "recovery does not reset the accumulator"),
    _m("protection", "charge-no-new-cycle",
       "_new_cycle(st, p, i, RESET_CHARGE, t_s, ev, src)", "pass",
       "sustained charging does not start a new cycle"),
    _m("protection", "unknown-not-conservative", "            if not known:\n",
       "            if False:\n", "an unknown status does not get the most conservative row"),
    _m("protection", "conservative-lowest-cut", "cut > best_cut or",
       "cut < best_cut or", "the 'most conservative' row has the lowest cut-off"),
    _m("protection", "fallback-strongest-group", "g_min = fmin(g_min, x)",
       "g_min = fmax(g_min, x)", "the fallback voltage reads the strongest group"),
    _m("protection", "no-hysteresis", "                prm.use_hysteresis\n",
       "                False\n", "row changes ignore the hysteresis band"),
    _m("protection", "reinsert-keeps-cycle", "if prm.reset_on_reinsert:", "if False:",
       "a re-inserted battery keeps its accumulator"),
]

SUPERVISOR = [
    _m("supervisor", "join-limit-ignored", "if math.isfinite(vi) and hi - lo <= limit:",
       "if math.isfinite(vi):", "a relay closes onto batteries far apart"),
    _m("supervisor", "join-limit-lt", "if math.isfinite(vi) and hi - lo <= limit:",
       "if math.isfinite(vi) and hi - lo < limit:", "exactly the limit is refused"),
    _m("supervisor", "nan-voltage-joins", "if math.isfinite(vi) and hi - lo <= limit:",
       "if not math.isfinite(vi) or hi - lo <= limit:", "a battery of unknown voltage joins"),
    _m("supervisor", "seed-ignores-limit",
       "            if v[p, st.order[p, b]] - lo <= prm.join_limit_v:\n                n += 1",
       "            if True:\n                n += 1",
       "the first group on an empty bus ignores the join limit"),
    _m("supervisor", "charger-on-outside-charge", "if mode != CHARGE:\n        put_charger_off",
       "if mode == FAULT:\n        put_charger_off", "the charger may run outside CHARGE"),
    _m("supervisor", "shutdown-keeps-paths", "if mode == SHUTDOWN:\n        for i",
       "if False:\n        for i", "SHUTDOWN leaves the paths alone"),
    _m("supervisor", "no-fault-hold", "if st.since_fault_s[p] < prm.fault_hold_s:",
       "if False:", "a fault does not hold the FAULT mode"),
    _m("supervisor", "reset-ignored",
       "if cls & CLS_RESET and 0 <= b < n_b:\n            st.tripped[p, b] = False",
       "if cls & CLS_RESET and 0 <= b < n_b:\n            st.tripped[p, b] = True",
       "a reset does not un-trip the battery"),
    _m("supervisor", "no-init-wait", "if st.t_in_mode_s[p] + dt_s < prm.init_time_s:",
       "if False:", "INIT ends at once"),
]

SOC = [
    _m("soc", "no-clamp",
       "st.soc[p, i] = fmin(1.0, fmax(0.0, st.soc[p, i] + counted))",
       "st.soc[p, i] = st.soc[p, i] + counted",
       "coulomb counting leaves 0..1"),
    _m("soc", "sign-flipped", "    counted = -cur * dt / (3600.0",
       "    counted = cur * dt / (3600.0", "discharge raises the SOC"),
    _m("soc", "no-rest-reset", "    if abs(cur) >= prm.rest_current_a:\n",
       "    if False:\n", "load does not restart the rest clock"),
    _m("soc", "nan-current-counted",
       "    if not math.isfinite(cur):\n        st.rest_s[p, i] = 0.0",
       "    if False:\n        st.rest_s[p, i] = 0.0", "a NaN current is counted"),
    _m("soc", "no-rest-wait", "if st.rest_s[p, i] < st.next_fix_s[p, i] - EPS:",
       "if False:", "the OCV correction does not wait for rest_time_s"),
    _m("soc", "blend-ignored", "(1.0 - prm.blend) * before + prm.blend * ocv_soc",
       "ocv_soc", "the OCV correction ignores blend"),
    _m("soc", "ocv-unclamped", "return fmin(1.0, fmax(0.0, s))", "return s",
       "the OCV lookup leaves 0..1"),
    _m("soc", "observer-no-fallback", "if prm.observer and st.obs_ok[p, i]:", "if prm.observer:",
       "a diverged observer stays the SOC source (issue #28)"),
    _m("soc", "observer-never-diverges",
       "bad = not _finite_state(st, p, i) or not (st.nis_avg[p, i] <= prm.nis_limit)",
       "bad = not _finite_state(st, p, i)", "the innovation window test never fails"),
    _m("soc", "observer-resumes-at-once",
       "elif not st.obs_ok[p, i] and st.obs_age_s[p, i] >= prm.nis_window_s - EPS:",
       "elif not st.obs_ok[p, i]:", "a restarted observer is the source before a window"),
    _m("soc", "cutoff-no-polarisation", "    v_ss = r1 * cur\n", "    v_ss = 0.0\n",
       "time to cut-off ignores the polarisation at the load"),
    _m("soc", "cutoff-no-r0", "    return ocv - r0 * cur - v1\n", "    return ocv - v1\n",
       "time to cut-off ignores the ohmic drop"),
    _m("soc", "load-not-averaged",
       "a = fmin(1.0, dt / fmin(prm.load_tau_s, st.load_age_s[p, i]))", "a = 1.0",
       "the predictions follow the instantaneous load (jumpy)"),
    _m("soc", "time-to-go-no-soc",
       "left_ah = st.shown_soc[p, i] * st.x[p, i, ob.X_CAP]", "left_ah = st.x[p, i, ob.X_CAP]",
       "time to go ignores the SOC"),
    # issue #28, h28ttf: time to full to the end of a CC/CV charge (replaces time-to-full-sign,
    # whose constant-current rule is gone; that rule is the first mutant below)
    _m("soc", "time-to-full-constant-current",
       "    st.time_to_full_s[p, i] = time_to_full(prm, st, m, p, i, -avg, elapsed, temp)\n",
       "    st.time_to_full_s[p, i] = ((1.0 - st.shown_soc[p, i]) * st.x[p, i, ob.X_CAP] * 3600.0"
       " / -avg if avg <= -prm.rest_current_a else math.nan)\n",
       "the pre-h28ttf rule: the missing charge at constant current to 100 %, no CV taper"),
    _m("soc", "time-to-full-no-taper",
       "    return hi + cv_taper_s(prm, st, p, i, soc, v1, -chg_a, t_cv, q)\n",
       "    return hi\n", "time to full ends where the CV phase begins"),
    _m("soc", "time-to-full-weakest-cell",
       "    soc0 = fmax(soc0, mean) if math.isfinite(mean) else soc0\n", "",
       "the CV voltage judged on the weakest cell, not the battery's mean cell"),
    _m("soc", "time-to-full-no-countdown",
       "        st.cv_left_s[p, i] = fmax(0.0, st.cv_left_s[p, i] - elapsed_s)\n", "",
       "the CV phase's taper is never counted down"),
    # issue #28, h28full: the charge path, the exact taper and its temperature
    _m("soc", "time-to-full-taper-no-charge-path",
       "    rp: float = prm.full_path_ohm[i]\n    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, "
       "prm.ax_s, temp, soc) + rp\n    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, "
       "soc)\n    _v, slope",
       "    rp: float = 0.0\n    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, "
       "prm.ax_s, temp, soc) + rp\n    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, "
       "soc)\n    _v, slope",
       "the CV taper on the bare cell, without the charge path's resistance"),
    _m("soc", "time-to-full-cc-no-charge-path",
       "    rp: float = prm.full_path_ohm[i]\n    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, "
       "prm.ax_s, temp, soc) + rp\n    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, "
       "soc)\n    tau",
       "    rp: float = 0.0\n    r0 = rs * ob.table2(prm.r0_tab, prm.ax_t, "
       "prm.ax_s, temp, soc) + rp\n    r1 = rs * ob.table2(prm.r1_tab, prm.ax_t, prm.ax_s, temp, "
       "soc)\n    tau",
       "the CC phase ends when the cell terminals, not the charger, reach the CV voltage"),
    _m("soc", "time-to-full-taper-implicit-euler",
       "        c1, l1, c2, l2 = _taper_modes(r0, r1, tau, a, cur, v1)\n",
       "        k = h / tau\n"
       "        nxt = (r0 * cur + k * v1 / (1.0 + k)) / (r0 + h * a + k * r1 / (1.0 + k))\n"
       "        if nxt >= i_end:\n"
       "            return t + h * (i_end - cur) / (nxt - cur)\n"
       "        v1 = (v1 + k * r1 * nxt) / (1.0 + k)\n"
       "        soc -= nxt * h / (3600.0 * q)\n"
       "        cur = nxt\n"
       "        t += h\n"
       "        continue\n"
       "        c1, l1, c2, l2 = _taper_modes(r0, r1, tau, a, cur, v1)\n",
       "the pre-h28full taper: implicit Euler at an eighth of its time constant (5 % long)"),
    _m("soc", "time-to-full-taper-present-temp",
       "    t_cv = fmin(temp, 0.5 * (temp + st.chg_temp0_c[p, i]))\n", "    t_cv = temp\n",
       "the taper at the present temperature, as if the cells did not cool as it falls"),
    # issue #28, h28soc: what the observer reads and counts
    Mutant("soc", "ocv-no-temperature", "    ocv = ocv + dtemp * (d0 + (d1 - d0) * fs)\n",
           "    ocv = ocv + 0.0 * dtemp\n",
           "the observer's OCV ignores the cell set's entropic term", file="observer.py"),
    Mutant("soc", "capacity-not-learned", "    fm[p, i, X_SOC, X_CAP] = ic * k_ah / q\n",
           "    fm[p, i, X_SOC, X_CAP] = 0.0\n",
           "the capacity state never learns from the charge counted", file="observer.py"),
    # issue #28, h28cold: the OCV term over the SOC's uncertainty (staged-charging misses)
    Mutant("soc", "ocv-point-linearisation", "    if not (var_soc > 0.0):\n        return f0,",
           "    if True:\n        return f0,",
           "the OCV linearised at the SOC's point estimate (over-confident on the OCV's foot)",
           file="observer.py"),
    Mutant("soc", "ocv-spread-no-variance", "    s = var_v + lin_var\n",
           "    s = var_v + 0.0 * lin_var\n",
           "the OCV averaged over the SOC's spread, its curvature not counted as noise",
           file="observer.py"),
    # issue #28, h28cold2: the point OCV predicted, the curvature's bias counted as noise
    Mutant("soc", "ocv-spread-mean", "    return f0, slope, max(0.0,",
           "    return mean, slope, -((mean - f0) ** 2) + max(0.0,",
           "the spread's mean OCV predicted (a right SOC reads the curvature's bias as news)",
           file="observer.py"),
    _m("soc", "insertion-keeps-stale-belief",
       "    if st.absent[p, i]:  # inserted: its first reading is open-circuit, it tells its SOC",
       "    if False:  # inserted: its first reading is open-circuit, it tells its SOC",
       "an inserted battery keeps the slot's stale belief (shown for a whole window)"),
    # issue #28, h28cut: time to cut-off within 10 % near the trip (cutoff-capacity-state
    # is gone: the capacity state is the rule again, h28soc's SOC-rate capacity removed)
    _m("soc", "cutoff-stale-between-predictions",
       "        if st.time_to_cutoff_s[p, i] > 0.0:\n",
       "        if False:\n",
       "the time to cut-off is not counted down between its 1 s predictions (read stale)"),
    _m("soc", "cutoff-no-reading-offset", "        vc = vc - res\n", "        vc = vc\n",
       "the cut-off level ignores the reading's recent offset from the model"),
    _m("soc", "cutoff-no-gust-margin", "        vc = vc + r0 * exc\n", "        vc = vc\n",
       "the cut-off level ignores the load's gusts above its average"),
    _m("soc", "cutoff-not-smoothed",
       "        raw = shown + fmin(1.0, elapsed / prm.cutoff_tau_s) * (raw - shown)\n",
       "        raw = raw + 0.0 * shown\n",
       "each new time-to-cut-off prediction is shown at once (its jitter shows)"),
    _m("soc", "equalizer-current-ignored",
       "    return float(cur + p_in / v_sum - st.bal_a[p, i, g])\n", "    return cur\n",
       "the observer counts only the battery current, not the equalizers' into its group"),
    _m("soc", "weak-group-no-hysteresis",
       "    if prev_v - best_v < WEAK_HYST_V:", "    if prev_v - best_v < 0.0:",
       "the group the observer reads follows the noise on a flat OCV (h28lfp)"),
    # issue #28, h28mis: the polarisation's prior at an open-circuit start; the offset state
    _m("soc", "v1-prior-wide-at-ocv-start",
       "    st.cov[p, i, ob.X_V1, ob.X_V1] = V1_SIGMA0_OCV_V * V1_SIGMA0_OCV_V\n",
       "    st.cov[p, i, ob.X_V1, ob.X_V1] = 0.05 * 0.05\n",
       "a start from an OCV reading keeps the 50 mV polarisation prior (an inrush read as SOC)"),
    Mutant("soc", "offset-not-estimated", "        default=0.3,\n", "        default=0.0,\n",
           "the current-sensor offset is not estimated by default (the capacity absorbs it)",
           file="src/packpilot/config/soc.py"),
    # issue #28, eighth session: trusted and wrong on a real log; a reinserted battery's counter
    _m("soc", "consistency-unchecked",
       "    elif prm.consistency_sigma > 0.0 and z > prm.consistency_sigma:\n",
       "    elif False:\n",
       "an observer far outside the coulomb counter's reach stays trusted (its model is wrong)"),
    _m("soc", "fallback-stale-after-insertion",
       "        st.fb_absent[p, i] = False\n        st.soc[p, i] = math.nan\n",
       "        st.fb_absent[p, i] = False\n",
       "a reinserted battery's coulomb counter keeps the slot's old SOC"),
    _m("soc", "cell-set-mismatch-not-gated",
       "    elif st.misfit[p, i] > ob.R_SCALE_MAX:", "    elif False:",
       "an observer whose cell set's R0 is beyond its reach is trusted"),
    _m("soc", "cell-set-mismatch-never-read", "    if not (r > STEP_RATIO * r_set):",
       "    if True:", "a battery far from its cell set is never named"),
]

EQUALIZATION = [
    _m("equalization", "hi-keeps-lo-timer", "hi[p, i, g] += ts_s\n            lo[p, i, g] = 0.0",
       "hi[p, i, g] += ts_s", "a lagging group keeps its leading timer"),
    _m("equalization", "t1-halved", "if not hi[p, i, g] >= prm.t1_s - SAMPLE_TOL:",
       "if not hi[p, i, g] >= 0.5 * prm.t1_s - SAMPLE_TOL:", "formula 1 fires before t1"),
    _m("equalization", "formula1-no-average", "return (ah + n_ah) / 2.0",
       "return ah + n_ah", "formula 1 does not average toward N"),
    _m("equalization", "no-subtract-min", "    if subtracted:\n        low",
       "    if False:\n        low", "the minimum is not subtracted"),
    _m("equalization", "bad-input-not-held", "        if not ok:\n            # Hold",
       "        if False:\n            # Hold", "a bad input does not hold the string"),
    _m("equalization", "gate-ignores-min-current",
       "if mag < prm.min_current_a or mag == 0.0:", "if mag == 0.0:",
       "equalizers run below the minimum string current"),
    _m("equalization", "owed-never-lowered",
       "            granted[p, i, g] += a - owed[p, i, g]\n            owed[p, i, g] = a\n",
       "            if a > owed[p, i, g]:\n                granted[p, i, g] += a - owed[p, i, g]\n"
       "                owed[p, i, g] = a\n",
       "formula 2 / the subtraction lower AH but not what the group is still owed (#24)"),
    _m("equalization", "above-average-charged", "if q <= 0.0 or not dvs[p, i, g] > 0.0:",
       "if q <= 0.0:", "a group above the string average keeps receiving what it is owed"),
    _m("equalization", "last-step-overdelivers", "cur[p, i, g] = q * 3600.0 / dt",
       "cur[p, i, g] = i_eq", "the last partial step delivers more than owed"),
    _m("equalization", "zero-voltage-accepted", "if not math.isfinite(v) or v <= 0.0:",
       "if not math.isfinite(v):", "a zero group voltage is used"),
]

SEQUENCING = [
    _m("sequencing", "r1-le", "new = DISCHARGING if v_max - volt[k] < prm.v_th else STANDBY",
       "new = DISCHARGING if v_max - volt[k] <= prm.v_th else STANDBY",
       "R1: a battery exactly v_th below the highest is admitted"),
    _m("sequencing", "r1-admits-all",
       "new = DISCHARGING if v_max - volt[k] < prm.v_th else STANDBY", "new = DISCHARGING",
       "R1: a battery far below the highest is admitted (cross-charge)"),
    _m("sequencing", "r2-never-joins", "            if e_ref - ef[k] >= prm.v_co:\n",
       "            if True:\n", "R2: a standby battery never joins once the voltages meet"),
    _m("sequencing", "r2-joins-early", "            if e_ref - ef[k] >= prm.v_co:\n",
       "            if e_ref - ef[k] >= 10.0 * prm.v_co:\n",
       "R2: a standby battery joins while still well below the others"),
    _m("sequencing", "time-backwards-accepted", "elif not math.isnan(last) and t < last:",
       "elif False:", "a sample older than the last one is used (no fail-safe)"),
    _m("sequencing", "negative-voltage-accepted", "if not math.isfinite(v) or v < 0.0:",
       "if not math.isfinite(v):", "a negative battery voltage is used"),
    _m("sequencing", "reverse-cut-dropped",
       "if cur[k] < -prm.i_rev or rev_q_as[p, k] > prm.q_rev_as + 1e-12:", "if False:",
       "reverse current into an engaged battery is never cut (embodiment 5)"),
    _m("sequencing", "reverse-cut-one-feeder", "                fed += cur[j]\n",
       "                fed = max(fed, cur[j])\n",
       "the reverse cut needs one sibling above i_det (many small feeders are missed)"),
    _m("sequencing", "reverse-cut-current-only",
       "if cur[k] < -prm.i_rev or rev_q_as[p, k] > prm.q_rev_as + 1e-12:",
       "if cur[k] < -prm.i_rev:", "a small circulating reverse current is never cut"),
    _m("sequencing", "trickle-needs-i-det", "        if fed <= 0.0:\n",
       "        if fed <= i_det:\n",
       "a sibling trickling less than i_det into an engaged battery is never cut (#24)"),
    _m("sequencing", "engage-no-margin",
       "            if pred[j] > prm.charge_limit_margin * i_lim[j]:\n",
       "            if pred[j] > i_lim[j]:\n",
       "engage lets the zero-load prediction reach the limit itself (no room for its error)"),
    _m("sequencing", "risk-flag-no-margin",
       "risk = pred[k] > prm.charge_limit_margin * i_lim[k] or (",
       "risk = pred[k] > i_lim[k] or (",
       "the zero-load risk flag is raised only above the limit itself"),
    _m("sequencing", "risk-flag-no-hysteresis",
       "at_risk[p, k] and pred[k] > prm.risk_clear_ratio * i_lim[k]", "False",
       "the zero-load risk flag drops as soon as the estimate dips under the limit"),
    _m("sequencing", "engage-ignores-zero-load",
       "            if pred[j] > prm.charge_limit_margin * i_lim[j]:\n",
       "            if False:\n",
       "engage closes a charge FET that would take more than its limit if the load vanished"),
    _m("sequencing", "engage-no-hysteresis", "if j != k and pred[j] > 0.5 * prm.i_rev:",
       "if False:", "engage closes a charge FET that would charge a sibling (close-cut chatter)"),
    _m("sequencing", "r3-no-deadline",
       "due: bool = elapsed + EPS_S >= prm.t_debounce or elapsed + dt > prm.t_on + EPS_S",
       "due: bool = elapsed + EPS_S >= prm.t_debounce",
       "R3/R4: waiting one more period may overrun t_on"),
    _m("sequencing", "r3-counts-own-current",
       "through = (not was_c[k]) and was_d[k] and cur[k] > i_det",
       "through = was_d[k] and cur[k] > i_det",
       "R3: current through a closed charge FET is taken for diode conduction"),
    _m("sequencing", "no-handover", "    if any_r3:\n        _open_charged",
       "    if False:\n        _open_charged",
       "R3 closes the higher battery and the lower sibling stays engaged (it is charged)"),
    _m("sequencing", "no-cascade", "    if any_cut:\n        _open_charged",
       "    if False:\n        _open_charged",
       "after a reverse cut the next engaged battery takes the same current"),
    _m("sequencing", "hot-insert-no-standby",
       "if state[p, j] == DISCHARGING and volt[k] - volt[j] >= prm.v_th:", "if False:",
       "a higher hot-inserted battery charges the admitted lower ones"),
    _m("sequencing", "charge-mode-no-mirror",
       "if state[p, k] == CHARGING and dsg_on[p, k] and cur[k] > prm.i_rev:", "if False:",
       "charge mode: a battery feeding a charging sibling keeps its discharge FET on"),
    _m("sequencing", "close-out-dropped",
       "if cmd.dsg_on[p, k] == 0 and not relay and not charge:", "if False:",
       "a tripped battery keeps its charge FET on (a sibling charges it through the diode)"),
    _m("sequencing", "held-open-not-noted",
       "held[p, k] = cmd.dsg_on[p, k] == 0 and st.dsg_on[p, k] and not relay",
       "held[p, k] = False and not relay",
       "#26: a battery another layer held open stays DISCHARGING and engaged; its release "
       "closes both FETs at once and the rested battery charges its sibling above the limit"),
    _m("sequencing", "held-open-stays-engaged",
       "            _set(sw, ev, src, p, k, STANDBY, False, t, SET, R_HELD)\n",
       "            pass\n",
       "#26: a battery held open is not stood by: its release connects it directly"),
    _m("sequencing", "fail-safe-keeps-fets",
       "_set(sw, ev, src, p, k, new, False, t, SET, R_FAIL_SAFE)",
       "_set(sw, ev, src, p, k, DISCHARGING if present else OFF, True, t, SET, R_FAIL_SAFE)",
       "invalid measurements leave the charge FETs on"),
    _m("sequencing", "mode-evidence-raw-current",
       "tot += c if can_charge[k] or not c < 0.0 else 0.0", "tot += c",
       "#26: a standby battery's implausible negative current (its charge path open) puts "
       "the pack in charge mode and opens the healthy battery's discharge FET"),
    _m("sequencing", "zero-load-observer-ignored",
       "        if status[p, k, s_ok] == 1.0 and 0.0 < r0 <= r_max:\n", "        if False:\n",
       "#28: the zero-load prediction keeps the -dV/dI resistance, which takes in the "
       "polarisation after a long heavy load, although the observer's R0 is trusted"),
    _m("sequencing", "zero-load-source-with-polarisation-r",
       "            ez[k] = volt[k] + cur[k] * r0\n", "            ez[k] = ef[k]\n",
       "#28: the source voltage behind R0 is V + I x r with the polarised -dV/dI r"),
    _m("sequencing", "zero-load-open-dropped",
       "    _open_predicted(prm, st, ev, src, p, t)\n", "    pass\n",
       "#28 rule 8b (opt-in): an engaged battery the observer predicts above its charge limit "
       "stays engaged after a join (seed 25: 1.40x at the loss)"),
    _m("sequencing", "diode-hold-dropped",
       "        elif _diode_holds(prm, st, p, k, cur[k]):\n", "        elif False:\n",
       "#28 rule 8c: R3 closes a lower battery whose diode conducts under a heavy load although "
       "the zero-load prediction puts it above its limit (SOAK_4 observed: 2.64 A > 2.5 A)"),
    _m("sequencing", "diode-hold-no-cap", "    if not cur_a <= prm.diode_hold_a:\n",
       "    if False:\n",
       "#28 rule 8c: the diode is left carrying more than diode_hold_a (its rating) past R3's "
       "deadline"),
    Mutant("sequencing", "diode-hold-at-open-ratio",
           "        hold_ratio=float(config.charge_limit_margin),\n",
           "        hold_ratio=max(float(config.zero_load_open_ratio), 0.9),\n",
           "#28 rule 8c: R3 closes a held battery at rule 8b's 0.95 x the limit, not the engage "
           "rule's 0.9: no room for the prediction's error in the period of the closure "
           "(seed 2928, loss at 333.5 s: 0.98x instead of 0)",
           file="controller.py"),
    _m("sequencing", "r3-hold-ignores-diode-hold",
       "    within: bool = prm.diode_hold_a > 0.0 and st.forced_a[p, k] <= prm.diode_hold_a\n",
       "    within: bool = False\n",
       "#28 rules 8b/8c: 8b waits R3_HOLD_S before opening a battery R3 closed within "
       "diode_hold_a, whose prediction passes its limit within ~2 s of the closure (seed 230, "
       "loss at 76.5 s: 1.62x)"),
    _m("sequencing", "r3-closed-now-skipped",
       "    now: bool = st.forced_s[p, k] == t and not _r3_holds_off(prm, st, p, k, t)\n",
       "    now: bool = False\n",
       "#28 rules 8b/8c: 8b skips a battery R3 closed within diode_hold_a in this period, which "
       "another closure in the same period put above its limit (seed 75, loss at 149 s: "
       "1.65x)"),
    _m("sequencing", "diode-hold-8b-opened-at-margin",
       "    ratio = prm.hold_ratio if math.isnan(st.zl_open_s[p, k]) else prm.risk_clear_ratio\n",
       "    ratio = prm.hold_ratio\n",
       "#28 rule 8c: R3 re-closes a battery rule 8b opened at the engage rule's 0.9, not the "
       "0.8 the engage rule asks of it; its prediction jumps back with the current (seed 230: "
       "a 1.5 s hand-over cycle, 48 changes per minute)"),
]


def _io(name: str, old: str, new: str, why: str, file: str = "plant.py") -> Mutant:
    return Mutant("can", name, old, new, why, src=f"io/can/{file}")


CAN = [
    _io("counter-unchecked",
        "if kind in COUNTED and not self._fresh(i, node, kind, vals, t):", "if False:",
        "#26: frozen frames (alive counter frozen) refresh the battery: never detected"),
    _io("never-suspect", "node.suspect = node.bad_periods >= SUSPECT_PERIODS",
        "node.suspect = False",
        "#26: frozen / conflicting telemetry detected only when it is 2 s old"),
    _io("order-unchecked", "if d <= min(allowed, 127):", "if d <= 255:",
        "#26: frames with an old counter (replayed, reordered) are accepted"),
    _io("no-resync", "elif period_s > 0 and gap >= RESYNC_PERIODS * period_s - 1e-9:",
        "elif False:", "#26: a rebooted node's new counter is never accepted"),
    _io("present-undebounced",
        "raw_ok = t - node.present_bit_since_s >= PRESENT_DEBOUNCE_S - 1e-9",
        "raw_ok = True", "#26: one frame with the Present bit clear removes the battery"),
    _io("dock-unchecked", "why = self._dock_doubt(m)", 'why = ""',
        "#26: a dock contact stuck in flight puts the pack in charge mode"),
    _io("dock-undebounced",
        "if t - self.dock_since_s < DOCK_DEBOUNCE_S - 1e-9:\n            return False",
        "if False:\n            return False",
        "#26: the dock contact is believed (or judged) the moment it reads docked"),
    _io("explained-never", "if t - node.sw_rx_s > self.stale_s:\n            return False",
        "if True:\n            return False",
        "#26: the node's timeout does not explain a switch disagreement"),
    _io("timestamp-ignored", "            self.freshness.late += 1\n        return d",
        "            self.freshness.late += 1\n        return 0.0",
        "#26: a frame read late (behind a backlog) counts as new"),
    _io("log-never-flushed",
        "elif not float(t_s) - self._flushed_s < self.flush_every_s:", "elif False:",
        "#26: the frame log is written only when python-can's container fills: a killed "
        "run's log ends long before its database", "bus.py"),
]

# fmt: on

MUTANTS: list[Mutant] = [
    *LIMITS, *PLAUSIBILITY, *CHARGING, *PROTECTION, *SUPERVISOR, *SOC, *EQUALIZATION,
    *SEQUENCING, *PUBLISH, *QUALITY, *CAN, *BMU, *POWER,
]

PENDING: dict[str, str] = {}
"""Modules deliberately without mutants yet, shown in the report as TODO."""

TESTS: dict[str, list[str]] = {
    "limits": [
        "tests/test_limits_controller.py",
        "tests/test_limits_edges.py",
        "tests/test_limits_derating.py",
        "tests/test_limits_properties.py",
    ],
    "plausibility": [
        "tests/test_plausibility_monitor.py",
        "tests/test_plausibility_edges.py",
        "tests/test_plausibility_properties.py",
        "tests/test_plausibility_closed_loop.py",
        "tests/test_fault_injection.py",
        "tests/test_runtime_fault_suite.py::test_lost_switch_commands_are_not_a_switch_fault",
    ],
    "charging": [
        "tests/test_charging_controller.py",
        "tests/test_charging_rules.py",
        "tests/test_charging_properties.py",
        "tests/test_charging_schedule.py",
        "tests/test_charging_delta_v1.py",
    ],
    "publish": ["tests/test_publish_standby.py"],
    "power": [
        "tests/test_power.py",
        "tests/test_power_cli.py",
        "tests/test_power_publish.py",
        "tests/test_power_observer.py",
        "tests/test_power_series.py",
    ],
    "quality": ["tests/test_demo_goals.py"],
    "protection": [
        "tests/test_protection_controller.py",
        "tests/test_protection_properties.py",
        "tests/test_protection_replay.py",
        # the warning, time to trip / to empty and the resistance axis: behaviour of the same
        # rules, left out until #26's generated mutants showed them unguarded here
        "tests/test_protection_platform.py",
        "tests/test_protection_axes.py",
    ],
    "sequencing": [
        "tests/test_sequencing_controller.py",
        "tests/test_sequencing_properties.py",
        "tests/test_sequencing_closed_loop_properties.py",
        "tests/test_sequencing_replay.py",
        "tests/test_sequencing_trickle.py",
        "tests/test_fault_injection.py::test_a_tripped_battery_cannot_be_charged_by_the_reserve"
        "_that_replaces_it",
        "tests/test_runtime_fault_suite.py::test_a_standby_batterys_current_never_moves_the_other",
        "tests/test_runtime_fault_suite.py::test_a_frozen_loaded_battery_rejoins_without"
        "_charging_its_sibling",
        "tests/test_sequencing_zero_load.py::test_the_zero_load_prediction_uses_the_observers_r0",
        "tests/test_sequencing_zero_load.py::test_an_abrupt_load_loss_never_pushes_more_than_the"
        "_charge_limit[25]",
        "tests/test_sequencing_zero_load.py::test_r3_leaves_a_lower_battery_on_its_diode_while"
        "_closing_it_would_exceed_its_limit",
        "tests/test_sequencing_zero_load.py::test_a_diode_carrying_more_than_diode_hold_a_is"
        "_closed_on_r3s_deadline",
        "tests/test_sequencing_zero_load.py::test_rules_8b_and_8c_together_hold_the_charge_limit"
        "_where_r3_forced_it",
        "tests/test_sequencing_zero_load.py::test_a_load_loss_just_after_r3_closes_a_battery"
        "_within_the_cap_stays_in_the_limit",
        "tests/test_sequencing_zero_load.py::test_a_load_loss_in_the_period_r3_closes_two"
        "_batteries_stays_in_the_limit",
        "tests/test_sequencing_zero_load.py::test_r3_recloses_a_battery_rule_8b_opened_only"
        "_below_the_clear_ratio",
        "tests/test_sequencing_zero_load.py::test_r3_closes_a_battery_held_on_its_diode_only"
        "_within_the_charge_limit_margin",
    ],
    "can": ["tests/test_runtime_fault_suite.py"],
    "supervisor": ["tests/test_supervisor.py"],
    "bmu": [  # the plant's BMU supply (issue #24 item 5); one 400-step closed loop
        "tests/test_bmu_supply.py::test_the_aux_battery_never_goes_below_empty",
        "tests/test_bmu_supply.py::test_the_dock_restarts_the_bmu_and_charges_the_aux_battery"
        "_by_itself",
        "tests/test_bmu_supply.py::test_the_dock_alone_restarts_the_bmu_with_the_aux_battery"
        "_still_empty",
        "tests/test_bmu_supply.py::test_closed_loop_a_browned_out_bmu_logs_no_stage_while_docked",
    ],
    "soc": [
        "tests/test_soc_estimator.py", "tests/test_soc_observer.py",
        "tests/test_soc_lfp_plateau.py", "tests/test_soc_real_log.py",
    ],
    # shared helpers (#26 item 4: generated mutants only): every method's commands and events
    # go through control/commands.py, capacity / conduction through control/battery.py
    "commands": [
        "tests/test_commands.py",
        "tests/test_limits_controller.py",
        "tests/test_limits_edges.py",
        "tests/test_sequencing_controller.py",
        "tests/test_charging_controller.py",
    ],
    "battery": [
        "tests/test_limits_controller.py",
        "tests/test_limits_edges.py",
        "tests/test_plausibility_monitor.py",
        "tests/test_plausibility_edges.py",
    ],
    "equalization": [
        "tests/test_equalization_controller.py",
        "tests/test_equalization_core.py",
        "tests/test_equalization_owed.py",
        "tests/test_equalization_above_average.py",
        "tests/test_equalization_properties.py",
        "tests/test_equalization_replay.py",
    ],
}
"""Behavioural tests per module, run interpreted (NUMBA_DISABLE_JIT=1). Equivalence tests
(test_fused_step, test_interpreted, test_golden) are never listed: they compare two copies of
the same code and would kill every mutant without checking a rule. Slow closed loops (the
charging closed loop takes ~40 s interpreted) are left out to keep a run in minutes."""
