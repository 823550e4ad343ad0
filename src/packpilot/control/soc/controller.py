"""The SOC estimator as a core method, and its one-pack face :class:`SocEstimator`."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from itertools import pairwise
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config.soc import SocConfig, VoltageSource
from packpilot.contract.bms import Event, Measurements, SwitchKind
from packpilot.contract.events import Labels, Reason, fields
from packpilot.contract.topology import PackInfo
from packpilot.control.method import CompiledController, Method, StatusChannel
from packpilot.control.soc import rules
from packpilot.control.soc.observer import N_X
from packpilot.control.soc.rules import SocParams, SocState
from packpilot.errors import ConfigError

REASONS = (
    Reason(
        "SocCorrected",
        "SOC {before:.3f} -> {after:.3f} from OCV {cell_v:.4f} V",
        fields("before", "after", "ocv_soc", "cell_v"),
    ),
    Reason(
        "SocObserverDiverged",
        "SOC observer diverged (innovations {nis:.1f}x their variance over {window_s:g} s): "
        "SOC from the coulomb counter ({fallback:.3f}; the observer had {observer:.3f}), "
        "observer restarted",
        fields("nis", "window_s", "fallback", "observer"),
    ),
    Reason(
        "SocObserverResumed",
        "SOC observer consistent again (innovations {nis:.2f}x their variance): SOC "
        "{soc:.3f} from the observer",
        fields("nis", "soc"),
    ),
    Reason(
        "SocObserverInconsistent",
        "SOC observer {observer:.3f} is {z:.1f} sigma from the coulomb counter's {fallback:.3f} "
        "(the counter uncertain by {fallback_sigma:.3f}): SOC from the counter, observer "
        "restarted; its cell model may not describe this battery",
        fields("observer", "fallback", "fallback_sigma", "z"),
    ),
    Reason(
        "SocCellSetMismatch",
        "battery resistance at current steps {step_ohm:.4f} ohm per cell, {ratio:.1f}x the cell "
        "set's {set_ohm:.4f}: the cell set does not describe this battery (fit its logs: "
        "packpilot fit); beyond 10x the observer is not trusted",
        fields("step_ohm", "set_ohm", "ratio", "step_a"),
    ),
)
STATUS = (
    StatusChannel("soc_est"),
    StatusChannel("soc_rest_s"),
    StatusChannel("soc_fallback"),
    StatusChannel("soc_sigma"),
    StatusChannel("soc_emf_v"),
    StatusChannel("soc_r0_ohm"),
    StatusChannel("soc_v_rc_v"),
    StatusChannel("soc_capacity_ah"),
    StatusChannel("soc_current_offset_a"),
    StatusChannel("soc_nis"),
    StatusChannel("soc_observer_ok", "b"),
    StatusChannel("soc_time_to_go_s", "o"),
    StatusChannel("soc_time_to_cutoff_s", "o"),
    StatusChannel("soc_time_to_full_s", "o"),
    StatusChannel("soc_load_avg_a", "o"),
)
assert STATUS[rules.ST_OK].name == "soc_observer_ok"
assert STATUS[rules.ST_LOAD].name == "soc_load_avg_a"


def _finite(x: float) -> bool:
    return isinstance(x, int | float) and math.isfinite(x)


def check_ocv(
    ocv_soc: Iterable[float], ocv_v: Iterable[float]
) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The OCV table as (volts, soc), or a :class:`ConfigError` saying what is wrong."""
    soc = tuple(float(x) for x in ocv_soc)
    volts = tuple(float(x) for x in ocv_v)
    if len(soc) < 2 or len(soc) != len(volts):
        raise ConfigError(
            f"soc: OCV table needs >= 2 points and equal lengths, got {len(soc)} SOC and "
            f"{len(volts)} voltage values"
        )
    if not all(_finite(x) for x in soc + volts):
        raise ConfigError("soc: OCV table values must be finite numbers")
    if any(b <= a for a, b in pairwise(soc)):
        raise ConfigError("soc: ocv_soc must be strictly increasing")
    if any(b <= a for a, b in pairwise(volts)):
        k = next(k for k, (a, b) in enumerate(pairwise(volts)) if b <= a)
        raise ConfigError(
            f"soc: ocv_v must be strictly increasing to be inverted; point {k + 1} "
            f"({volts[k + 1]} V) is not above point {k} ({volts[k]} V)"
        )
    return volts, soc


WEAK_TAU_S = 30.0
"""Low-pass of the group voltages that pick the weakest group: long against the noise of one
sample (at 0.1-5 s periods, 6-300 samples), short against how fast the weakest changes."""


CUTOFF_TAU_S = 15.0
"""How fast the time to cut-off shown follows a new prediction (s): its second-to-second noise
near the trip (the filter's voltage jitters by ~1 mV, ~1 s at the knee, where 10 % is 1-2 s)
is averaged out, while a real change (the recent average load moves over minutes) shows
within seconds. Measured (h28cut, the acceptance bench over 8 sensor seeds x start 10 % low /
high x both loads): worst of the 32 runs 10.6 % at 5 s, 9.8 % at 10 s, 8.9 % at 15 s; held-out
seeds 4-7 alone 8.6 / 8.6 / 8.9 / 9.6 % at 5 / 10 / 15 / 20 s."""


def build(config: SocConfig, infos: Sequence[PackInfo]) -> tuple[SocParams, SocState]:
    info = infos[0]
    n = info.n_batteries
    for pk in infos:
        if len(pk.capacity_ah) != n:
            raise ConfigError("soc: PackInfo.capacity_ah must give one capacity per battery")
        for i, c in enumerate(pk.capacity_ah):
            if not (_finite(c) and c > 0.0):
                raise ConfigError(f"soc: capacity_ah[{i}] must be > 0 Ah, got {c}")
    volts, soc = check_ocv(info.ocv_soc, info.ocv_v)
    series = np.array(
        [g * c for g, c in zip(info.groups_per_battery, info.cells_per_group, strict=True)],
        np.int64,
    )
    if config.voltage == "avg" and not (series > 0).all():
        raise ConfigError("soc: voltage = 'avg' needs series_cells > 0 for every battery")
    prm = SocParams(
        rest_current_a=float(config.rest_current_a),
        rest_time_s=float(config.rest_time_s),
        blend=float(config.blend),
        use_min_cell=config.voltage == "min",
        ocv_v=np.array(volts, np.float64),
        ocv_soc=np.array(soc, np.float64),
        series_cells=series,
        cells_per_group=np.array(info.cells_per_group, np.int64),
        bal_lo_a=-float(info.balancer_max_a) if info.balancer_bidirectional else 0.0,
        bal_hi_a=float(info.balancer_max_a),
        bal_eff=float(info.balancer_efficiency),
        weak_tau_s=WEAK_TAU_S,
        **_observer_params(config, info),
    )
    shape = (len(infos), n)
    nan = np.full(shape, np.nan)
    st = SocState(
        soc=nan.copy(),
        rest_s=np.zeros(shape),
        next_fix_s=np.zeros(shape),
        corrections=np.zeros(shape, np.int64),
        shown_soc=nan.copy(),
        x=np.full((*shape, N_X), np.nan),
        cov=np.zeros((*shape, N_X, N_X)),
        fm=np.zeros((*shape, N_X, N_X)),
        wk=np.zeros((*shape, N_X, N_X)),
        hv=np.zeros((*shape, N_X)),
        kv=np.zeros((*shape, N_X)),
        nis_avg=np.ones(shape),
        obs_age_s=np.zeros(shape),
        obs_ok=np.zeros(shape, np.bool_),
        absent=np.zeros(shape, np.bool_),
        grp_lp=np.full((*shape, max(info.groups_per_battery, default=1)), np.nan),
        weak_g=np.full(shape, -1, np.int64),
        bal_a=np.zeros((*shape, max(info.groups_per_battery, default=1))),
        pred_age_s=np.full(shape, np.inf),
        load_age_s=np.zeros(shape),
        v_res_avg_v=np.zeros(shape),
        load_exc_a=np.zeros(shape),
        fb_var0=nan.copy(),
        fb_net=np.zeros(shape),
        fb_age_s=np.zeros(shape),
        fb_absent=np.zeros(shape, np.bool_),
        prev_i_a=nan.copy(),
        prev_v=nan.copy(),
        step_hi_n=np.zeros(shape, np.int64),
        misfit=np.zeros(shape),
        **{name: nan.copy() for name in _OUTPUTS},
    )
    return prm, st


_OUTPUTS = (
    "emf_v", "r0_ohm", "r0_var_ohm2", "r1_ohm", "tau_s", "v_rc_v", "v_rc_var_v2", "soc_var",
    "capacity_ah", "capacity_var_ah2", "offset_a", "offset_var_a2", "load_avg_a",
    "time_to_go_s", "time_to_cutoff_s", "time_to_full_s", "cv_left_s",
    "chg_temp0_c",
)  # fmt: skip


def _observer_params(config: SocConfig, info: PackInfo) -> dict[str, Any]:
    """The observer's part of :class:`SocParams`: the cell tables of ``info`` (empty ones turn
    the observer off: the fallback is then the estimate) and the filter's tuning."""
    nt, ns = len(info.ecm_temp_c), len(info.ecm_soc)
    tables = (info.ecm_r0_ohm, info.ecm_r1_ohm, info.ecm_tau_s)
    have = nt >= 2 and ns >= 2 and all(len(t) == nt * ns for t in tables)
    if have and not all(_finite(x) and x > 0.0 for t in tables for x in t):
        raise ConfigError("soc: the cell set's R0, R1 and tau tables must be finite and > 0")
    n = info.n_batteries
    r_nom = info.r_scale or (1.0,) * n
    if len(r_nom) != n or not all(_finite(x) and x > 0.0 for x in r_nom):
        raise ConfigError(f"soc: PackInfo.r_scale needs {n} positive factors, got {r_nom}")

    def arr(t: tuple[float, ...], dummy: int) -> Any:
        return np.array(t, np.float64) if have else np.ones(dummy)

    sig0 = (
        config.ekf_soc_sigma0,
        0.05,
        config.ekf_resistance_sigma0,
        config.ekf_capacity_sigma0,
        config.ekf_offset_sigma0_a,
    )
    walk = (
        config.ekf_current_sigma_a,
        config.ekf_resistance_walk,
        config.ekf_capacity_walk,
        config.ekf_offset_walk_a if config.ekf_offset_sigma0_a > 0.0 else 0.0,
    )
    return {
        "observer": bool(config.observer and have),
        "ax_t": np.array(info.ecm_temp_c, np.float64) if have else np.array([0.0, 1.0]),
        "ax_s": np.array(info.ecm_soc, np.float64) if have else np.array([0.0, 1.0]),
        "r0_tab": arr(info.ecm_r0_ohm, 4),
        "r1_tab": arr(info.ecm_r1_ohm, 4),
        "tau_tab": arr(info.ecm_tau_s, 4),
        **_entropic(info),
        "r_nom": np.array(r_nom, np.float64),
        "sig0": np.array(sig0, np.float64),
        "walk": np.array(walk, np.float64),
        "var_v": float(config.ekf_voltage_sigma_v) ** 2,
        "nis_window_s": float(config.nis_window_s),
        "nis_limit": float(config.nis_limit),
        "offset_max_a": float(4.0 * config.ekf_offset_sigma0_a),
        "load_tau_s": float(config.load_avg_s),
        "cutoff_cell_v": float(
            config.cutoff_cell_v if config.cutoff_cell_v is not None else info.cell_v_min_v
        ),
        "predict_every_s": 1.0,
        "cutoff_tau_s": CUTOFF_TAU_S,
        "consistency_sigma": float(config.consistency_sigma),
        **_full(config, info),
    }


def _full(config: SocConfig, info: PackInfo) -> dict[str, Any]:
    """Where the time to full ends: the charger's CV voltage per cell (default the cell set's
    upper voltage limit, else its OCV at 100 %) and the end current (default C/20 of each
    battery's capacity, the common CC/CV termination)."""
    v = config.full_cell_v
    if v is None:
        v = info.cell_v_max_v
    if not (_finite(v) and v > 0.0):
        v = float(np.interp(1.0, info.ocv_soc, info.ocv_v)) if info.ocv_soc else 4.2
    cap = info.capacity_ah or (1.0,) * info.n_batteries
    ends = [config.full_current_a if config.full_current_a is not None else 0.05 * c
            for c in cap]  # fmt: skip
    return {"full_cell_v": float(v), "full_current_a": np.array(ends, np.float64),
            "full_path_ohm": _path_per_cell(config, info)}  # fmt: skip


def _path_per_cell(config: SocConfig, info: PackInfo) -> NDArray[np.float64]:
    """(B,) each battery's charge path (``charge_path_ohm``, else the pack's stated one, else
    0) over its series cells: the time to full's model is one cell, so its share of the drop
    that lowers the charger's CV voltage at the cells."""
    n = info.n_batteries
    stated = info.charge_path_ohm if len(info.charge_path_ohm) == n else (0.0,) * n
    out = np.zeros(n, np.float64)
    for b in range(n):
        r = config.charge_path_ohm if config.charge_path_ohm is not None else stated[b]
        known = b < min(len(info.groups_per_battery), len(info.cells_per_group))
        series = info.groups_per_battery[b] * info.cells_per_group[b] if known else 0
        if _finite(r) and r > 0.0 and series > 0:
            out[b] = float(r) / series
    return out


def _entropic(info: PackInfo) -> dict[str, Any]:
    """The OCV's temperature term of :class:`SocParams` from ``info`` (none where the cell set
    has no reference temperature or the table does not fit the OCV table)."""
    nt, n = len(info.ocv_dudt_temp_c), len(info.ocv_soc)
    tab = info.ocv_dudt_v_per_k
    have = math.isfinite(info.ocv_ref_temp_c) and nt >= 2 and len(tab) == nt * n
    if have and not all(_finite(x) for x in tab + info.ocv_dudt_temp_c):
        raise ConfigError("soc: the cell set's dU/dT table must be finite")
    return {
        "du_t": np.array(info.ocv_dudt_temp_c if have else (0.0, 1.0), np.float64),
        "du_tab": np.array(tab, np.float64) if have else np.zeros(2 * n),
        "t_ref_c": float(info.ocv_ref_temp_c) if have else math.nan,
    }


def _labels(prm: SocParams) -> Labels:
    return {}


METHOD = Method(
    name="soc",
    src=6,
    config=SocConfig,
    build=build,
    step_packs=rules.step_packs,
    reasons=REASONS,
    status=STATUS,
    labels=_labels,
    max_events=lambda info: 3 * info.n_batteries,
    after=rules.note_balancer_packs,
)


class SocEstimator(CompiledController):
    """Per-battery SOC by coulomb counting with OCV correction after a rest (one pack).

    ``capacity_ah`` per battery; ``ocv_soc`` / ``ocv_v`` the cell OCV curve (``ocv_v`` strictly
    increasing); ``series_cells`` per battery is needed for ``voltage='avg'``. ``soc0`` gives
    initial estimates; without it (or where an entry is NaN) the first tick initialises the
    battery from the OCV of its cell voltage, as a BMS does at power-up after the pack rested.
    """

    method = METHOD
    prm: SocParams
    st: SocState

    def __init__(
        self,
        capacity_ah: Iterable[float],
        ocv_soc: Iterable[float],
        ocv_v: Iterable[float],
        rest_current_a: float = 0.1,
        rest_time_s: float = 600.0,
        *,
        blend: float = 1.0,
        voltage: VoltageSource = "min",
        series_cells: Iterable[int] | None = None,
        soc0: Iterable[float] | None = None,
    ) -> None:
        cfg = SocConfig(
            rest_current_a=rest_current_a, rest_time_s=rest_time_s, blend=blend, voltage=voltage
        )
        caps = tuple(float(c) for c in capacity_ah)
        n = len(caps)
        series = tuple(int(s) for s in series_cells) if series_cells is not None else (0,) * n
        if len(series) != n:
            raise ConfigError(f"soc: series_cells has {len(series)} entries, need {n}")
        info = PackInfo(
            n_batteries=n,
            groups_per_battery=series,
            cells_per_group=(1,) * n,
            switch_kind=(SwitchKind.MOSFET_PAIR,) * n,
            capacity_ah=caps,
            ocv_soc=tuple(float(x) for x in ocv_soc),
            ocv_v=tuple(float(x) for x in ocv_v),
        )
        super().__init__(cfg, info)
        init = list(soc0) if soc0 is not None else [math.nan] * n
        if len(init) != n:
            raise ConfigError(f"soc: soc0 has {len(init)} entries, need {n}")
        for i, s in enumerate(init):
            self.st.soc[0, i] = min(1.0, max(0.0, float(s))) if _finite(s) else math.nan

    @classmethod
    def from_config(
        cls,
        config: SocConfig,
        pack: PackInfo,
        ocv_soc: Iterable[float] | None = None,
        ocv_v: Iterable[float] | None = None,
        soc0: Iterable[float] | None = None,
    ) -> SocEstimator:
        """Build for a pack: capacities, series counts (and the OCV curve, unless given)."""
        if len(pack.capacity_ah) != pack.n_batteries:
            raise ConfigError("soc: PackInfo.capacity_ah must give one capacity per battery")
        series = tuple(
            g * c for g, c in zip(pack.groups_per_battery, pack.cells_per_group, strict=True)
        )
        return cls(
            pack.capacity_ah,
            pack.ocv_soc if ocv_soc is None else ocv_soc,
            pack.ocv_v if ocv_v is None else ocv_v,
            config.rest_current_a,
            config.rest_time_s,
            blend=config.blend,
            voltage=config.voltage,
            series_cells=series,
            soc0=soc0,
        )

    @property
    def soc(self) -> tuple[float, ...]:
        """Current estimates (NaN until a battery has been initialised)."""
        return tuple(float(x) for x in self.st.soc[0])

    def soc_from_ocv(self, cell_v: float) -> float:
        """Inverse of the OCV table, clamped to its ends and to 0..1 (NaN for a NaN input)."""
        return float(rules.soc_from_ocv(self.prm, float(cell_v) if _finite(cell_v) else math.nan))

    def update(self, meas: Measurements, dt_s: float) -> tuple[tuple[float, ...], list[Event]]:
        """Advance every battery by one tick; returns the estimates and any correction events."""
        out = self.step(meas, dt_s)
        return self.soc, list(out.events)


__all__ = ["METHOD", "REASONS", "STATUS", "SocEstimator", "build", "check_ocv"]
