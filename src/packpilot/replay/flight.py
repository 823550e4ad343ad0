"""What PackPilot would have done on a recorded flight: every battery of the log through the
discharge protection and, when the user says two batteries were in parallel (``--parallel
A,B``), that pair through parallel discharge sequencing, with the log's own facts (reverse
currents, the lowest cell) and the autopilot's own judgement (its warnings) beside the verdicts.

Batteries in one log are independent unless the user says otherwise: a log can hold a 6S
30 Ah flight pack and a 12S 6 Ah payload pack, and taking those for a parallel pair predicts
hundreds of amperes of cross-current that cannot flow. A pair whose voltages differ by more than
:data:`PARALLEL_MAX_SPREAD` is refused with both voltages.

A replay is open loop: the log's measurements are what they were (flown without PackPilot);
the answer is what the controller would have commanded from them — when the protection would
have opened a battery's discharge path, which battery sequencing would have held back and when
it would have let it join — not how the flight would then have gone. A battery the log cannot
replay (no current, no temperature and no ``--assume-temp-c``) is listed with the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from packpilot.control.protection import ProtectionConfig
from packpilot.control.sequencing import SequencingConfig
from packpilot.errors import InputError
from packpilot.replay import protection, sequencing
from packpilot.replay.common import AUX, LogOptions, LogTable, ReplayResult, open_log
from packpilot.replay.pilot import pilot_summary

PARALLEL_MAX_SPREAD = 0.10
"""Largest relative difference of two batteries' median voltages over the first samples for a
``--parallel`` pair: packs of one cell count differ by a few percent at most."""
FIRST_SAMPLES = 10

REVERSE_A = 0.5
"""A battery current below -this while the pack discharges is a charge flowing into it from
another battery (cross-charge), as sequencing's i_rev default reads it."""


@dataclass(frozen=True)
class FlightReplay:
    log: LogTable
    batteries: list[str]
    protection: dict[str, ReplayResult]
    skipped: dict[str, str]
    """Battery -> why its protection was not replayed."""
    sequencing: ReplayResult | None
    summary: dict[str, object]


def _log_facts(log: LogTable, name: str) -> dict[str, object]:
    """What the log itself shows of a battery: peak currents, the lowest cell."""
    facts: dict[str, object] = {}
    cur = log.columns.get(f"{name}_current_a")
    if cur is not None:
        t = log.columns["t_s"]
        k = int(np.argmin(cur))
        facts["peak_discharge_a"] = float(np.max(cur))
        facts["peak_charge_a"] = max(0.0, -float(cur[k]))
        facts["peak_charge_t_s"] = float(t[k]) if cur[k] < -REVERSE_A else None
    vmin = log.columns.get(f"{name}_min_cell_v")
    if vmin is not None:
        facts["lowest_min_cell_v"] = float(np.min(vmin))
    return facts


def _headline(name: str, res: ReplayResult | None, why: str | None) -> str:
    if res is None:
        return f"{name}: protection not replayed ({why})"
    s = res.summary
    if s["tripped"]:
        return (
            f"{name}: the protection would have opened the discharge path at "
            f"{s['trip_time_s']:.1f} s under {s['param_at_trip']} "
            f"(cut-off {s['cutoff_at_trip_v']} V)"
        )
    peak = 100 * float(s["peak_fraction"])  # type: ignore[arg-type]
    return f"{name}: the protection would not have tripped (at most {peak:.0f} % of its allowance)"


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """(first, last) row of each run of True in ``mask``."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0] - 1, strict=True))


MAX_RUNS = 3
"""Most intervals per battery the headlines name (the table has them all)."""


def _fet_lines(log: LogTable, res: ReplayResult, k: int, name: str) -> list[str]:
    """When sequencing would have kept a battery's charge FET off while the pack discharged,
    and how much charge the log shows flowing into it meanwhile (what that FET would block)."""
    t = log.columns["t_s"]
    cur = log.columns[f"{name}_current_a"]
    j_chg, j_state = res.columns.index(f"chg_{k}"), res.columns.index(f"state_{k}")
    j_mode = res.columns.index("mode")
    off = np.array([r[j_chg] == 0 and r[j_mode] == "discharge" for r in res.rows])
    lines = []
    for a, b in _runs(off)[:MAX_RUNS]:
        into = max(0.0, -float(np.min(cur[a : b + 1])))
        states = sorted({str(res.rows[i][j_state]) for i in range(a, b + 1)})
        until = f"{t[b + 1]:.1f} s" if b + 1 < len(t) else "the end of the log"
        blocked = (
            f"; the log shows up to {into:.1f} A flowing into {name} meanwhile, which it blocks"
            if into > REVERSE_A
            else ""
        )
        lines.append(
            f"{name}: sequencing would have kept its charge FET off from {t[a]:.1f} s to {until}"
            f" ({'/'.join(states)}){blocked}"
        )
    return lines


def _sequencing_lines(log: LogTable, res: ReplayResult, names: list[str]) -> list[str]:
    s = res.summary
    lines: list[str] = []
    for k, name in enumerate(names):
        lines += _fet_lines(log, res, k, name)
    for j in s["joins"]:  # type: ignore[attr-defined]
        lines.append(f"{names[j['index']]} joins at {j['t_s']:.1f} s by {j['rule']}")
    for r in s["reverse_current"]:  # type: ignore[attr-defined]
        lines.append(
            f"{names[r['index']]}: reverse current {r['current_a']:.1f} A at {r['t_s']:.1f} s:"
            " its charge FET opened"
        )
    risks: list[dict[str, float]] = s["cross_current_risk"]  # type: ignore[assignment]
    for k, name in enumerate(names):
        mine = [r for r in risks if r["index"] == k]
        if mine:
            when = ", ".join(
                f"{r['t_s']:.1f} s ({r['predicted_a']:.1f} A)" for r in mine[:MAX_RUNS]
            )
            more = f" and {len(mine) - MAX_RUNS} more" if len(mine) > MAX_RUNS else ""
            lines.append(
                f"{name}: its charge FET would be switched on with cross-current predicted "
                f"(a reported risk) at {when}{more}"
            )
    return lines


def _pair(log: LogTable, names: list[str], parallel: tuple[str, str]) -> LogTable:
    """The log restricted to the two batteries the user says were in parallel; refused with
    the reason when they are not in the log or cannot be a parallel pair."""
    path = log.path
    for n in parallel:
        if n not in names:
            raise InputError(f"{path}: --parallel {n}: no battery {n} in the log ({names})")
    if parallel[0] == parallel[1]:
        raise InputError(f"{path}: --parallel {parallel[0]},{parallel[1]}: name two batteries")
    v = [float(np.median(log.columns[f"{n}_voltage_v"][:FIRST_SAMPLES])) for n in parallel]
    if abs(v[0] - v[1]) > PARALLEL_MAX_SPREAD * max(v):
        raise InputError(
            f"{path}: --parallel {','.join(parallel)} refused: {parallel[0]} is at {v[0]:.2f} V "
            f"and {parallel[1]} at {v[1]:.2f} V at the start, more than "
            f"{100 * PARALLEL_MAX_SPREAD:.0f} % apart (different cell counts or voltages "
            "cannot be a parallel pair)"
        )
    keep = {
        c: x for c, x in log.columns.items()
        if c in ("t_s", "docked") or c.split("_")[0] in parallel
    }  # fmt: skip
    return replace(log, columns=keep)


def replay_flight(
    path: Path, prot_cfg: ProtectionConfig, seq_cfg: SequencingConfig, options: LogOptions,
    parallel: tuple[str, str] | None = None,
) -> FlightReplay:  # fmt: skip
    """Protection per battery, sequencing for a pair the user says was in parallel; one
    summary of both."""
    if options.battery is not None:
        raise InputError(f"{path}: --battery does not apply: a flight replay takes every battery")
    log = open_log(path, options)
    log.require(["t_s"], {"t_s": "every replay needs the time of each row"})
    names = [b for b in log.batteries() if b != AUX]
    if not names or names == [""]:
        names = [""]
    prot: dict[str, ReplayResult] = {}
    skipped: dict[str, str] = {}
    for name in names:
        try:
            prot[name] = protection.replay(
                log, prot_cfg, LogOptions(name or None, options.assume_temp_c, options.cells)
            )
        except InputError as err:
            skipped[name] = str(err).removeprefix(f"{path}: ").split("; header is")[0]
    pair = None if parallel is None else _pair(log, names, parallel)
    seq = None if pair is None else sequencing.replay(pair, seq_cfg)
    headlines = [_headline(n or "battery", prot.get(n), skipped.get(n)) for n in names]
    headlines += [n for n in log.notes if "the autopilot warned" in n]
    if seq is not None and parallel is not None:
        headlines += _sequencing_lines(pair or log, seq, list(parallel))
    elif len(names) > 1:
        headlines.append(
            f"batteries {', '.join(names)} replayed as independent batteries (give "
            "--parallel A,B if two of them were in parallel)"
        )
    t = log.columns["t_s"]
    assumed = sorted({a for r in prot.values() for a in r.summary["assumed"]})  # type: ignore[attr-defined]
    summary: dict[str, object] = {
        "method": "flight",
        "log": str(path),
        "source": log.source,
        "rows": len(log),
        "duration_s": float(t[-1] - t[0]),
        "batteries": names,
        "headlines": headlines,
        "protection": {n: _brief(r.summary) for n, r in prot.items()},
        "not_replayed": skipped,
        "sequencing": None if seq is None else _brief(seq.summary),
        "log_facts": {n: _log_facts(log, n) for n in names if n},
        "assumed": assumed,
        "notes": list(log.notes),
        "pilot": pilot_summary(log, names),
    }
    return FlightReplay(log, names, prot, skipped, seq, summary)


def _brief(summary: dict[str, object]) -> dict[str, object]:
    drop = {"config", "notes", "log", "source", "rows", "method", "assumed"}
    return {k: v for k, v in summary.items() if k not in drop}


__all__ = ["FlightReplay", "replay_flight"]
