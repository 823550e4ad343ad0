"""A flight log as a load profile (``[load] profile = "flight.ulg"``): the same flight
replayed through the closed loop on another pack — the fitted one, a colder one, one with a
second battery — as "what if".

The demand is what the aircraft drew: the sum over the log's batteries of current (``kind =
"current"``) or of voltage x current (``kind = "power"``, what motors hold when the pack sags
differently). Samples where the log shows charge flowing back (regeneration, a cross-charge)
count as zero demand, said in the error-free path by :data:`NOTE`; a resistance load cannot be
read off a log and is refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from packpilot.errors import InputError
from packpilot.io.flightlog import read_flight_log
from packpilot.model.loads import LoadProfile

SUFFIXES = (".ulg", ".bin", ".log", ".tlog")
NOTE = "negative demand in the log (charge flowing back) is taken as zero demand"


def flight_load(path: Path, kind: str, repeat: bool = False) -> LoadProfile:
    """The log's total demand on its own time base, from t = 0 at its first sample."""
    if kind not in ("current", "power"):
        raise InputError(
            f"[load] profile {path}: a flight log gives kind = 'current' or 'power', not {kind!r}"
        )
    table = read_flight_log(path).table()
    cols = table.columns
    names = sorted({c[: -len("_current_a")] for c in cols if c.endswith("_current_a")})
    if not names:
        raise InputError(f"[load] profile {path}: the log has no battery current to replay")
    demand = np.zeros(table.n_rows)
    for n in names:
        i = cols[f"{n}_current_a"]
        demand += i if kind == "current" else i * cols[f"{n}_voltage_v"]
    t = cols["t_s"] - cols["t_s"][0]
    return LoadProfile(kind=kind, t_s=t, value=np.maximum(demand, 0.0), repeat=repeat)


__all__ = ["NOTE", "SUFFIXES", "flight_load"]
