"""Thevenin equivalent-circuit cell model, vectorized over cells, with PyBaMM's conventions.

Per cell (current ``I`` positive on discharge, SoC as a fraction)::

    dSoC/dt   = -I / (3600 Q)
    deta_j/dt = (I R_j - eta_j) / (R_j C_j)            j = 1..n_rc   (eta_j = drop across RC j)
    V         = OCV(SoC, T) - sum_j eta_j - I R0
    Q_heat    = I^2 R0 + I sum_j eta_j - I (T + 273.15) dU/dT

``eta_j`` is the *drop* across RC branch j; PyBaMM's "Element-j overpotential [V]" is ``-eta_j``.
R0, R_j, C_j are trilinear tables on (cell temperature, current, SoC); dU/dT is a bilinear table on
(OCV or SoC, temperature), as in PyBaMM's ``ECM_Example`` where it is looked up by the OCV value.
The OCV table is the OCV at ``ocv_ref_temp_c``; when that is ``None`` (PyBaMM's convention) the
OCV does not depend on temperature and dU/dT only enters the reversible heat.

Discretization for a step of constant current (see docs/cell_model.md): SoC is advanced exactly;
the tables are read once per step at (T at step start, I, SoC at mid-step); each RC branch uses its
exact exponential solution; the heat (with the RC drop averaged exactly over the step) is held
constant and the thermal network is advanced exactly (:mod:`packpilot.model.thermal`).

The hot loops are numba kernels; ``*_numpy`` functions are a plain NumPy reference used in tests.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal, TypeVar, cast

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from packpilot.errors import ConfigError
from packpilot.model.thermal import KELVIN, ThermalParams, step_coefficients

__all__ = [
    "FORMAT",
    "PARAMETER_SETS",
    "CellParams",
    "CellState",
    "CellTrace",
    "ThermalParams",
    "advance",
    "advance_numpy",
    "initial_state",
    "load_parameter_file",
    "load_parameter_set",
    "ocv_v",
    "parameter_set_path",
    "params_from_dict",
    "params_to_dict",
    "simulate_current",
    "step",
    "thevenin",
    "thevenin_numpy",
    "write_parameter_file",
]

FORMAT = "packpilot-cell/1"
PARAMETER_SETS = ("ecm_example", "uav_5ah", "lfp_storage")

F64 = NDArray[np.float64]
_F = TypeVar("_F", bound=Callable[..., Any])


# error_model="numpy": no zero-division checks; _nrt=False: kernels never allocate, so no
# reference counting of the array arguments (which otherwise costs ~10x in the inlined helpers);
# contract: allow fused multiply-add.
_NUMBA_OPTIONS: dict[str, Any] = {
    "cache": True,
    "nogil": True,
    "error_model": "numpy",
    "_nrt": False,
    "fastmath": {"contract"},
}


def _jit(fn: _F) -> _F:
    """``numba.njit`` with the options above, keeping the Python signature visible to mypy."""
    return cast(_F, numba.njit(**_NUMBA_OPTIONS)(fn))


def _jit_inline(fn: _F) -> _F:
    """A kernel helper inlined into its callers at numba-IR level (no call, hoistable loads)."""
    return cast(_F, numba.njit(inline="always", **_NUMBA_OPTIONS)(fn))


# --------------------------------------------------------------------------------------------
# Parameters
# --------------------------------------------------------------------------------------------

_AXES_RC = ("rc_temp_c", "rc_current_a", "rc_soc")
_TABLES_RC = ("r0_ohm", "r1_ohm", "c1_f", "r2_ohm", "c2_f")


@dataclass(frozen=True, eq=False)
class _Packed:
    """Tables laid out for the kernels (built once per parameter set)."""

    rc_flat: F64  # [T][I][SoC][table], tables r0, r1, c1[, r2, c2]
    ax_t: F64
    ax_i: F64
    ax_s: F64
    ocv_x: F64
    ocv_y: F64
    du_x: F64
    du_t: F64
    du_y: F64
    fmeta: F64  # inverse spacing of uniform axes (0 = not uniform) x6, ocv reference temp (nan)
    imeta: NDArray[np.int64]  # n_rc, dudt on OCV (1)/SoC (0), clamp (1)/linear (0), nT, nI, nS, nt


@dataclass(frozen=True, eq=False)
class CellParams:
    """An equivalent-circuit parameter set; field names are also the keys of the JSON files.

    RC tables have shape ``(len(rc_temp_c), len(rc_current_a), len(rc_soc))``; ``dudt_v_per_k``
    has shape ``(len(dudt_x), len(dudt_temp_c))`` where ``dudt_x`` holds OCV values
    (``dudt_axis="ocv_v"``, PyBaMM's convention) or SoC values (``dudt_axis="soc"``).
    Outside a table the value is held at the edge (``extrapolation="clamp"``) or extended
    linearly (``"linear"``, what PyBaMM's ``Interpolant`` does).
    """

    name: str
    capacity_ah: float
    ocv_soc: F64
    ocv_table_v: F64
    dudt_axis: Literal["ocv_v", "soc"]
    dudt_x: F64
    dudt_temp_c: F64
    dudt_v_per_k: F64
    rc_temp_c: F64
    rc_current_a: F64
    rc_soc: F64
    r0_ohm: F64
    r1_ohm: F64
    c1_f: F64
    thermal: ThermalParams
    v_min_v: float
    v_max_v: float
    provenance: str
    r2_ohm: F64 | None = None
    c2_f: F64 | None = None
    ocv_ref_temp_c: float | None = None
    extrapolation: Literal["clamp", "linear"] = "clamp"
    _packed: _Packed = field(init=False, repr=False, compare=False)
    _thermal_cache: dict[float, F64] = field(
        init=False, repr=False, compare=False, default_factory=dict
    )

    @property
    def n_rc(self) -> int:
        """Number of RC branches (1 or 2)."""
        return 1 if self.r2_ohm is None else 2

    def __post_init__(self) -> None:
        _validate_and_freeze(self)
        object.__setattr__(self, "_packed", _pack(self))


def _fail(name: str, field_name: str, msg: str) -> ConfigError:
    return ConfigError(f"cell parameter set '{name}': field '{field_name}': {msg}")


def _float_array(p: CellParams, key: str, ndim: int) -> F64:
    raw = getattr(p, key)
    try:
        arr = np.array(raw, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(p.name, key, "must be an array of numbers") from None
    if arr.ndim != ndim:
        raise _fail(p.name, key, f"must be a {ndim}-D array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise _fail(p.name, key, "contains NaN or infinite values")
    arr = np.ascontiguousarray(arr)
    arr.setflags(write=False)
    object.__setattr__(p, key, arr)
    return arr


def _axis(p: CellParams, key: str) -> F64:
    arr = _float_array(p, key, 1)
    if arr.size < 2:
        raise _fail(p.name, key, f"needs at least 2 points, got {arr.size}")
    if not np.all(np.diff(arr) > 0.0):
        raise _fail(p.name, key, "must be strictly increasing")
    return arr


def _scalar(p: CellParams, key: str, positive: bool = False) -> float:
    value = getattr(p, key)
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise _fail(p.name, key, f"must be a number, got {value!r}") from None
    if not math.isfinite(x):
        raise _fail(p.name, key, f"must be finite, got {value!r}")
    if positive and x <= 0.0:
        raise _fail(p.name, key, f"must be > 0, got {value!r}")
    object.__setattr__(p, key, x)
    return x


def _validate_and_freeze(p: CellParams) -> None:
    if not isinstance(p.name, str) or not p.name:
        raise ConfigError("cell parameter set: field 'name': must be a non-empty string")
    _scalar(p, "capacity_ah", positive=True)
    vmin, vmax = _scalar(p, "v_min_v", positive=True), _scalar(p, "v_max_v", positive=True)
    if vmin >= vmax:
        raise _fail(p.name, "v_min_v", f"must be below v_max_v ({vmin} >= {vmax})")
    if p.ocv_ref_temp_c is not None:
        _scalar(p, "ocv_ref_temp_c")
    if p.extrapolation not in ("clamp", "linear"):
        raise _fail(
            p.name, "extrapolation", f"must be 'clamp' or 'linear', got {p.extrapolation!r}"
        )
    if p.dudt_axis not in ("ocv_v", "soc"):
        raise _fail(p.name, "dudt_axis", f"must be 'ocv_v' or 'soc', got {p.dudt_axis!r}")
    if not isinstance(p.thermal, ThermalParams):
        raise _fail(p.name, "thermal", "must be a ThermalParams")
    if not isinstance(p.provenance, str) or not p.provenance.strip():
        raise _fail(p.name, "provenance", "must be a non-empty string")

    soc = _axis(p, "ocv_soc")
    ocv = _float_array(p, "ocv_table_v", 1)
    if ocv.shape != soc.shape:
        raise _fail(p.name, "ocv_table_v", f"has {ocv.size} points, ocv_soc has {soc.size}")

    dx, dt = _axis(p, "dudt_x"), _axis(p, "dudt_temp_c")
    du = _float_array(p, "dudt_v_per_k", 2)
    if du.shape != (dx.size, dt.size):
        raise _fail(
            p.name, "dudt_v_per_k", f"shape {du.shape} does not match axes {(dx.size, dt.size)}"
        )

    shape = tuple(_axis(p, key).size for key in _AXES_RC)
    if (p.r2_ohm is None) != (p.c2_f is None):
        missing = "c2_f" if p.c2_f is None else "r2_ohm"
        raise _fail(p.name, missing, "r2_ohm and c2_f must be given together")
    for key in _TABLES_RC:
        if getattr(p, key) is None:
            continue
        tab = _float_array(p, key, 3)
        if tab.shape != shape:
            raise _fail(p.name, key, f"shape {tab.shape} does not match axes {shape}")
        if not np.all(tab > 0.0):
            raise _fail(p.name, key, "must be > 0 everywhere")


def _inv_spacing(ax: F64) -> float:
    """1/dx when the axis is uniform (to 1e-9 of dx), else 0 (binary search)."""
    d = np.diff(ax)
    if np.all(np.abs(d - d[0]) <= 1e-9 * d[0]):
        return float((ax.size - 1) / (ax[-1] - ax[0]))
    return 0.0


def _pack(p: CellParams) -> _Packed:
    names = ["r0_ohm", "r1_ohm", "c1_f"] + (["r2_ohm", "c2_f"] if p.n_rc == 2 else [])
    rc_flat = np.ascontiguousarray(np.stack([getattr(p, k) for k in names], axis=-1).ravel())
    axes = (p.rc_temp_c, p.rc_current_a, p.rc_soc, p.ocv_soc, p.dudt_x, p.dudt_temp_c)
    ref = np.nan if p.ocv_ref_temp_c is None else p.ocv_ref_temp_c
    fmeta = np.array([*(_inv_spacing(a) for a in axes), ref], dtype=np.float64)
    flags = [p.n_rc, int(p.dudt_axis == "ocv_v"), int(p.extrapolation == "clamp")]
    imeta = np.array([*flags, *p.r0_ohm.shape, len(names)], dtype=np.int64)
    return _Packed(
        rc_flat=rc_flat,
        ax_t=p.rc_temp_c,
        ax_i=p.rc_current_a,
        ax_s=p.rc_soc,
        ocv_x=p.ocv_soc,
        ocv_y=p.ocv_table_v,
        du_x=p.dudt_x,
        du_t=p.dudt_temp_c,
        du_y=p.dudt_v_per_k,
        fmeta=fmeta,
        imeta=imeta,
    )


# --------------------------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------------------------

_REQUIRED = (
    "name",
    "capacity_ah",
    "ocv_soc",
    "ocv_table_v",
    "dudt_axis",
    "dudt_x",
    "dudt_temp_c",
    "dudt_v_per_k",
    "rc_temp_c",
    "rc_current_a",
    "rc_soc",
    "r0_ohm",
    "r1_ohm",
    "c1_f",
    "thermal",
    "v_min_v",
    "v_max_v",
    "provenance",
)
_OPTIONAL = ("r2_ohm", "c2_f", "ocv_ref_temp_c", "extrapolation")
_THERMAL_KEYS = (
    "cell_heat_capacity_j_per_k",
    "jig_heat_capacity_j_per_k",
    "cell_jig_w_per_k",
    "jig_air_w_per_k",
    "nodes",
)


def params_from_dict(data: dict[str, Any]) -> CellParams:
    """Build a :class:`CellParams` from the JSON structure (``format`` key optional)."""
    if not isinstance(data, dict):
        raise ConfigError("cell parameter file: top level must be a JSON object")
    fmt = data.get("format", FORMAT)
    if fmt != FORMAT:
        raise ConfigError(f"field 'format': expected {FORMAT!r}, got {fmt!r}")
    unknown = sorted(set(data) - set(_REQUIRED) - set(_OPTIONAL) - {"format", "notes"})
    if unknown:
        raise ConfigError(f"field '{unknown[0]}': unknown field")
    for key in _REQUIRED:
        if key not in data:
            raise ConfigError(f"field '{key}': missing")
    th = data["thermal"]
    if not isinstance(th, dict):
        raise ConfigError("field 'thermal': must be an object")
    for key in _THERMAL_KEYS:
        if key not in th:
            raise ConfigError(f"field 'thermal.{key}': missing")
    extra = sorted(set(th) - set(_THERMAL_KEYS))
    if extra:
        raise ConfigError(f"field 'thermal.{extra[0]}': unknown field")
    try:
        thermal = ThermalParams(
            cell_heat_capacity_j_per_k=float(th["cell_heat_capacity_j_per_k"]),
            jig_heat_capacity_j_per_k=float(th["jig_heat_capacity_j_per_k"]),
            cell_jig_w_per_k=float(th["cell_jig_w_per_k"]),
            jig_air_w_per_k=float(th["jig_air_w_per_k"]),
            nodes=int(th["nodes"]),
        )
    except (TypeError, ValueError) as err:
        raise ConfigError(f"field 'thermal': values must be numbers ({err})") from None
    kwargs = {k: data[k] for k in (*_REQUIRED, *_OPTIONAL) if k in data and k != "thermal"}
    return CellParams(thermal=thermal, **kwargs)


def params_to_dict(params: CellParams) -> dict[str, Any]:
    """The JSON structure of a parameter set (inverse of :func:`params_from_dict`)."""
    out: dict[str, Any] = {"format": FORMAT}
    for key in (*_REQUIRED, *_OPTIONAL):
        value = getattr(params, key)
        if key == "thermal":
            value = {k: getattr(params.thermal, k) for k in _THERMAL_KEYS}
        elif isinstance(value, np.ndarray):
            value = value.tolist()
        elif value is None and key in ("r2_ohm", "c2_f"):
            continue
        out[key] = value
    return out


def _dump(value: Any, indent: int) -> str:
    """JSON with the innermost number lists on one line (readable tables, exact floats)."""
    pad = " " * indent
    if isinstance(value, dict):
        items = [f'{pad}  "{k}": {_dump(v, indent + 2).lstrip()}' for k, v in value.items()]
        return pad + "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(value, list) and value and isinstance(value[0], list):
        rows = [_dump(v, indent + 2) for v in value]
        return pad + "[\n" + ",\n".join(rows) + "\n" + pad + "]"
    return pad + json.dumps(value)


def write_parameter_file(params: CellParams, path: str | Path) -> None:
    """Write a parameter set in the format read by :func:`load_parameter_file`."""
    Path(path).write_text(_dump(params_to_dict(params), 0) + "\n", encoding="utf-8")


def load_parameter_file(path: str | Path) -> CellParams:
    """Load and validate a user parameter set (JSON, format ``packpilot-cell/1``)."""
    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except OSError as err:
        raise ConfigError(f"{p}: cannot read cell parameter file ({err.strerror})") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{p}: line {err.lineno}: invalid JSON ({err.msg})") from None
    try:
        return params_from_dict(data)
    except ConfigError as err:
        raise ConfigError(f"{p}: {err}") from None


def parameter_set_path(name: str) -> Path:
    """Path of a shipped parameter set file."""
    if name not in PARAMETER_SETS:
        raise ConfigError(
            f"cell parameter set {name!r}: unknown, expected one of {', '.join(PARAMETER_SETS)}"
        )
    return Path(str(resources.files("packpilot") / "data" / "cells" / f"{name}.json"))


_SET_CACHE: dict[str, CellParams] = {}


def load_parameter_set(name: str) -> CellParams:
    """Load a shipped parameter set: ``ecm_example``, ``uav_5ah`` or ``lfp_storage``.

    Sets are immutable, so each is parsed once per process and shared.
    """
    if name not in _SET_CACHE:
        _SET_CACHE[name] = load_parameter_file(parameter_set_path(name))
    return _SET_CACHE[name]


# --------------------------------------------------------------------------------------------
# State
# --------------------------------------------------------------------------------------------


@dataclass
class CellState:
    """State of n cells: SoC (fraction), RC drops ``eta_v`` (n, n_rc), cell and jig temps."""

    soc: F64
    eta_v: F64
    temp_c: F64
    jig_temp_c: F64

    def copy(self) -> CellState:
        return CellState(
            self.soc.copy(), self.eta_v.copy(), self.temp_c.copy(), self.jig_temp_c.copy()
        )


@dataclass(frozen=True)
class CellTrace:
    """A single-cell simulation sampled at the step boundaries ``t_s = k dt`` (len n+1).

    Sample 0 is taken with the first step's current; sample k >= 1 at the end of step k-1 with
    that step's current still flowing (the left limit before the current changes), so
    ``current_a[k]`` is the current that produced ``voltage_v[k]``.
    """

    t_s: F64
    current_a: F64
    voltage_v: F64
    soc: F64
    temp_c: F64
    jig_temp_c: F64


def _cells(x: ArrayLike, n: int) -> F64:
    """x as a C-contiguous float64 array of shape (n,) (scalars broadcast; no copy if fine)."""
    if isinstance(x, float | int):
        return np.full(n, float(x))
    a = np.asarray(x, dtype=np.float64)
    if a.shape == (n,):
        return a if a.flags.c_contiguous else np.ascontiguousarray(a)
    if a.ndim == 0:
        return np.full(n, float(a))
    return np.ascontiguousarray(np.broadcast_to(a, (n,)))


def _state_arrays(params: CellParams, state: CellState) -> tuple[int, F64, F64, F64, F64]:
    """State arrays as the kernels need them (C-contiguous float64, no copy when they already
    are); shapes checked, since the kernels do no bounds checking."""
    f64 = np.float64
    soc = np.ascontiguousarray(state.soc, dtype=f64)
    eta = np.ascontiguousarray(state.eta_v, dtype=f64)
    tc = np.ascontiguousarray(state.temp_c, dtype=f64)
    tj = np.ascontiguousarray(state.jig_temp_c, dtype=f64)
    n = soc.shape[0]
    if eta.shape != (n, params.n_rc) or tc.shape != (n,) or tj.shape != (n,) or soc.ndim != 1:
        raise ValueError(
            f"inconsistent CellState shapes: soc {soc.shape}, eta_v {eta.shape} (n_rc = "
            f"{params.n_rc}), temp_c {tc.shape}, jig_temp_c {tj.shape}"
        )
    return n, soc, eta, tc, tj


def initial_state(params: CellParams, n: int, soc0: ArrayLike, ambient_c: ArrayLike) -> CellState:
    """n cells at rest: RC branches relaxed, cell and jig at ambient."""
    amb = _cells(ambient_c, n).copy()
    return CellState(
        soc=_cells(soc0, n).copy(),
        eta_v=np.zeros((n, params.n_rc)),
        temp_c=amb,
        jig_temp_c=amb.copy(),
    )


# --------------------------------------------------------------------------------------------
# Kernels (numba). The scalar helpers are inlined into the fleet and single-cell loops.
# --------------------------------------------------------------------------------------------


@_jit_inline
def _frac(x: float, ax: F64, inv: float) -> tuple[int, float]:
    """Bracket i (0..n-2) of x on ax and the unclamped fraction of x within it.

    Uniform axes (``inv`` = 1/spacing > 0) take O(1) and no division; others a binary search.
    At a node, rounding may pick either neighbouring bracket: the interpolated value is the
    same to rounding. NaN gives bracket 0 (never an out-of-range index) and a NaN fraction.
    """
    n = ax.shape[0]
    if inv > 0.0:
        f = (x - ax[0]) * inv
        g = f
        if not g > 0.0:
            g = 0.0
        i = int(g) if g < n - 2 else n - 2
        return i, f - i
    lo, hi = 0, n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if x >= ax[mid]:
            lo = mid
        else:
            hi = mid
    return lo, (x - ax[lo]) / (ax[lo + 1] - ax[lo])


@_jit_inline
def _lim(t: float, clamp: bool) -> float:
    """Fraction used for interpolation: held in [0, 1] (clamp) or not (linear extrapolation)."""
    if clamp:
        if t < 0.0:
            return 0.0
        if t > 1.0:
            return 1.0
    return t


@_jit_inline
def _interp1(x: float, ax: F64, inv: float, y: F64, clamp: bool) -> float:
    i, t = _frac(x, ax, inv)
    t = _lim(t, clamp)
    return float(y[i] + t * (y[i + 1] - y[i]))


@_jit_inline
def _col2(y: F64, i: int, t: float, j: int) -> tuple[float, float]:
    """Bilinear table: values at z nodes j and j+1, interpolated along x (bracket i, fraction t)."""
    a0, a1 = y[i, j], y[i, j + 1]
    return a0 + t * (y[i + 1, j] - a0), a1 + t * (y[i + 1, j + 1] - a1)


@_jit_inline
def _planes3(
    flat: F64, m: int, base: int, di: int, dj: int, dk: int, u: float, v: float
) -> tuple[float, float]:  # fmt: skip
    """Table m at (I, SoC) on the two temperature nodes bracketing T.

    The flat layout [T][I][SoC][table] puts all tables of one corner side by side.
    """
    b = base + m
    c00 = flat[b] + v * (flat[b + dk] - flat[b])
    c01 = flat[b + dj] + v * (flat[b + dj + dk] - flat[b + dj])
    c10 = flat[b + di] + v * (flat[b + di + dk] - flat[b + di])
    c11 = flat[b + di + dj] + v * (flat[b + di + dj + dk] - flat[b + di + dj])
    return c00 + u * (c01 - c00), c10 + u * (c11 - c10)


@_jit_inline
def _ocv_at(
    soc: float, temp: float, jd: int, w: float, ocv_x: F64, ocv_y: F64, du_x: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> float:  # fmt: skip
    """OCV including the entropic term, given the bracket (jd, unclamped w) of ``temp`` on the
    dU/dT temperature axis, so that a caller that already has it does not look it up again."""
    clamp = imeta[2] == 1
    u_ref = _interp1(soc, ocv_x, fmeta[3], ocv_y, clamp)
    t_ref = fmeta[6]
    if math.isnan(t_ref):
        return u_ref
    x = u_ref if imeta[1] == 1 else soc
    i, t = _frac(x, du_x, fmeta[4])
    c0, c1 = _col2(du_y, i, _lim(t, clamp), jd)
    return float(u_ref + (temp - t_ref) * (c0 + _lim(w, clamp) * (c1 - c0)))


@_jit_inline
def _ocv_scalar(
    soc: float, temp: float, ocv_x: F64, ocv_y: F64, du_x: F64, du_t: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> float:  # fmt: skip
    """OCV including the entropic term (none when the reference temperature is NaN)."""
    jd, w = _frac(temp, du_t, fmeta[5])
    return _ocv_at(soc, temp, jd, w, ocv_x, ocv_y, du_x, du_y, fmeta, imeta)


@_jit_inline
def _terminal_at(
    soc: float, eta_sum: float, temp: float, r_scale: float, i: int, t: float, j: int, u: float,
    jd: int, w: float, flat: F64, ax_s: F64, ocv_x: F64, ocv_y: F64, du_x: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64],
) -> tuple[float, float]:  # fmt: skip
    """(OCV - sum eta, R0 r_scale) given the brackets of ``temp`` (i, t on the RC axis; jd, w
    on the dU/dT axis) and of the current (j, u); fractions may be unclamped. A step shares
    these with its own lookups (:func:`_step_scalar`)."""
    clamp = imeta[2] == 1
    dk = imeta[6]
    dj = imeta[5] * dk
    di = imeta[4] * dj
    k, v = _frac(soc, ax_s, fmeta[2])
    base = i * di + j * dj + k * dk
    p0, p1 = _planes3(flat, 0, base, di, dj, dk, _lim(u, clamp), _lim(v, clamp))
    r0 = p0 + _lim(t, clamp) * (p1 - p0)
    ocv = _ocv_at(soc, temp, jd, w, ocv_x, ocv_y, du_x, du_y, fmeta, imeta)
    return ocv - eta_sum, r0 * r_scale


@_jit_inline
def _terminal_scalar(
    soc: float, eta_sum: float, temp: float, cur: float, r_scale: float,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
) -> tuple[float, float]:  # fmt: skip
    """(source voltage OCV - sum eta, series resistance R0 at this current)."""
    i, t = _frac(temp, ax_t, fmeta[0])
    j, u = _frac(cur, ax_i, fmeta[1])
    jd, w = _frac(temp, du_t, fmeta[5])
    return _terminal_at(
        soc, eta_sum, temp, r_scale, i, t, j, u, jd, w,
        flat, ax_s, ocv_x, ocv_y, du_x, du_y, fmeta, imeta,
    )  # fmt: skip


@_jit_inline
def _one_minus_exp_neg(x: float) -> float:
    """1 - exp(-x), inline for |x| < 0.25 (RC steps shorter than tau/4: the usual case).

    A libm call inside the cell loop makes the compiler spill every live register around it;
    the nested Taylor form x(1 - x/2(1 - x/3(... (1 - x/13)))) has a relative error < 1e-17.
    """
    if abs(x) < 0.25:
        p = 1.0 - x * (1.0 / 13.0)
        p = 1.0 - x * (1.0 / 12.0) * p
        p = 1.0 - x * (1.0 / 11.0) * p
        p = 1.0 - x * (1.0 / 10.0) * p
        p = 1.0 - x * (1.0 / 9.0) * p
        p = 1.0 - x * (1.0 / 8.0) * p
        p = 1.0 - x * (1.0 / 7.0) * p
        p = 1.0 - x * (1.0 / 6.0) * p
        p = 1.0 - x * (1.0 / 5.0) * p
        p = 1.0 - x * (1.0 / 4.0) * p
        p = 1.0 - x * (1.0 / 3.0) * p
        p = 1.0 - x * 0.5 * p
        return x * p
    return -math.expm1(-x)


@_jit_inline
def _rc_branch(
    eta: float, cur: float, r: float, c: float, r_scale: float, h: float, inv_h: float
) -> tuple[float, float]:
    """Exact RC step: (drop at step end, drop averaged over the step); tau = R C."""
    tau = r * c
    target = cur * r * r_scale
    frac = _one_minus_exp_neg(h / tau)
    d = eta - target
    return target + d * (1.0 - frac), target + d * frac * tau * inv_h


@_jit_inline
def _step_scalar(
    soc: float, eta1: float, eta2: float, tc: float, tj: float,
    cur: float, h: float, ta: float, cap_ah: float, r_scale: float, th: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64], with_v: bool,
) -> tuple[float, float, float, float, float, float, float, float]:  # fmt: skip
    """One cell over one step of constant current:
    (soc, eta1, eta2, T_cell, T_jig, heat_w, e_v, r0_ohm).

    Tables are read at mid-step: SoC exactly (it is linear in time), the cell temperature from
    a predictor (exact half-step of the thermal network under the heat at step start).
    ``with_v`` (a constant at each call site, so the other branch compiles away) also returns
    :func:`_terminal_scalar` at the step-start state, reusing the temperature and current
    brackets of the predictor; otherwise e_v = r0_ohm = 0.
    """
    clamp = imeta[2] == 1
    nt = imeta[6]
    dk = nt
    dj = imeta[5] * dk
    di = imeta[4] * dj
    soc1 = soc - cur * h / (3600.0 * cap_ah)
    sm = 0.5 * (soc + soc1)
    inv_h = 1.0 / h
    i, tu = _frac(tc, ax_t, fmeta[0])
    j, u = _frac(cur, ax_i, fmeta[1])
    k, v = _frac(sm, ax_s, fmeta[2])
    u = _lim(u, clamp)
    v = _lim(v, clamp)
    t = _lim(tu, clamp)
    base = i * di + j * dj + k * dk
    u_ref = _interp1(sm, ocv_x, fmeta[3], ocv_y, clamp)
    xd = u_ref if imeta[1] == 1 else sm
    # predictor: heat at step start -> cell temperature at mid-step
    p0, p1 = _planes3(flat, 0, base, di, dj, dk, u, v)
    xi, xt = _frac(xd, du_x, fmeta[4])
    xt = _lim(xt, clamp)
    jd, w = _frac(tc, du_t, fmeta[5])
    d0, d1 = _col2(du_y, xi, xt, jd)
    r0 = (p0 + t * (p1 - p0)) * r_scale
    ev, r0v = 0.0, 0.0
    if with_v:
        ev, r0v = _terminal_at(
            soc, eta1 + eta2, tc, r_scale, i, tu, j, u, jd, w,
            flat, ax_s, ocv_x, ocv_y, du_x, du_y, fmeta, imeta,
        )  # fmt: skip
    q0 = cur * (cur * r0 + eta1 + eta2 - (tc + 273.15) * (d0 + _lim(w, clamp) * (d1 - d0)))
    yc = tc - ta
    yj = tj - ta
    tmid = ta + th[6] * yc + th[7] * yj + th[10] * q0
    # corrector: every table at (T_mid, I, SoC_mid); the brackets rarely change
    im, tm = _frac(tmid, ax_t, fmeta[0])
    tm = _lim(tm, clamp)
    if im != i:
        base += (im - i) * di
        p0, p1 = _planes3(flat, 0, base, di, dj, dk, u, v)
    heat = cur * cur * (p0 + tm * (p1 - p0)) * r_scale
    p0, p1 = _planes3(flat, 1, base, di, dj, dk, u, v)
    r = p0 + tm * (p1 - p0)
    p0, p1 = _planes3(flat, 2, base, di, dj, dk, u, v)
    eta1_new, mean = _rc_branch(eta1, cur, r, p0 + tm * (p1 - p0), r_scale, h, inv_h)
    heat += cur * mean
    eta2_new = 0.0
    if imeta[0] == 2:
        p0, p1 = _planes3(flat, 3, base, di, dj, dk, u, v)
        r = p0 + tm * (p1 - p0)
        p0, p1 = _planes3(flat, 4, base, di, dj, dk, u, v)
        eta2_new, mean = _rc_branch(eta2, cur, r, p0 + tm * (p1 - p0), r_scale, h, inv_h)
        heat += cur * mean
    jm, w = _frac(tmid, du_t, fmeta[5])
    if jm != jd:
        d0, d1 = _col2(du_y, xi, xt, jm)
    heat -= cur * (tmid + 273.15) * (d0 + _lim(w, clamp) * (d1 - d0))
    tc_new = ta + th[0] * yc + th[1] * yj + th[4] * heat
    tj_new = ta + th[2] * yc + th[3] * yj + th[5] * heat
    return soc1, eta1_new, eta2_new, tc_new, tj_new, heat, ev, r0v


@_jit
def _advance_kernel(
    soc: F64, eta: F64, tc: F64, tj: F64, cur: F64, ta: F64, cap: F64, rs: F64,
    h: float, th: F64, flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    soc_o: F64, eta_o: F64, tc_o: F64, tj_o: F64, heat_o: F64,
) -> None:  # fmt: skip
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        e2 = eta[c, 1] if two else 0.0
        s1, a1, a2, t1, j1, q, _e, _r = _step_scalar(
            soc[c], eta[c, 0], e2, tc[c], tj[c], cur[c], h, ta[c], cap[c], rs[c], th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, False,
        )  # fmt: skip
        soc_o[c] = s1
        eta_o[c, 0] = a1
        if two:
            eta_o[c, 1] = a2
        tc_o[c] = t1
        tj_o[c] = j1
        heat_o[c] = q


@_jit
def _step_kernel(
    soc: F64, eta: F64, tc: F64, tj: F64, cur: F64, ta: F64, cap: F64, rs: F64,
    h: float, th: F64, flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    v_o: F64, soc_o: F64, eta_o: F64, tc_o: F64, tj_o: F64, heat_o: F64,
) -> None:  # fmt: skip
    """``_thevenin_kernel`` then ``_advance_kernel`` in one pass, sharing the axis lookups."""
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        i = cur[c]
        e2 = eta[c, 1] if two else 0.0
        s1, a1, a2, t1, j1, q, e, r0 = _step_scalar(
            soc[c], eta[c, 0], e2, tc[c], tj[c], i, h, ta[c], cap[c], rs[c], th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, True,
        )  # fmt: skip
        v_o[c] = e - r0 * i
        soc_o[c] = s1
        eta_o[c, 0] = a1
        if two:
            eta_o[c, 1] = a2
        tc_o[c] = t1
        tj_o[c] = j1
        heat_o[c] = q


@_jit
def _ocv_kernel(
    soc: F64, temp: F64, ocv_x: F64, ocv_y: F64, du_x: F64, du_t: F64, du_y: F64,
    fmeta: F64, imeta: NDArray[np.int64], out: F64,
) -> None:  # fmt: skip
    for c in range(soc.shape[0]):
        out[c] = _ocv_scalar(soc[c], temp[c], ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta)


@_jit
def _thevenin_kernel(
    soc: F64, eta: F64, tc: F64, cur: F64, rs: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    e_o: F64, r_o: F64,
) -> None:  # fmt: skip
    two = imeta[0] == 2
    for c in range(soc.shape[0]):
        s = eta[c, 0] + eta[c, 1] if two else eta[c, 0]
        e, r = _terminal_scalar(
            soc[c], s, tc[c], cur[c], rs[c],
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        )  # fmt: skip
        e_o[c] = e
        r_o[c] = r


@_jit
def _simulate_kernel(
    cur: F64, amb: F64, h: float, soc0: float, cap_ah: float, r_scale: float, th: F64,
    flat: F64, ax_t: F64, ax_i: F64, ax_s: F64, ocv_x: F64, ocv_y: F64,
    du_x: F64, du_t: F64, du_y: F64, fmeta: F64, imeta: NDArray[np.int64],
    v_o: F64, soc_o: F64, tc_o: F64, tj_o: F64,
) -> None:  # fmt: skip
    n = cur.shape[0]
    soc, e1, e2, tc, tj = soc0, 0.0, 0.0, amb[0], amb[0]
    ev, r0 = _terminal_scalar(
        soc, 0.0, tc, cur[0], r_scale,
        flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
    )  # fmt: skip
    v_o[0] = ev - r0 * cur[0]
    soc_o[0], tc_o[0], tj_o[0] = soc, tc, tj
    for k in range(n):
        soc, e1, e2, tc, tj, _q, _e, _r = _step_scalar(
            soc, e1, e2, tc, tj, cur[k], h, amb[k], cap_ah, r_scale, th,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta, False,
        )  # fmt: skip
        ev, r0 = _terminal_scalar(
            soc, e1 + e2, tc, cur[k], r_scale,
            flat, ax_t, ax_i, ax_s, ocv_x, ocv_y, du_x, du_t, du_y, fmeta, imeta,
        )  # fmt: skip
        v_o[k + 1] = ev - r0 * cur[k]
        soc_o[k + 1], tc_o[k + 1], tj_o[k + 1] = soc, tc, tj


# --------------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------------


def ocv_v(params: CellParams, soc: ArrayLike, temp_c: ArrayLike) -> F64:
    """Open-circuit voltage at (SoC, cell temperature), including the entropic term if enabled.

    Broadcasts ``soc`` against ``temp_c``; the result has their broadcast shape.
    """
    s, t = np.broadcast_arrays(np.asarray(soc, np.float64), np.asarray(temp_c, np.float64))
    out = np.empty(s.shape)
    k = params._packed
    _ocv_kernel(
        np.ascontiguousarray(s).ravel(), np.ascontiguousarray(t).ravel(),
        k.ocv_x, k.ocv_y, k.du_x, k.du_t, k.du_y, k.fmeta, k.imeta, out.reshape(-1),
    )  # fmt: skip
    return out


def _thermal_coeffs(params: CellParams, h: float) -> F64:
    """Exact thermal step coefficients for dt = h (6) and for the mid-step predictor h/2 (6)."""
    cached = params._thermal_cache.get(h)
    if cached is None:
        th = params.thermal
        cached = np.array(step_coefficients(th, h) + step_coefficients(th, 0.5 * h))
        cached.setflags(write=False)
        if len(params._thermal_cache) < 64:
            params._thermal_cache[h] = cached
    return cached


_Tables = tuple[F64, F64, F64, F64, F64, F64, F64, F64, F64, F64, NDArray[np.int64]]


def _tables(params: CellParams) -> _Tables:
    k = params._packed
    return (k.rc_flat, k.ax_t, k.ax_i, k.ax_s, k.ocv_x, k.ocv_y, k.du_x, k.du_t, k.du_y,
            k.fmeta, k.imeta)  # fmt: skip


def thevenin(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, F64]:
    """Per cell (e_v, r0_ohm) so that the terminal voltage is ``e_v - r0_ohm * I``.

    ``e_v = OCV(soc, T) - sum(eta)``; R0 is read at ``current_a`` and scaled by ``r_scale``.
    ``capacity_ah`` does not enter (the source has no capacity term); it is accepted so that
    :func:`thevenin` and :func:`advance` take the same per-cell arguments.
    """
    n, soc, eta, tc, _ = _state_arrays(params, state)
    e = np.empty(n)
    r = np.empty(n)
    _thevenin_kernel(
        soc, eta, tc, _cells(current_a, n), _cells(r_scale, n),
        *_tables(params), e, r,
    )  # fmt: skip
    return e, r


def advance(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[CellState, F64]:
    """Advance n cells over ``dt_s`` at constant current; returns (new state, mean heat W).

    ``r_scale`` multiplies every resistance and divides every capacitance (time constants
    unchanged); ``capacity_ah`` is the per-cell capacity used for coulomb counting. Thermal
    masses and conductances are the parameter set's for every cell.
    """
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    n, soc, eta, tc, tj = _state_arrays(params, state)
    th = _thermal_coeffs(params, h)
    new = CellState(np.empty(n), np.empty((n, params.n_rc)), np.empty(n), np.empty(n))
    heat = np.empty(n)
    _advance_kernel(
        soc, eta, tc, tj,
        _cells(current_a, n), _cells(ambient_c, n), _cells(capacity_ah, n), _cells(r_scale, n),
        h, th, *_tables(params), new.soc, new.eta_v, new.temp_c, new.jig_temp_c, heat,
    )  # fmt: skip
    return new, heat


def step(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, CellState, F64]:
    """One closed-loop step of n cells: (terminal voltage V, new state, mean heat W).

    The voltage is ``e_v - r0_ohm * I`` of :func:`thevenin` at the *start* state; the new state
    and heat are those of :func:`advance`. Same arguments as :func:`advance`; one fused kernel
    (one pass over the cells, shared axis lookups), so it is faster than the two calls.
    """
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    n, soc, eta, tc, tj = _state_arrays(params, state)
    th = _thermal_coeffs(params, h)
    new = CellState(np.empty(n), np.empty((n, params.n_rc)), np.empty(n), np.empty(n))
    v = np.empty(n)
    heat = np.empty(n)
    _step_kernel(
        soc, eta, tc, tj,
        _cells(current_a, n), _cells(ambient_c, n), _cells(capacity_ah, n), _cells(r_scale, n),
        h, th, *_tables(params), v, new.soc, new.eta_v, new.temp_c, new.jig_temp_c, heat,
    )  # fmt: skip
    return v, new, heat


def simulate_current(
    params: CellParams,
    current_a: ArrayLike,
    dt_s: float,
    soc0: float,
    ambient_c: ArrayLike,
    *,
    capacity_ah: float | None = None,
    r_scale: float = 1.0,
) -> CellTrace:
    """Simulate one cell from rest at ambient under a piecewise-constant current.

    ``current_a[k]`` (+ = discharge) flows over ``[k dt, (k+1) dt)``; ``ambient_c`` is a scalar
    or one value per step. Samples follow the :class:`CellTrace` convention (len n+1).
    """
    cur = np.ascontiguousarray(np.asarray(current_a, dtype=np.float64).ravel())
    n = cur.size
    if n == 0:
        raise ValueError("current_a must have at least one step")
    h = float(dt_s)
    if not h > 0.0:
        raise ValueError(f"dt_s must be > 0, got {dt_s!r}")
    amb = _cells(ambient_c, n)
    cap = params.capacity_ah if capacity_ah is None else float(capacity_ah)
    th = _thermal_coeffs(params, h)
    v, soc, tc, tj = (np.empty(n + 1) for _ in range(4))
    _simulate_kernel(
        cur, amb, h, float(soc0), cap, float(r_scale), th, *_tables(params), v, soc, tc, tj
    )
    return CellTrace(
        t_s=np.arange(n + 1, dtype=np.float64) * h,
        current_a=np.concatenate([cur[:1], cur]),
        voltage_v=v,
        soc=soc,
        temp_c=tc,
        jig_temp_c=tj,
    )


# --------------------------------------------------------------------------------------------
# NumPy reference (independent of the kernels: binary search, vectorized over cells)
# --------------------------------------------------------------------------------------------


def _np_locate(x: F64, ax: F64) -> tuple[NDArray[np.intp], F64]:
    """Bracket and unclamped fraction, by binary search (the kernels use O(1) on uniform axes)."""
    i = np.clip(np.searchsorted(ax, x, side="right") - 1, 0, ax.size - 2)
    return i, (x - ax[i]) / (ax[i + 1] - ax[i])


def _np_lim(t: F64, clamp: bool) -> F64:
    return np.clip(t, 0.0, 1.0) if clamp else t


def _np_interp2(x: F64, z: F64, ax: F64, az: F64, y: F64, clamp: bool) -> F64:
    """Bilinear y(x, z)."""
    i, t = _np_locate(x, ax)
    j, u = _np_locate(z, az)
    t, u = _np_lim(t, clamp), _np_lim(u, clamp)
    a = y[i, j] * (1 - u) + y[i, j + 1] * u
    b = y[i + 1, j] * (1 - u) + y[i + 1, j + 1] * u
    return a * (1 - t) + b * t


def _np_interp3(params: CellParams, key: str, temp: F64, cur: F64, soc: F64) -> F64:
    """Trilinear table at (temp, cur, soc)."""
    clamp = params.extrapolation == "clamp"
    tab = getattr(params, key)
    i, t = _np_locate(temp, params.rc_temp_c)
    t = _np_lim(t, clamp)
    j, u = _np_locate(cur, params.rc_current_a)
    k, v = _np_locate(soc, params.rc_soc)
    u, v = _np_lim(u, clamp), _np_lim(v, clamp)
    out = np.zeros_like(t)
    for di, wi in ((0, 1 - t), (1, t)):
        for dj, wj in ((0, 1 - u), (1, u)):
            for dk, wk in ((0, 1 - v), (1, v)):
                out += wi * wj * wk * tab[i + di, j + dj, k + dk]
    return out


def _ocv_numpy(params: CellParams, soc: F64, temp: F64) -> tuple[F64, F64]:
    """(OCV at the reference temperature, OCV including the entropic term)."""
    clamp = params.extrapolation == "clamp"
    i, t = _np_locate(soc, params.ocv_soc)
    t = _np_lim(t, clamp)
    y = params.ocv_table_v
    u_ref = y[i] * (1 - t) + y[i + 1] * t
    if params.ocv_ref_temp_c is None:
        return u_ref, u_ref
    x = u_ref if params.dudt_axis == "ocv_v" else soc
    dudt = _np_interp2(x, temp, params.dudt_x, params.dudt_temp_c, params.dudt_v_per_k, clamp)
    return u_ref, u_ref + (temp - params.ocv_ref_temp_c) * dudt


def thevenin_numpy(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[F64, F64]:
    """NumPy reference of :func:`thevenin`."""
    n = state.soc.shape[0]
    cur, rs = _cells(current_a, n), _cells(r_scale, n)
    r0 = _np_interp3(params, "r0_ohm", state.temp_c, cur, state.soc) * rs
    e = _ocv_numpy(params, state.soc, state.temp_c)[1] - state.eta_v.sum(axis=1)
    return e, r0


def advance_numpy(
    params: CellParams,
    state: CellState,
    current_a: ArrayLike,
    dt_s: float,
    ambient_c: ArrayLike,
    capacity_ah: ArrayLike,
    r_scale: ArrayLike,
) -> tuple[CellState, F64]:
    """NumPy reference of :func:`advance` (same equations, written directly)."""
    n = state.soc.shape[0]
    h = float(dt_s)
    cur, ta = _cells(current_a, n), _cells(ambient_c, n)
    cap, rs = _cells(capacity_ah, n), _cells(r_scale, n)
    clamp = params.extrapolation == "clamp"
    soc1 = state.soc - cur * h / (3600.0 * cap)
    sm = 0.5 * (state.soc + soc1)
    tc = state.temp_c
    yc, yj = tc - ta, state.jig_temp_c - ta
    u_ref = _ocv_numpy(params, sm, tc)[0]
    x = u_ref if params.dudt_axis == "ocv_v" else sm
    du_args = (params.dudt_x, params.dudt_temp_c, params.dudt_v_per_k, clamp)
    # predictor: heat at step start held over half a step gives the mid-step cell temperature
    q0 = cur * (
        cur * _np_interp3(params, "r0_ohm", tc, cur, sm) * rs
        + state.eta_v.sum(axis=1)
        - (tc + KELVIN) * _np_interp2(x, tc, *du_args)
    )
    h11, h12, _, _, hkc, _ = step_coefficients(params.thermal, 0.5 * h)
    tm = ta + h11 * yc + h12 * yj + hkc * q0
    # corrector: tables at (T_mid, I, SoC_mid), exact RC and thermal steps
    heat = cur**2 * _np_interp3(params, "r0_ohm", tm, cur, sm) * rs
    eta1 = np.empty_like(state.eta_v)
    for b, (rk, ck) in enumerate((("r1_ohm", "c1_f"), ("r2_ohm", "c2_f"))[: params.n_rc]):
        r = _np_interp3(params, rk, tm, cur, sm) * rs
        c = _np_interp3(params, ck, tm, cur, sm) / rs
        tau = r * c
        decay = np.exp(-h / tau)
        target = cur * r
        eta1[:, b] = target + (state.eta_v[:, b] - target) * decay
        mean = target + (state.eta_v[:, b] - target) * (1 - decay) * tau / h
        heat = heat + cur * mean
    heat = heat - cur * (tm + KELVIN) * _np_interp2(x, tm, *du_args)
    e11, e12, e21, e22, kc, kj = step_coefficients(params.thermal, h)
    new = CellState(
        soc=soc1,
        eta_v=eta1,
        temp_c=ta + e11 * yc + e12 * yj + kc * heat,
        jig_temp_c=ta + e21 * yc + e22 * yj + kj * heat,
    )
    return new, heat
