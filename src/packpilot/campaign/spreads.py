"""Spreads and draws: how each run's parameters vary over a campaign, and their values.

A campaign draws, for every run index ``i``, a capacity scale, a resistance scale, an
initial-SOC offset and an ambient temperature from ``np.random.default_rng([seed, i])`` — so a
run's draw depends only on ``(seed, i)``, never on batching, scheduling or the other runs. The
drawn values reach the plant through its hooks (:meth:`Draw.pack_overrides`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from packpilot.errors import InputError

# Spread name -> Parquet column (= Draw field), and the physical range draws are clipped to.
SPREAD_NAMES: tuple[str, ...] = ("capacity", "r0", "soc0", "ambient_c")
_COLUMN = {
    "capacity": "capacity_scale",
    "r0": "r0_scale",
    "soc0": "soc0_offset",
    "ambient_c": "ambient_c",
}
_LIMITS: dict[str, tuple[float, float]] = {
    "capacity": (0.05, math.inf),
    "r0": (0.05, math.inf),
    "soc0": (-1.0, 1.0),
    "ambient_c": (-60.0, 80.0),
}
PARAM_COLUMNS: tuple[str, ...] = tuple(_COLUMN[n] for n in SPREAD_NAMES)


# --------------------------------------------------------------------------------- spreads
@dataclass(frozen=True)
class Spread:
    """How one parameter varies over the campaign.

    ``kind="normal"``: nominal + ``a`` * N(0, 1) (``a`` = sigma in the parameter's unit);
    ``kind="uniform"``: uniform on ``[a, b]``, or on ``[nominal + a, nominal + b]`` when
    ``relative`` (the ``+-X`` form, so ``ambient_c=+-10`` follows the scenario's ambient).
    Draws are clipped to the parameter's physical range (scales >= 0.05, ambient -60..80 degC).
    """

    name: str
    kind: Literal["normal", "uniform"]
    a: float
    b: float = 0.0
    relative: bool = False

    def sample(self, nominal: float, z: float, u: float) -> float:
        """Map one standard-normal ``z`` and one uniform ``u`` to a value (both always drawn)."""
        if self.kind == "normal":
            x = nominal + self.a * z
        else:
            x = (nominal if self.relative else 0.0) + self.a + (self.b - self.a) * u
        lo, hi = _LIMITS[self.name]
        return float(min(max(x, lo), hi))

    def canonical(self) -> str:
        """Exact text identity of the spread (stored in the file so resume can check it)."""
        rel = ":rel" if self.relative else ""
        return f"{self.name}:{self.kind}:{self.a!r}:{self.b!r}{rel}"


_NUM = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
_NUM_RE = re.compile(rf"^({_NUM})(%?)$")


def _number(text: str, token: str) -> float:
    m = _NUM_RE.match(text.strip())
    if m is None:
        raise InputError(f"spread {token!r}: {text.strip()!r} is not a number")
    value = float(m.group(1)) / (100.0 if m.group(2) else 1.0)
    if not math.isfinite(value):
        raise InputError(f"spread {token!r}: value must be finite")
    return value


def _spread_value(name: str, value: str, token: str) -> Spread:
    """The spread of one ``name=value`` token (``value`` non-empty)."""
    if name == "ambient_c" and "%" in value:
        raise InputError(
            f"spread {token!r}: ambient_c takes degC (sigma, +-X or lo:hi), not a percentage"
        )
    if ":" in value:
        lo_t, hi_t = value.split(":", 1)
        lo, hi = _number(lo_t, token), _number(hi_t, token)
        if lo > hi:
            raise InputError(f"spread {token!r}: range lo must be <= hi")
        floor, ceil = _LIMITS[name]
        if lo < floor or hi > ceil:
            raise InputError(f"spread {token!r}: range must lie within [{floor:g}, {ceil:g}]")
        return Spread(name, "uniform", lo, hi)
    if value.startswith(("+-", "±")):
        half = _number(value.removeprefix("+-").removeprefix("±"), token)
        if half < 0:
            raise InputError(f"spread {token!r}: +- half-width must be >= 0")
        return Spread(name, "uniform", -half, half, relative=True)
    sigma = _number(value, token)
    if sigma < 0:
        raise InputError(f"spread {token!r}: sigma must be >= 0")
    return Spread(name, "normal", sigma)


def parse_spreads(text: str | None) -> dict[str, Spread]:
    """Parse ``capacity=5%,r0=10%,soc0=0.05,ambient_c=-10:35`` into spreads by name.

    Forms of the value: ``X%`` or ``X`` — normal with sigma X/100 or X around nominal (for the
    scales ``capacity``/``r0`` the nominal is 1, so ``5%`` = ``0.05``; for ``soc0`` a percentage
    is SOC points; ``ambient_c`` takes degC, not ``%``); ``+-X`` — uniform nominal +- X;
    ``lo:hi`` — uniform on [lo, hi] in absolute terms (scale, SOC offset, degC).
    Raises :class:`InputError` naming the offending token.
    """
    out: dict[str, Spread] = {}
    if text is None or not text.strip():
        return out
    for raw in text.split(","):
        token = raw.strip()
        if not token:
            continue
        if "=" not in token:
            raise InputError(f"spread {token!r}: expected name=value (e.g. capacity=5%)")
        name, value = (s.strip() for s in token.split("=", 1))
        if name not in SPREAD_NAMES:
            raise InputError(
                f"spread {token!r}: unknown parameter {name!r}; allowed: {', '.join(SPREAD_NAMES)}"
            )
        if name in out:
            raise InputError(f"spread {token!r}: {name} is given twice")
        if not value:
            raise InputError(f"spread {token!r}: missing value")
        out[name] = _spread_value(name, value, token)
    return out


def _spreads_canonical(spreads: Mapping[str, Spread]) -> str:
    return ",".join(spreads[n].canonical() for n in SPREAD_NAMES if n in spreads)


# --------------------------------------------------------------------------------- draws
@dataclass(frozen=True)
class Draw:
    """The drawn parameters of one run (what its Parquet row records before the metrics)."""

    run: int
    seed: int
    capacity_scale: float = 1.0
    r0_scale: float = 1.0
    soc0_offset: float = 0.0
    ambient_c: float = 25.0

    def pack_overrides(self) -> dict[str, Any]:
        """The plant's campaign hooks for one pack (``SimulatedPlant(cfg, 1, ...)``): the
        ``Pack`` factors, and ``sensor_stream``, the key of the run's own sensor noise
        (``[sensors]``), ``(seed, run)``, so the noise too depends only on the run."""
        return {
            "capacity_scale": np.array([self.capacity_scale]),
            "r_scale": np.array([self.r0_scale]),
            "soc_offset": np.array([self.soc0_offset]),
            "ambient_c": np.array([self.ambient_c]),
            "sensor_stream": np.array([[self.seed, self.run]], np.int64),
        }


def draw_run(spreads: Mapping[str, Spread], seed: int, run: int, nominal_ambient_c: float) -> Draw:
    """Run ``run``'s parameters: always 4 normals then 4 uniforms from ``default_rng([seed,
    run])``, one pair per parameter in fixed order, so adding a spread never shifts another's
    draws."""
    rng = np.random.default_rng([seed, run])
    z = rng.standard_normal(len(SPREAD_NAMES))
    u = rng.random(len(SPREAD_NAMES))
    values: dict[str, float] = {}
    for k, name in enumerate(SPREAD_NAMES):
        nominal = nominal_ambient_c if name == "ambient_c" else (0.0 if name == "soc0" else 1.0)
        sp = spreads.get(name)
        values[_COLUMN[name]] = nominal if sp is None else sp.sample(nominal, z[k], u[k])
    return Draw(run=run, seed=seed, **values)


def make_draws(
    spreads: Mapping[str, Spread], seed: int, runs: Iterable[int], nominal_ambient_c: float
) -> list[Draw]:
    return [draw_run(spreads, seed, i, nominal_ambient_c) for i in runs]
