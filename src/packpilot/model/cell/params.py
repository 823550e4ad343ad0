"""Cell parameter sets: :class:`CellParams`, its validation, and the JSON parameter files.

A parameter set is validated and frozen when it is built, and its tables are laid out once for
the kernels (:class:`_Packed`). Files use the format ``packpilot-cell/1``; the shipped sets
(``PARAMETER_SETS``) live in ``packpilot/data/cells``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from packpilot.errors import ConfigError
from packpilot.model.thermal import ThermalParams

FORMAT = "packpilot-cell/1"
PARAMETER_SETS = ("ecm_example", "uav_5ah", "lfp_storage", "lipo_pouch")

F64 = NDArray[np.float64]


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
    series_ohm: float = 0.0
    """Resistance in series with each cell outside it (its share of the battery's leads,
    connectors and current shunt): a default for a battery's ``series_ohm`` (x series groups /
    cells per group). It drops the battery's voltage at the load but heats no cell and does not
    follow the cell's temperature law; the cell model itself never sees it (the pack puts it in
    the battery's branch). 0 in every shipped set; ``packpilot fit --series-ohm`` sets it."""
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
    """Check every field and freeze the arrays, scalars first, then the tables."""
    _validate_scalars(p)
    _validate_tables(p)


def _validate_scalars(p: CellParams) -> None:
    if not isinstance(p.name, str) or not p.name:
        raise ConfigError("cell parameter set: field 'name': must be a non-empty string")
    _scalar(p, "capacity_ah", positive=True)
    vmin, vmax = _scalar(p, "v_min_v", positive=True), _scalar(p, "v_max_v", positive=True)
    if vmin >= vmax:
        raise _fail(p.name, "v_min_v", f"must be below v_max_v ({vmin} >= {vmax})")
    if p.ocv_ref_temp_c is not None:
        _scalar(p, "ocv_ref_temp_c")
    if _scalar(p, "series_ohm") < 0.0:
        raise _fail(p.name, "series_ohm", f"must be >= 0, got {p.series_ohm!r}")
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


def _validate_tables(p: CellParams) -> None:
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
_OPTIONAL = ("r2_ohm", "c2_f", "ocv_ref_temp_c", "extrapolation", "series_ohm")
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
        elif key == "series_ohm" and value == 0.0:
            continue  # the shipped sets' files do not carry it
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
    """Load a shipped parameter set: ``ecm_example``, ``uav_5ah``, ``lfp_storage`` or
    ``lipo_pouch``.

    Sets are immutable, so each is parsed once per process and shared.
    """
    if name not in _SET_CACHE:
        _SET_CACHE[name] = load_parameter_file(parameter_set_path(name))
    return _SET_CACHE[name]
