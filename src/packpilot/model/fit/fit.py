"""Fit an equivalent-circuit cell to logged flights: capacity, the initial state of charge of
each log, R0, R1 / tau1 (a second RC pair only where the data resolve it), the OCV as the
chemistry's default corrected over the SOC window the data cover (:mod:`.ocv`; kept only where
the data ask for it) and, when the logs span temperatures, an Arrhenius law for the
resistances.

Bounded least squares (``scipy.optimize.least_squares``, trust region) on log-scaled
parameters (a resistance of 2 mOhm and one of 200 mOhm are equally far from a start), from
several starts, keeping the best. Uncertainty from the Jacobian at the optimum
(``s^2 (J^T J)^-1``, relative for the log-scaled ones). A parameter is flagged *not
identifiable* — and said so in the output — when it sits on a bound, when its relative
uncertainty exceeds :data:`MAX_REL_UNCERTAINTY`, when a time constant is shorter than two
logging periods (the branch has settled before the next sample: R0 and R1 merge), or, for the
capacity, when the logs swing the state of charge by less than :data:`MIN_SOC_SWING`.

Pure: arrays in, a :class:`FitResult` out; no I/O (the CLI reads logs and writes files).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from packpilot.errors import InputError
from packpilot.model.fit.ocv import OcvFit, OcvShape, shape, summarise
from packpilot.model.fit.profile import F64, EcmValues, Profile, noise_floor, predict

MIN_SOC_SWING = 0.30
"""Below this swing of the state of charge the capacity is flagged not identifiable."""
MAX_REL_UNCERTAINTY = 1.0
"""A log-scaled parameter whose one-sigma relative uncertainty exceeds this is not identified."""
SECOND_RC_GAIN = 0.10
"""Without a rest after load a second RC pair must lower the RMSE by at least this share."""
SECOND_RC_NOISE = 1.0
"""A second RC pair is tried only when one pair leaves more than this many noise floors (the
training part's): a model already at the noise has nothing left for a branch to explain (the
self-heating's gate, SELF_HEATING_NOISE)."""
TAU_MIN_PERIODS = 2.0
"""A time constant below this many logging periods is flagged not identifiable."""
MIN_TEMP_SPAN_K = 10.0
"""Logs must span this much temperature before a resistance-temperature law is fitted."""
REST_A_PER_AH = 0.02
"""A rest: cell current below C/50 ..."""
REST_MIN_S = 60.0
"""... for at least this long; its last sample is a point of the OCV curve."""
CAPACITY_PRIOR_LOG_SD = 0.7
"""The capacity's weak prior: log-normal about the guess from the voltages, one sigma a factor
of 2 — one residual of the size of the voltage noise per 0.7 in log capacity, negligible against
thousands of samples that see the capacity, decisive only where the SOC barely moves (then the
capacity is flagged not identifiable anyway, and it no longer runs to a bound)."""
CAPACITY_TIED = (
    "tied to the OCV correction: the logs show the voltage against the charge drawn, and a "
    "corrected OCV stretched along the SOC fits them as well with another capacity"
)
"""Why the capacity is flagged whenever the OCV correction is kept (measured: a plant-made
flight whose OCV has an 80 mV bump at 75 % SOC, capacity 5.0 Ah, is fitted to its noise with
the correction and a capacity of 5.9-9.4 Ah, depending on the seed and the rate)."""
KNOT_PASSES = 3
"""The OCV correction's knots are placed at most this many times (see _fit_ocv) ..."""
KNOT_MOVE_SOC = 0.02
"""... again only while the covered window's ends move by more than this."""
SELF_HEATING_GAIN = 0.10
"""Self-heating (logs without temperature) is kept only when it lowers the RMSE by at least
this share: a pack that does not warm enough to move its resistance keeps constant ones."""
SELF_HEATING_NOISE = 1.0
"""... and only when constant resistances leave more than the noise floor (of the training
part): a model already at the noise has nothing left for heat to explain
(robert_lefebvre_octo_PM.log: 15.5 mV against a 15.7 mV floor; with heat the training RMSE
fell 13 % to below the floor and the held-out one rose from 22.2 to 30.0 mV). Not twice the
floor: a warming pack's capacity and OCV absorb much of the heating in the training part
(a plant-made warming flight: 13.6 mV against an 11.0 mV floor, held-out 28.7 mV)."""
MIN_HEAT_J_PER_K_AH = 9.9
"""The least heat capacity a Li-ion cell can have per Ah: 0.8 J/(g K) (the low end of measured
specific heats, 0.8-1.3 J/(g K)) x 3.7 V / 300 Wh/kg (above the best cells' specific energy) =
9.9 J/(K Ah). The heat capacity is fitted per Ah of capacity with this as its lower bound, in
every refit (the OCV correction's and the second RC pair's too: before, only the first
self-heating fit was checked, and the later refits took the Maccor pulse test's to 4.7
J/(K Ah), a modelled rise of 43 K in a cycler); a first self-heating fit that runs to the bound
is rejected, with the reason."""
NATURAL_CONVECTION_W_PER_M2K = 5.0
"""The least heat transfer coefficient from a pack's outer surface to air: the low end of
natural convection in still air (5-10 W/(m2 K) for a small body a few K to tens of K above
ambient), radiation (about 5.5 W/(m2 K) more for a wrap of emissivity 0.9 at 300 K) and any
airflow (prop wash, the cycler's fan) left out: a floor, not an estimate."""
MAX_WH_PER_L = 600.0
"""The most energy per volume a Li-ion cell holds (Wh/L; high-energy pouch and cylindrical cells
reach 500-700): the densest cell gives the least volume, hence the least surface, per Ah."""
NOMINAL_CELL_V = 3.7
"""Energy per Ah of a Li-ion cell (Wh/Ah, nominal voltage of LCO/NMC/LiPo; LFP's 3.2 V comes with
a lower Wh/L, so a larger volume per Ah: 3.7 V over MAX_WH_PER_L is the least volume)."""
MAX_CELLS_PER_PACK = 16
"""A cell's share of its pack's outer surface falls as the pack grows (n^(-1/3) for a cube):
the floor takes the largest pack PackPilot's logs come from (UAV packs up to 14S; 16 cells)."""
MIN_HEAT_G_W_PER_K_AH23 = (
    NATURAL_CONVECTION_W_PER_M2K
    * 6.0
    * (MAX_CELLS_PER_PACK * NOMINAL_CELL_V / (MAX_WH_PER_L * 1000.0)) ** (2.0 / 3.0)
    / MAX_CELLS_PER_PACK
)
"""The least conductance to ambient a cell of capacity Q can have, per Ah^(2/3) (a surface
scales with volume^(2/3)): h = NATURAL_CONVECTION_W_PER_M2K over the cell's share of the outer
surface of a cube-shaped pack (the least surface a box of that volume has) of
MAX_CELLS_PER_PACK cells at MAX_WH_PER_L: G_min = h * 6 (n * 3.7 V * Q / 600 Wh/L)^(2/3) / n
= 4.0e-3 W/K per Ah^(2/3) (7.7 mW/K for a 2.65 Ah cell; a real 3S 2650 mAh pack, 135 x 43 x 22
mm, has 4.2x that surface per cell). Before, G's floor was 1 mW/K for any cell, and the
dronekit tlog's fit ran to it: a pack heating with no cooling at all. The conductance is
fitted per Ah^(2/3) with this as its lower bound in every refit, like the heat capacity."""
HEAT_B_K = 20000.0 / 8.314462618
"""Arrhenius constant of the resistances under self-heating (K): Ea = 20 kJ/mol, uav_5ah's and
PyBaMM ECM_Example's law (src/packpilot/data/cells/README.md: inside the 11-53 kJ/mol of PyBaMM's
physics sets). Not fitted: without a logged temperature only B / C is seen."""
BOUNDS = {
    "r0_ohm": (1e-4, 1.0),
    "r1_ohm": (1e-5, 1.0),
    "tau1_s": (0.05, 3000.0),
    "r2_ohm": (1e-5, 1.0),
    "tau2_s": (1.0, 20000.0),
    "b_k": (0.0, 8000.0),
    "heat_c_j_per_k_ah": (MIN_HEAT_J_PER_K_AH, 1000.0),
    "heat_g_w_per_k_ah23": (MIN_HEAT_G_W_PER_K_AH23, 50.0),
}
"""Bounds per cell: resistances 0.1 mOhm .. 1 Ohm, time constants 50 ms .. 50 min, heat
capacity per Ah of capacity 9.9 .. 1000 J/(K Ah), conductance to ambient per Ah^(2/3)
4.0e-3 .. 50 W/(K Ah^(2/3))."""
UNITS = {"capacity_ah": "Ah", "r0_ohm": "Ohm", "r1_ohm": "Ohm", "tau1_s": "s",
         "r2_ohm": "Ohm", "tau2_s": "s", "b_k": "K", "heat_c_j_per_k": "J/K",
         "heat_c_j_per_k_ah": "J/(K Ah)", "heat_g_w_per_k_ah23": "W/(K Ah^(2/3))",
         "heat_g_w_per_k": "W/K"}  # fmt: skip


@dataclass(frozen=True)
class FitParam:
    name: str
    value: float
    unit: str
    rel_uncertainty: float
    """One-sigma relative uncertainty (absolute for the initial SOC and b_k)."""
    identifiable: bool = True
    reason: str = ""


@dataclass(frozen=True)
class Window:
    """The data the fitted set holds for."""

    soc_min: float
    soc_max: float
    current_min_a: float
    current_max_a: float
    temp_min_c: float | None
    temp_max_c: float | None
    duration_s: float
    samples: int


@dataclass(frozen=True)
class FitResult:
    params: dict[str, FitParam]
    soc0: dict[str, FitParam]
    values: EcmValues
    ocv_soc: F64
    ocv_v: F64
    ocv_note: str
    rmse_v: float
    window: Window
    assumptions: list[str]
    notes: list[str]
    fit_time_s: float
    n_rc: int
    ocv_fit: OcvFit | None = None
    """The fitted correction of the default OCV (None: the default kept, see ocv_note)."""

    def flags(self) -> list[str]:
        """Every 'not identifiable' with its reason."""
        out = [f"{p.name}: not identifiable ({p.reason})" for p in self.params.values()
               if not p.identifiable]  # fmt: skip
        out += [f"{p.name}: not identifiable ({p.reason})" for p in self.soc0.values()
                if not p.identifiable]  # fmt: skip
        return out + (self.ocv_fit.flags if self.ocv_fit is not None else [])


@dataclass
class _Layout:
    """The parameter vector: log-scaled positives, then b_k (linear), then each log's SOC0."""

    names: list[str]
    logs: list[str]
    lo: list[float] = field(default_factory=list)
    hi: list[float] = field(default_factory=list)
    heat_b_k: float = HEAT_B_K
    """B of the self-heating law (fixed; used when the layout has heat_c_j_per_k)."""
    prior: tuple[float, float] = (0.0, 0.0)
    """(log capacity the voltages suggest, weight in V per unit of log): a weak prior that
    holds the capacity where the data say nothing (see CAPACITY_PRIOR_LOG_SD)."""
    ocv: OcvShape | None = None
    """The OCV correction's knots and bounds; its parameters close the vector."""
    noise_v: float = 0.0
    """The scale of the OCV correction's regularisation residuals."""

    def ocv_table(self, x: F64, default: tuple[F64, F64]) -> tuple[F64, F64]:
        """The OCV the parameters describe: the default, corrected when the layout has one."""
        if self.ocv is None:
            return default
        return self.ocv.table(x[len(x) - self.ocv.n :])

    def values(self, x: F64, t_ref_c: float) -> tuple[EcmValues, list[float]]:
        p = {n: (x[k] if n == "b_k" else math.exp(x[k])) for k, n in enumerate(self.names)}
        rc = [(p["r1_ohm"], p["tau1_s"])]
        if "r2_ohm" in p:
            rc.append((p["r2_ohm"], p["tau2_s"]))
        n_ocv = 0 if self.ocv is None else self.ocv.n
        soc0 = [float(v) for v in x[len(self.names) : len(self.names) + len(self.logs)]]
        assert len(x) == len(self.names) + len(self.logs) + n_ocv
        heat = "heat_c_j_per_k_ah" in p
        b_k = self.heat_b_k if heat else p.get("b_k", 0.0)
        heat_c = p["heat_c_j_per_k_ah"] * p["capacity_ah"] if heat else 0.0
        heat_g = p["heat_g_w_per_k_ah23"] * p["capacity_ah"] ** (2.0 / 3.0) if heat else 0.0
        vals = EcmValues(p["capacity_ah"], p["r0_ohm"], tuple(rc), b_k, t_ref_c,
                         heat_c, heat_g)  # fmt: skip
        return vals, soc0


def _layout(n_rc: int, law: bool, q_bounds: tuple[float, float], logs: list[str],
            heat: bool = False, like: _Layout | None = None) -> _Layout:  # fmt: skip
    """The vector's names and bounds; ``like`` passes on the priors and the OCV correction."""
    names = ["capacity_ah", "r0_ohm", "r1_ohm", "tau1_s"]
    names += ["r2_ohm", "tau2_s"] if n_rc == 2 else []
    names += ["b_k"] if law else []
    names += ["heat_c_j_per_k_ah", "heat_g_w_per_k_ah23"] if heat else []
    lay = _Layout(names, logs)
    for n in names:
        lo, hi = q_bounds if n == "capacity_ah" else BOUNDS[n]
        lay.lo.append(lo if n == "b_k" else math.log(lo))
        lay.hi.append(hi if n == "b_k" else math.log(hi))
    for _ in logs:
        lay.lo.append(0.0)
        lay.hi.append(1.05)
    if like is not None:
        lay.prior, lay.noise_v = like.prior, like.noise_v
        _with_ocv(lay, like.ocv)
    return lay


def _with_ocv(lay: _Layout, sh: OcvShape | None) -> None:
    """Close the layout's vector with the OCV correction's parameters."""
    lay.ocv = sh
    if sh is not None:
        lay.lo += sh.lo
        lay.hi += sh.hi


def _n_fit(profs: Sequence[Profile]) -> int:
    """The samples whose voltage the fit sees (a held-out flight's are left out)."""
    return int(sum(np.count_nonzero(p.fitted) for p in profs))


def _noise(profs: Sequence[Profile]) -> float:
    """A robust scale of the sample-to-sample voltage scatter (at least 1 mV)."""
    d = np.concatenate([np.diff(p.voltage_v) for p in profs])
    return max(float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)), 1e-3)


def _soc_from_ocv(v: float, ocv_soc: F64, ocv_v: F64) -> float:
    """The SOC whose OCV is v (the OCV table increases with SOC)."""
    return float(np.clip(np.interp(v, ocv_v, ocv_soc), 0.0, 1.0))


def _guess_capacity(profiles: Sequence[Profile], ocv_soc: F64, ocv_v: F64) -> float:
    """Charge drawn over the SOC change the voltages suggest (a start, not an answer)."""
    guesses = []
    for p in profiles:
        last = int(np.flatnonzero(p.fitted)[-1])  # a held-out flight tells the fit nothing
        s0 = _soc_from_ocv(float(p.voltage_v[0]), ocv_soc, ocv_v)
        s1 = _soc_from_ocv(float(p.voltage_v[last] + 0.01 * p.current_a[last]), ocv_soc, ocv_v)
        drawn = float(p.drawn_ah[last])
        if drawn > 0 and s0 - s1 > 0.05:
            guesses.append(drawn / (s0 - s1))
        elif drawn > 0:
            guesses.append(drawn / 0.3)
    return float(np.median(guesses)) if guesses else 5.0


def _residuals(x: F64, lay: _Layout, profs: Sequence[Profile], ocv: tuple[F64, F64],
               t_ref_c: float) -> F64:  # fmt: skip
    vals, soc0 = lay.values(x, t_ref_c)
    table = lay.ocv_table(x, ocv)
    parts = [(predict(p, vals, s, *table)[0] - p.voltage_v)[p.fitted]
             for p, s in zip(profs, soc0, strict=True)]  # fmt: skip
    if lay.prior[1] > 0.0:
        parts.append(np.array([lay.prior[1] * (x[0] - lay.prior[0])]))
    if lay.ocv is not None:
        parts.append(lay.ocv.prior(x[len(x) - lay.ocv.n :], lay.noise_v))
    return np.concatenate(parts)


def _starts(lay: _Layout, q0: float, soc_starts: list[float], n_rc: int,
            prev: F64 | None) -> list[F64]:  # fmt: skip
    combos = [(1.0, 0.01, 0.005, 20.0), (0.6, 0.03, 0.01, 5.0), (1.7, 0.005, 0.002, 100.0),
              (1.0, 0.02, 0.02, 1.0)]  # fmt: skip
    out = []
    for qf, r0, r1, tau in combos:
        x = [math.log(q0 * qf), math.log(r0), math.log(r1), math.log(tau)]
        if n_rc == 2:
            x += [math.log(r1), math.log(tau * 20.0)]
        if "b_k" in lay.names:
            x.append(2000.0)
        out.append(np.array(x + soc_starts))
    if prev is not None:
        out.insert(0, prev)
    lo, hi = np.array(lay.lo), np.array(lay.hi)
    return [np.clip(x, lo + 1e-9, hi - 1e-9) for x in out]


def _solve(lay: _Layout, profs: Sequence[Profile], ocv: tuple[F64, F64], t_ref_c: float,
           starts: list[F64]) -> tuple[F64, F64, F64]:  # fmt: skip
    """(x, residuals, jacobian) of the best start."""
    best = None
    for x0 in starts:
        r = least_squares(
            _residuals, x0, bounds=(lay.lo, lay.hi), args=(lay, profs, ocv, t_ref_c),
            x_scale="jac", max_nfev=400, xtol=1e-10, ftol=1e-10,
        )  # fmt: skip
        if best is None or r.cost < best.cost:
            best = r
    assert best is not None
    return best.x, best.fun, best.jac


def _covariance(res: F64, jac: F64) -> F64:
    m, p = jac.shape
    s2 = float(res @ res) / max(m - p, 1)
    out: F64 = np.linalg.pinv(jac.T @ jac) * s2
    return out


def _uncertainty(res: F64, jac: F64) -> F64:
    out: F64 = np.sqrt(np.clip(np.diag(_covariance(res, jac)), 0.0, None))
    return out


def _params(lay: _Layout, x: F64, sig: F64, period_s: float, swing: float
            ) -> tuple[dict[str, FitParam], dict[str, FitParam]]:  # fmt: skip
    out: dict[str, FitParam] = {}
    for k, n in enumerate(lay.names):
        value = float(x[k]) if n == "b_k" else math.exp(x[k])
        rel = float(sig[k]) if n == "b_k" else math.expm1(min(float(sig[k]), 700.0))
        reasons = []
        edge = 1e-3 * max(1.0, abs(lay.hi[k] - lay.lo[k]))
        if x[k] - lay.lo[k] < edge or lay.hi[k] - x[k] < edge:
            reasons.append("at a bound")
        if n != "b_k" and rel > MAX_REL_UNCERTAINTY:
            reasons.append(f"uncertainty {100 * rel:.0f} %")
        if n.startswith("tau") and value < TAU_MIN_PERIODS * period_s:
            reasons.append(
                f"{value:.2g} s is below {TAU_MIN_PERIODS:g} logging periods ({period_s:.3g} s)"
            )
        if n == "capacity_ah" and swing < MIN_SOC_SWING:
            reasons.append(f"SOC swing {100 * swing:.0f} % < {100 * MIN_SOC_SWING:.0f} %")
        out[n] = FitParam(n, value, UNITS[n], rel, not reasons, "; ".join(reasons))
    _merge_flags(out, period_s)
    soc0 = {}
    for j, log in enumerate(lay.logs):
        k = len(lay.names) + j
        edge = x[k] - lay.lo[k] < 1e-3 or lay.hi[k] - x[k] < 1e-3
        soc0[log] = FitParam(f"soc0[{log}]", float(x[k]), "", float(sig[k]), not edge,
                             "at a bound" if edge else "")  # fmt: skip
    return out, soc0


def _thermal_per_cell(lay: _Layout, params: dict[str, FitParam], cov: F64) -> None:
    """The heat capacity and the conductance per cell, from those fitted per Ah (C) and per
    Ah^(2/3) (G)."""
    params["heat_c_j_per_k"] = _per_cell(lay, params, cov, "heat_c_j_per_k",
                                         "heat_c_j_per_k_ah", 1.0)  # fmt: skip
    params["heat_g_w_per_k"] = _per_cell(lay, params, cov, "heat_g_w_per_k",
                                         "heat_g_w_per_k_ah23", 2.0 / 3.0)  # fmt: skip


def _per_cell(lay: _Layout, params: dict[str, FitParam], cov: F64, name: str, of: str,
              power: float) -> FitParam:  # fmt: skip
    """A thermal value per cell from the one fitted per Ah**power of capacity (the heat
    capacity per Ah, bounded below by MIN_HEAT_J_PER_K_AH; the conductance per Ah^(2/3),
    bounded below by MIN_HEAT_G_W_PER_K_AH23, in every refit, so no later step can take them
    below what a cell can have); its uncertainty from both log-scaled factors and their
    covariance."""
    k = lay.names.index(of)
    var = power**2 * cov[0, 0] + cov[k, k] + 2.0 * power * cov[0, k]
    per = params[of]
    value = per.value * params["capacity_ah"].value ** power
    rel = math.expm1(min(math.sqrt(max(float(var), 0.0)), 700.0))
    return FitParam(name, value, UNITS[name], rel, per.identifiable, per.reason)


def _merge_flags(out: dict[str, FitParam], period_s: float) -> None:
    """When tau1 is below two logging periods the RC branch has settled by the next sample:
    the data see R0 + R1 (the resistance a pulse shows), not how it splits."""
    tau = out["tau1_s"]
    if tau.value >= TAU_MIN_PERIODS * period_s:
        return
    total = out["r0_ohm"].value + out["r1_ohm"].value
    why = f"merges with R1 (tau1 below two logging periods): R0 + R1 = {1000 * total:.2f} mOhm"
    for n in ("r0_ohm", "r1_ohm"):
        p = out[n]
        reason = "; ".join(x for x in (p.reason, why) if x)
        out[n] = FitParam(p.name, p.value, p.unit, p.rel_uncertainty, False, reason)


def _rests(p: Profile, capacity_ah: float) -> list[int]:
    """Last sample of each rest (|I| below C/50 for REST_MIN_S or longer)."""
    quiet = (np.abs(p.current_a) < REST_A_PER_AH * capacity_ah) & p.fitted
    ends = []
    start = None
    for k, q in enumerate(np.append(quiet, False)):
        if q and start is None:
            start = k
        elif not q and start is not None:
            if p.t_s[k - 1] - p.t_s[start] >= REST_MIN_S:
                ends.append(k - 1)
            start = None
    return ends


def _relaxed_rests(profs: Sequence[Profile], capacity_ah: float) -> int:
    """How many rests end relaxed (the last sample of each rest: a point of the OCV curve)."""
    return sum(len(_rests(p, capacity_ah)) for p in profs)


def _fit_ocv(lay: _Layout, x: F64, profs: Sequence[Profile], ocv: tuple[F64, F64],
             t_ref: float) -> tuple[_Layout, F64, F64, F64]:  # fmt: skip
    """Refit with the OCV correction (see :mod:`packpilot.model.fit.ocv`), started from no
    correction, its knots over the SOC window the fit covers. That window moves with the
    capacity and initial SOC the correction brings, so the knots are placed again (the
    correction carried over) while the window's ends move by more than
    :data:`KNOT_MOVE_SOC`, at most :data:`KNOT_PASSES` times."""
    lay2, x2 = lay, np.asarray(x, np.float64)
    res2 = jac2 = np.zeros(0)
    knots, corr = np.zeros(0), np.zeros(0)
    for _ in range(KNOT_PASSES):
        vals, soc0 = lay2.values(x2, t_ref)
        socs = np.concatenate([predict(p, vals, s, *ocv)[1][p.fitted]
                               for p, s in zip(profs, soc0, strict=True)])  # fmt: skip
        sh = shape(float(socs.min()), float(socs.max()), *ocv)
        if len(knots) and (abs(sh.knots[0] - knots[0]) < KNOT_MOVE_SOC
                           and abs(sh.knots[-1] - knots[-1]) < KNOT_MOVE_SOC):  # fmt: skip
            break
        head = x2[: len(x2) - (0 if lay2.ocv is None else lay2.ocv.n)]
        p0 = sh.params_for(knots, corr) if len(knots) else np.zeros(sh.n)
        lay2 = _layout(len(vals.rc), "b_k" in lay.names,
                       (math.exp(lay.lo[0]), math.exp(lay.hi[0])), lay.logs,
                       "heat_c_j_per_k_ah" in lay.names)  # fmt: skip
        lay2.prior, lay2.noise_v = lay.prior, lay.noise_v
        _with_ocv(lay2, sh)
        x2, res2, jac2 = _solve(lay2, profs, ocv, t_ref, [np.concatenate([head, p0])])
        knots, corr = sh.knots, sh.values(x2[len(x2) - sh.n :])
    return lay2, x2, res2, jac2


def _keep_ocv(res: F64, res2: F64, n_data: int, k: int) -> tuple[bool, str]:
    """Schwarz's criterion (BIC) on the training samples: the correction's k parameters are
    kept when ``n ln(RSS_default / RSS_corrected) > k ln n``. On plant-made logs whose OCV *is*
    the default the correction lowered the training RMSE by 0.01-0.17 % (BIC 24-34 against it)
    while moving the capacity by up to 5 % (knots placed once): a free correction trades with
    the capacity (the data see the voltage against the charge drawn, not against the SOC), so
    it is kept only where the data ask for it."""
    rss0 = float(res[:n_data] @ res[:n_data])
    rss1 = float(res2[:n_data] @ res2[:n_data])
    gain = n_data * math.log(max(rss0, 1e-30) / max(rss1, 1e-30))
    cost = k * math.log(n_data)
    what = (f"training RMSE {1000 * math.sqrt(rss0 / n_data):.2f} mV with the default, "
            f"{1000 * math.sqrt(rss1 / n_data):.2f} mV corrected ({k} parameters; BIC "
            f"{gain - cost:+.1f} for it)")  # fmt: skip
    return gain > cost, what


def _ocv_step(lay: _Layout, x: F64, res: F64, jac: F64, profs: Sequence[Profile],
              ocv: tuple[F64, F64], t_ref: float, notes: list[str]
              ) -> tuple[F64, F64, F64, _Layout, str]:  # fmt: skip
    """The fit with the OCV correction, kept where the data ask for it (_keep_ocv)."""
    lay2, x2, res2, jac2 = _fit_ocv(lay, x, profs, ocv, t_ref)
    assert lay2.ocv is not None
    keep, why = _keep_ocv(res, res2, _n_fit(profs), lay2.ocv.n)
    if keep:
        notes.append(f"OCV correction kept: {why}")
        return x2, res2, jac2, lay2, why
    return x, res, jac, lay, f"the data do not ask for a correction: {why}"


def _ocv_summary(lay: _Layout, x: F64, res: F64, jac: F64, profs: Sequence[Profile],
                 capacity_ah: float) -> OcvFit | None:  # fmt: skip
    if lay.ocv is None:
        return None
    n = lay.ocv.n
    cov = _covariance(res, jac)[-n:, -n:]
    return summarise(lay.ocv, x[-n:], cov, _relaxed_rests(profs, capacity_ah))


def _window(profs: Sequence[Profile], vals: EcmValues, soc0: list[float], ocv: tuple[F64, F64],
            ) -> Window:  # fmt: skip
    socs = np.concatenate([predict(p, vals, s, *ocv)[1][p.fitted]
                           for p, s in zip(profs, soc0, strict=True)])  # fmt: skip
    cur = np.concatenate([p.current_a[p.fitted] for p in profs])
    temps = [p.temp_c for p in profs if p.temp_c is not None]
    tt = np.concatenate(temps) if temps else None
    return Window(
        float(socs.min()), float(socs.max()), float(cur.min()), float(cur.max()),
        None if tt is None else float(tt.min()), None if tt is None else float(tt.max()),
        float(sum(np.sum(np.diff(p.t_s, prepend=p.t_s[0])[p.fitted]) for p in profs)),
        _n_fit(profs),
    )  # fmt: skip


def fit(
    profiles: Sequence[Profile],
    ocv_soc: F64,
    ocv_v: F64,
    *,
    max_rc: int = 2,
    ref_temp_c: float = 25.0,
    fit_ocv: bool = True,
) -> FitResult:
    """Fit one cell model to every profile at once (one capacity and resistance set, one
    initial SOC per profile); ``fit_ocv=False`` keeps the chemistry's default OCV as it is
    (the comparison in the benchmark, and the tests' proof that the correction matters)."""
    t0 = time.process_time()
    profs = list(profiles)
    if not profs:
        raise InputError("fit: no profile to fit")
    for p in profs:
        if len(p.t_s) < 20:
            raise InputError(f"fit: {p.name}: {len(p.t_s)} samples; at least 20 are needed")
    notes: list[str] = []
    assumptions: list[str] = []
    temps = [p.temp_c for p in profs if p.temp_c is not None]
    span = float(np.ptp(np.concatenate(temps))) if temps else 0.0
    law = span >= MIN_TEMP_SPAN_K
    t_ref = float(np.mean(np.concatenate(temps))) if temps else ref_temp_c
    if not law:
        assumptions.append(
            f"the fitted resistances are those at {t_ref:.1f} degC (reference temperature): "
            "the logs "
            + (f"span {span:.1f} K of temperature" if temps else "carry no temperature")
            + f", a resistance-temperature law needs {MIN_TEMP_SPAN_K:g} K"
        )
    ocv = (np.asarray(ocv_soc, dtype=np.float64), np.asarray(ocv_v, dtype=np.float64))
    q0 = _guess_capacity(profs, *ocv)
    drawn = max(float(np.max(p.drawn_ah)) for p in profs)
    q_bounds = (max(q0 / 20.0, drawn * 0.5, 1e-3), q0 * 20.0)
    socs = [_soc_from_ocv(float(p.voltage_v[0] + 0.01 * p.current_a[0]), *ocv) for p in profs]
    names = [p.name for p in profs]
    period = float(np.median([p.period_s for p in profs]))

    prior = (math.log(q0), _noise(profs) / CAPACITY_PRIOR_LOG_SD)
    lay = _layout(1, law, q_bounds, names)
    lay.prior, lay.noise_v = prior, _noise(profs)
    x, res, jac = _solve(lay, profs, ocv, t_ref, _starts(lay, q0, socs, 1, None))
    n_rc = 1
    if not temps:
        x, res, jac, lay = _maybe_self_heating(lay, x, res, jac, profs, ocv, t_ref, notes)
        if "heat_c_j_per_k_ah" in lay.names:
            assumptions[:] = [a for a in assumptions if not a.startswith("the fitted resistances")]
            assumptions.append(
                f"self-heating: each log starts at {t_ref:.1f} degC (the reference temperature, "
                "at rest); the fitted resistances hold there and fall as the modelled cell "
                f"warms (Arrhenius B = {HEAT_B_K:.0f} K, the template's, not fitted); heat "
                "capacity and conductance are effective values (the fitted resistance includes "
                "wiring that heats no cell)"
            )
    ocv_why = "not corrected: fit_ocv off"
    if fit_ocv:
        x, res, jac, lay, ocv_why = _ocv_step(lay, x, res, jac, profs, ocv, t_ref, notes)
    if max_rc >= 2:
        x, res, jac, lay, n_rc = _maybe_second_rc(lay, x, res, jac, profs, ocv, t_ref, law,
                                                  q_bounds, names, period, notes)  # fmt: skip
    vals, soc0 = lay.values(x, t_ref)
    swing = max(np.ptp(predict(p, vals, s, *ocv)[1][p.fitted])
                for p, s in zip(profs, soc0, strict=True))  # fmt: skip
    params, soc0p = _params(lay, x, _uncertainty(res, jac), period, float(swing))
    if "heat_c_j_per_k_ah" in params:
        _thermal_per_cell(lay, params, _covariance(res, jac))
    ocv_fit = _ocv_summary(lay, x, res, jac, profs, vals.capacity_ah)
    if ocv_fit is not None:
        q = params["capacity_ah"]
        why = "; ".join(x for x in (q.reason, CAPACITY_TIED) if x)
        params["capacity_ah"] = FitParam(q.name, q.value, q.unit, q.rel_uncertainty, False, why)
    table = lay.ocv_table(x, ocv)
    ocv_note = f"chemistry default ({ocv_why})" if ocv_fit is None else ocv_fit.note()
    n_data = _n_fit(profs)
    return FitResult(
        params=params, soc0=soc0p, values=vals, ocv_soc=table[0], ocv_v=table[1],
        ocv_note=ocv_note, rmse_v=float(np.sqrt(np.mean(res[:n_data] ** 2))),
        window=_window(profs, vals, soc0, table), assumptions=assumptions, notes=notes,
        fit_time_s=time.process_time() - t0, n_rc=n_rc, ocv_fit=ocv_fit,
    )  # fmt: skip


def _maybe_self_heating(lay: _Layout, x: F64, res: F64, jac: F64, profs: Sequence[Profile],
                        ocv: tuple[F64, F64], t_ref: float, notes: list[str]
                        ) -> tuple[F64, F64, F64, _Layout]:  # fmt: skip
    """Logs without temperature: let the cell warm by its own losses (one lumped node, the
    resistances falling by the template's Arrhenius law) and keep it only where the data ask
    for it (SELF_HEATING_GAIN)."""
    rmse1 = float(np.sqrt(np.mean(res**2)))
    floor = max(noise_floor(p) for p in profs)
    if rmse1 <= SELF_HEATING_NOISE * floor:
        notes.append(
            f"self-heating not tried: constant resistances leave {1000 * rmse1:.2f} mV, within "
            f"the noise floor ({1000 * floor:.2f} mV): nothing left for heat to explain"
        )
        return x, res, jac, lay
    q_bounds = (math.exp(lay.lo[0]), math.exp(lay.hi[0]))
    heat = _layout(1, False, q_bounds, lay.logs, heat=True, like=lay)
    lo, hi = np.array(heat.lo), np.array(heat.hi)
    q0 = math.exp(x[0])
    a23 = q0 ** (2.0 / 3.0)
    starts = [np.clip(np.array([*x[:4], math.log(c), math.log(g), *x[4:]]), lo + 1e-9, hi - 1e-9)
              for c, g in ((50.0 / q0, 0.5 / a23), (200.0 / q0, 2.0 / a23),
                           (20.0 / q0, 0.1 / a23))]  # fmt: skip
    xh, resh, jach = _solve(heat, profs, ocv, t_ref, starts)
    rmseh = float(np.sqrt(np.mean(resh**2)))
    q = math.exp(xh[0])
    c_j, g_w = q * math.exp(xh[4]), q ** (2.0 / 3.0) * math.exp(xh[5])
    what = (f"RMSE {1000 * rmse1:.2f} mV with constant resistances, {1000 * rmseh:.2f} mV "
            f"self-heating (C {c_j:.3g} J/K, G {g_w:.3g} W/K per cell)")  # fmt: skip
    if xh[4] - heat.lo[4] < 1e-3 * (heat.hi[4] - heat.lo[4]):
        notes.append(
            f"self-heating rejected ({what}): the fit runs to the least heat capacity a Li-ion "
            f"cell can have ({MIN_HEAT_J_PER_K_AH:g} J/K per Ah, its bound): the data ask for "
            'less, so the "heat" explains something else; constant resistances kept'
        )
        return x, res, jac, lay
    if rmseh < (1.0 - SELF_HEATING_GAIN) * rmse1:
        notes.append(f"self-heating kept: {what}")
        return xh, resh, jach, heat
    notes.append(f"self-heating not resolved by the data ({what}): constant resistances kept")
    return x, res, jac, lay


def _maybe_second_rc(lay: _Layout, x: F64, res: F64, jac: F64, profs: Sequence[Profile],
                     ocv: tuple[F64, F64], t_ref: float, law: bool,
                     q_bounds: tuple[float, float], names: list[str], period: float,
                     notes: list[str]) -> tuple[F64, F64, F64, _Layout, int]:  # fmt: skip
    """Keep a second RC pair only where the data resolve it. Tried only when one pair leaves
    more than the noise floor (SECOND_RC_NOISE: a model at the noise has nothing left for a
    branch to explain). Then a time constant more than 3x the first's, and:

    - where the training part holds a relaxation (a rest after load, :func:`_relaxations`),
      Schwarz's criterion for its two parameters (the OCV correction's rule, :func:`_keep_ocv`)
      and each branch seen through its resistance or its capacitance
      (:func:`_branch_unseen`). At a fixed state of charge only the RC branches move the
      voltage, so a rest after load tells a slow branch from the OCV's shape;
    - without one, a slow branch and the OCV correction both follow the charge drawn under
      load and trade with each other: the RMSE must fall by SECOND_RC_GAIN and R1, tau1, R2,
      tau2 must each be identified."""
    n_data = _n_fit(profs)
    rmse1 = math.sqrt(float(res[:n_data] @ res[:n_data]) / n_data)
    floor = max(noise_floor(p) for p in profs)
    if rmse1 <= SECOND_RC_NOISE * floor:
        notes.append(
            f"second RC pair not tried: one pair leaves {1000 * rmse1:.2f} mV, within the "
            f"noise floor ({1000 * floor:.2f} mV): nothing left for a second branch to explain"
        )
        return x, res, jac, lay, 1
    lay2 = _layout(2, law, q_bounds, names, "heat_c_j_per_k_ah" in lay.names, like=lay)
    base = list(x[:4])
    tails = list(x[4:])
    starts = []
    for f in (10.0, 50.0):
        x0 = np.array([*base, x[2] - math.log(2.0), x[3] + math.log(f), *tails])
        starts.append(np.clip(x0, np.array(lay2.lo) + 1e-9, np.array(lay2.hi) - 1e-9))
    x2, res2, jac2 = _solve(lay2, profs, ocv, t_ref, starts)
    rss1, rss2 = float(res[:n_data] @ res[:n_data]), float(res2[:n_data] @ res2[:n_data])
    taus = sorted(math.exp(x2[lay2.names.index(t)]) for t in ("tau1_s", "tau2_s"))
    why = []
    if taus[1] <= 3.0 * taus[0]:
        why.append(f"time constants {taus[0]:.3g} and {taus[1]:.3g} s less than 3x apart")
    relaxed = _relaxations(profs, math.exp(x[0]))
    if relaxed:
        bic = n_data * math.log(max(rss1, 1e-30) / max(rss2, 1e-30)) - 2.0 * math.log(n_data)
        cov = _covariance(res2, jac2)
        why += [f"BIC {bic:+.1f} for it"] if bic <= 0.0 else []
        why += [w for w in (_branch_unseen(lay2, x2, cov, j, period) for j in (1, 2)) if w]
        how = f"{relaxed} rest(s) after load; BIC {bic:+.1f} for it"
    else:
        p2, _ = _params(lay2, x2, _uncertainty(res2, jac2), period, 1.0)
        if rss2 > (1.0 - SECOND_RC_GAIN) ** 2 * rss1:
            why.append(f"RMSE gain below {100 * SECOND_RC_GAIN:.0f} % and no rest after load")
        why += [f"{n}: {p2[n].reason}" for n in ("r1_ohm", "tau1_s", "r2_ohm", "tau2_s")
                if not p2[n].identifiable]  # fmt: skip
        how = "no rest after load"
    what = (f"RMSE {1000 * math.sqrt(rss1 / n_data):.2f} mV with one pair, "
            f"{1000 * math.sqrt(rss2 / n_data):.2f} mV with two")  # fmt: skip
    if not why:
        c2 = math.exp(x2[lay2.names.index("tau2_s")] - x2[lay2.names.index("r2_ohm")])
        notes.append(f"second RC pair kept: {what} ({how}; C2 = tau2 / R2 = {c2:.4g} F)")
        return x2, res2, jac2, lay2, 2
    notes.append(f"second RC pair not resolved by the data ({what}: {'; '.join(why)}): one "
                 "pair kept")  # fmt: skip
    return x, res, jac, lay, 1


def _relaxations(profs: Sequence[Profile], capacity_ah: float) -> int:
    """Rests after load in the logs: |I| below C/50 (REST_A_PER_AH) for REST_MIN_S or longer,
    with load before them — the voltage relaxing at a fixed state of charge."""
    count = 0
    for p in profs:
        quiet = np.abs(p.current_a) < REST_A_PER_AH * capacity_ah
        for a in _rests(p, capacity_ah):
            start = a
            while start > 0 and quiet[start - 1]:
                start -= 1
            count += int(start > 0 and bool(np.any(~quiet[:start])))
    return count


def _pct(sig_log: float) -> str:
    """A log-scale one-sigma as a relative uncertainty in per cent (capped for reading)."""
    rel = math.expm1(min(sig_log, 50.0))
    return f"{100 * rel:.0f} %" if rel <= 100.0 else "> 10000 %"


def _branch_unseen(lay: _Layout, x: F64, cov: F64, j: int, period: float) -> str:
    """Why RC branch j is not seen by the data ('' when it is): a value on a bound, a time
    constant below two logging periods (it merges with R0), or neither its resistance nor its
    capacitance C = tau / R identified (relative one-sigma above MAX_REL_UNCERTAINTY). Either
    suffices: a branch much slower than the data's rests is seen through its capacitance
    alone — its voltage is the charge through it over C, whatever R and tau are one by one
    (the Maccor pulse test's slow branch: R2 109 % and tau2 180 % alone, C2 55 %, correlation
    of log R2 and log tau2 0.93)."""
    r, t = lay.names.index(f"r{j}_ohm"), lay.names.index(f"tau{j}_s")
    for k in (r, t):
        if x[k] - lay.lo[k] < 1e-3 * (lay.hi[k] - lay.lo[k]) or lay.hi[k] - x[k] < 1e-3 * (
            lay.hi[k] - lay.lo[k]
        ):
            return f"{lay.names[k]} at a bound"
    tau = math.exp(x[t])
    if tau < TAU_MIN_PERIODS * period:
        return f"tau{j} {tau:.2g} s below {TAU_MIN_PERIODS:g} logging periods ({period:.3g} s)"
    sig_r = math.sqrt(max(float(cov[r, r]), 0.0))
    sig_c = math.sqrt(max(float(cov[r, r] + cov[t, t] - 2.0 * cov[r, t]), 0.0))
    if min(sig_r, sig_c) > math.log1p(MAX_REL_UNCERTAINTY):
        return f"branch {j}: neither R{j} ({_pct(sig_r)}) nor C{j} ({_pct(sig_c)}) identified"
    return ""


__all__ = ["FitParam", "FitResult", "Window", "fit"]
