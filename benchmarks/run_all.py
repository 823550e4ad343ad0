"""``make bench``: run every benchmark module, print its table, and write RESULTS.md.

Each ``benchmarks/bench_*.py`` exposes ``run() -> list[dict]`` (or a dict of figures). Ratios are
always against a reference measured in the same run, so the numbers travel across machines.
"""

from __future__ import annotations

import datetime as _dt
import importlib.util
import os
import platform
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ORDER = [
    "bench_cell",
    "bench_loop",
    "bench_core",
    "bench_user_run",
    "bench_compile",
    "bench_protection",
    "bench_sequencing",
    "bench_charging",
    "bench_bmu",
    "bench_faults",
    "bench_equalization",
    "bench_campaign",
]


def _cpu_model() -> str:
    """platform.processor() is empty on Linux; /proc/cpuinfo names the CPU."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return str(v)


def _table(rows: list[dict[str, Any]]) -> str:
    cols: list[str] = []
    for r in rows:
        for k in r:
            if k not in cols:
                cols.append(k)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(_fmt(r.get(c, "")) for c in cols) + " |")
    return "\n".join(lines)


def _pick(rows: list[dict[str, Any]], **match: Any) -> dict[str, Any]:
    for r in rows:
        if all(r.get(k) == v for k, v in match.items()):
            return r
    raise KeyError(str(match))


Headline = tuple[str, str, str]
"""(figure, value, target): one row of the closing table."""


def _cell_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """The cell model against PyBaMM, and the fleet throughput."""
    r = rows[0]
    return [
        (
            "cell vs PyBaMM, 25 degC: max / RMS dV (mV)",
            f"{r['max_dV_mV_25C']:.4f} / {r['rms_dV_mV_25C']:.5f}",
            "<= 0.5 / 0.05",
        ),
        (
            "cell vs PyBaMM, 0 degC: max / RMS dV (mV)",
            f"{r['max_dV_mV_0C']:.4f} / {r['rms_dV_mV_0C']:.5f}",
            "<= 0.5 / 0.1",
        ),
        (
            "cell vs PyBaMM: max dT (K) / max dSOC",
            f"{max(r['max_dT_K_25C'], r['max_dT_K_0C']):.2g} / "
            f"{max(r['max_dSOC_25C'], r['max_dSOC_0C']):.2g}",
            "<= 0.01 / 1e-6",
        ),
        ("1 h profile vs PyBaMM build+solve", f"{r['profile_speedup_x']:.0f}x faster", ""),
        (
            "fleet 10k cells, advance (M cell-steps/s)",
            f"{r['fleet10k_advance_Mcell_steps_per_s']:.1f}",
            ">= 20",
        ),
        (
            "fleet 10k cells, thevenin+advance (M cell-steps/s)",
            f"{r['fleet10k_thevenin_advance_Mcell_steps_per_s']:.1f}",
            ">= 20",
        ),
        (
            "fleet 10k cells, fused step (M cell-steps/s; per CPU-s)",
            f"{r['fleet10k_step_fused_Mcell_steps_per_s']:.1f}; "
            f"{r['fleet10k_step_fused_Mcell_steps_per_cpu_s']:.1f}",
            ">= 20",
        ),
    ]


def _loop_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """The closed-loop step against a PyBaMM step."""
    out: list[Headline] = []
    for r in rows[1:]:
        out.append(
            (
                f"{r['case']}: step",
                f"{r['step_us']:.0f} us = {r['ratio_vs_pybamm']:.1f}x PyBaMM step",
                ">= 200x",
            )
        )
    return out


def _protection_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """Energy and rest OCV of the protection method against the fixed cut-off."""
    out: list[Headline] = []
    for sc in ("cold_heavy", "warm_light", "warming_flight"):
        m = _pick(rows, scenario=sc, strategy="method")
        out.append(
            (
                f"protection {sc}: energy vs fixed 3.2 V/5 s",
                f"{m['energy_vs_conservative_pct']:+.1f} %",
                "",  # the +15 % goal is withdrawn (#15 §4: only +11.3 % exists above empty)
            )
        )
        for strat in ("fixed_conservative", "fixed_aggressive", "method", "calibrated"):
            r = _pick(rows, scenario=sc, strategy=strat)
            if r.get("captured_above_floor_pct") is None:
                continue
            out.append(
                (
                    f"protection {sc}: {strat} energy captured above 2 % SOC / min cell SOC",
                    f"{r['captured_above_floor_pct']:.1f} % / {r['min_cell_soc']:.4f}",
                    ">= 95 % / >= 0" if strat == "calibrated" else "",
                )
            )
        out.append(
            (
                f"protection {sc}: rest OCV vs conservative",
                f"{m['rest_ocv_vs_conservative_mv']:+.0f} mV",
                ">= -10 mV" if sc == "warm_light" else "",
            )
        )
        bound = [
            r["to_empty_vs_conservative_pct"]
            for r in rows
            if r["scenario"] == sc and r.get("to_empty_vs_conservative_pct") is not None
        ]
        if bound:
            out.append(
                (
                    f"protection {sc}: bound, energy until a cell is empty vs 3.2 V/5 s",
                    f"{max(bound):+.1f} %",
                    "",
                )
            )
    return out


def _sequencing_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """Issue #15's figures per scenario, without / with the reverse-current comparator."""
    out: list[Headline] = []

    def num(x: Any, fmt: str) -> str:
        return "-" if x is None else fmt.format(x)

    ok = sys.modules["bench_sequencing"].GOALS  # the bench's own table, loaded by run()

    def verdict(r: dict[str, Any], key: str) -> str:
        x = r.get(key)
        if key not in ok:
            return "no goal"
        return "n/a" if x is None else ("met" if ok[key](x) else "MISSED")

    for sc in ("dual_hover_2V", "hover_30A", "four_spread", "hot_insert"):
        d = _pick(rows, scenario=sc, strategy="direct")
        q = _pick(rows, scenario=sc, strategy="sequencing")
        c = _pick(rows, scenario=sc, strategy="sequencing+comp")
        figures = (
            ("both discharge after the voltages meet", "co_share", "{:.1%}", ">= 90 %"),
            ("switch changes per minute of hover", "sw_per_min", "{:.2f}", "<= 1"),
            ("peak share after meet, one held out", "peak_share_held", "{:.2f}", "<= 0.6"),
            ("peak per-battery current / load after meet", "peak_share", "{:.2f}", ""),
            ("longest reverse > 1 A (s)", "rev_1a_s", "{:.1f}", "<= 0.1 s"),
            ("cross-charge (mAh per hour)", "cross_mah_h", "{:.2f}", "<= 1"),
            ("energy vs direct to 1st brown-out", "energy_to_brownout_ratio", "{:.2%}", ">= 99%"),
            ("I2R heat vs direct", "heat_ratio", "{:.2f}", "< 1"),
        )
        for label, key, fmt, goal in figures:
            out.append(
                (
                    f"sequencing {sc}: {label} (no comparator / comparator)",
                    f"{num(q.get(key), fmt)} / {num(c.get(key), fmt)} "
                    f"({verdict(q, key)} / {verdict(c, key)})",
                    goal,
                )
            )
        out.append(
            (
                f"sequencing {sc}: peak reverse current, direct -> no comparator / comparator",
                f"{d['rev_peak_a']:.1f} -> {q['rev_peak_a']:.2f} / {c['rev_peak_a']:.2f} A",
                "<= 0.5C = 2.5 A",
            )
        )
    return out


def _charging_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """Peak current, heat and time to full of each strategy against the baseline."""
    out: list[Headline] = []
    base = _pick(rows, strategy="baseline")
    for r in rows:
        if r is base:
            continue
        peak = r["peak_charge_max_a"] / base["peak_charge_max_a"] - 1
        out.append(
            (
                f"charging {r['strategy']}: peak battery current vs baseline",
                f"{peak * 100:+.0f} %",
                "<= -50 %",
            )
        )
        heat_key = next(k for k in r if "heat" in k and "j" in k.lower())
        heat = r[heat_key] / base[heat_key] - 1
        out.append(
            (
                f"charging {r['strategy']}: I2R heat vs baseline",
                f"{heat * 100:+.1f} %",
                "<= -50 %",
            )
        )
        t = r["time_to_full_s"] / base["time_to_full_s"] - 1
        out.append(
            (
                f"charging {r['strategy']}: time to full vs baseline",
                f"{t * 100:+.1f} %",
                "<= +20 %",
            )
        )
    return out


def _equalization_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """Rest spread and usable capacity of the method per scenario; delivered vs granted Ah and
    the balancing time vs AH (issue #15 §2), with their verdicts."""
    out: list[Headline] = []
    timing = [r for r in rows if r["scenario"] == "time_vs_ah"]
    for sc in sorted({r["scenario"] for r in rows} - {"time_vs_ah"}):
        m = [r for r in rows if r["scenario"] == sc and r["strategy"] == "newton"]
        last = m[-1]
        ok = [
            r["cycle"]
            for r in m
            if r["rest_spread_top_mv"] <= 10.0
            and r.get("usable_ratio", r.get("usable_vs_limit", 0)) >= 0.98
        ]
        ratio = last.get("usable_ratio", last.get("usable_vs_limit"))
        out.append(
            (
                f"equalization {sc}: rest spread / usable vs limit (last cycle)",
                f"{last['rest_spread_top_mv']:.1f} mV / {ratio}",
                "<= 10 mV / >= 0.98",
            )
        )
        out.append(
            (
                f"equalization {sc}: first cycle meeting both",
                str(ok[0]) if ok else "none",
                "stated",
            )
        )
        for strategy in ("newton", "newton_bidir"):
            m = [r for r in rows if r["scenario"] == sc and r["strategy"] == strategy]
            if not m or "delivered_vs_granted" not in m[-1]:
                continue
            end = m[-1]["delivered_vs_granted"]
            worst = min(r["delivered_vs_granted"] for r in m)
            out.append(
                (
                    f"equalization {sc} {strategy}: delivered / granted Ah, worst group, "
                    "whole run (worst cycle end)",
                    f"{end:.4f} ({worst:.4f}) ({'met' if end >= 0.95 else 'NOT MET'})",
                    ">= 0.95",
                )
            )
            lost = max(r["dropped_ah"] for r in m)
            out.append(
                (
                    f"equalization {sc} {strategy}: Ah dropped (granted - delivered - owed)",
                    f"{lost:.1e} ({'met' if lost <= 1e-6 else 'NOT MET'})",
                    "0 (rounding)",
                )
            )
    for strategy in sorted({r["strategy"] for r in timing}):
        t = [r for r in timing if r["strategy"] == strategy]
        worst = max(abs(r["balancing_time_s"] / r["expected_s"] - 1.0) for r in t)
        times = [r["balancing_time_s"] for r in t]
        verdict = "met" if worst <= 0.01 and times == sorted(times) else "NOT MET"
        out.append(
            (
                f"equalization {strategy}: balancing time vs 3600·AH/I, AH "
                f"{t[0]['ah']:g}-{t[-1]['ah']:g} Ah",
                f"{', '.join(f'{x:g}' for x in times)} s; worst {worst * 100:.2f} % ({verdict})",
                "proportional within 1 %, monotone",
            )
        )
    return out


def _acceptance_headlines(name: str, rows: list[dict[str, Any]]) -> list[Headline]:
    """The rows that carry a goal are the issue's figures; bench_core adds its references."""
    out: list[Headline] = []
    for r in rows:
        if r.get("goal"):
            figure = f"{r['figure']:.4g} {r['unit']}"
            out.append((f"{name[6:]}: {r['case'].strip()}", figure, r["goal"]))
    if name == "bench_core":
        for key in ("PyBaMM", "vs one PyBaMM", "Runner.run", "plant alone", "core-less"):
            ref = next((r for r in rows if key in r["case"]), None)
            if ref is not None:
                out.append((f"core: {ref['case']}", f"{ref['figure']:.4g} {ref['unit']}", ""))
    return out


def _core_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """The one-pack and lockstep costs of the whole BMS, compile and start-up times."""
    return _acceptance_headlines("bench_core", rows)


def _campaign_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """The 1,000-flight campaign on Dask."""
    return _acceptance_headlines("bench_campaign", rows)


def _faults_headlines(rows: list[dict[str, Any]]) -> list[Headline]:
    """Issue #15 §5: the fault matrix on uav_mission."""
    faulty = [r for r in rows if r["fault"] != "fault-free"]
    worst = max(r["unsupplied_with_energy_s"] for r in faulty)
    low = min(r["energy_vs_fault_free"] for r in faulty)
    into = max(r["max_into_a"] for r in faulty)
    return [
        ("faults: worst load-unsupplied time with energy left", f"{worst:.3g} s", "0 s"),
        ("faults: lowest flight energy vs fault-free", f"{low:.1%}", "measured"),
        ("faults: largest current into a battery (undocked)", f"{into:.3g} A", "<= 2.5 A"),
    ]


ACCEPTANCE = ("bench_core", "bench_user_run", "bench_compile", "bench_campaign")
"""Modules whose rows with a ``goal`` are issue #14's acceptance figures."""


def _acceptance(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The acceptance rows: measured value, the reference measured in the same run, goal."""
    return [
        {
            "figure": r["case"].strip(),
            "measured": f"{r['figure']:.4g} {r['unit']}",
            "same-run reference": r.get("reference", ""),
            "goal": r["goal"],
            "verdict": r.get("verdict", ""),
        }
        for r in rows
        if r.get("goal")
    ]


_HEADLINES: dict[str, Callable[[list[dict[str, Any]]], list[Headline]]] = {
    "bench_cell": _cell_headlines,
    "bench_loop": _loop_headlines,
    "bench_protection": _protection_headlines,
    "bench_sequencing": _sequencing_headlines,
    "bench_charging": _charging_headlines,
    "bench_faults": _faults_headlines,
    "bench_equalization": _equalization_headlines,
    "bench_core": _core_headlines,
    "bench_campaign": _campaign_headlines,
    "bench_user_run": lambda rows: _acceptance_headlines("bench_user_run", rows),
    "bench_compile": lambda rows: _acceptance_headlines("bench_compile", rows),
}


def _headlines(name: str, rows: list[dict[str, Any]]) -> list[Headline]:
    """(figure, value, target) rows for the closing table; each module's key results."""
    per_module = _HEADLINES.get(name)
    return per_module(rows) if per_module is not None else []


def _run_module(name: str) -> tuple[str, list[Headline], list[dict[str, Any]], bool]:
    """Run one benchmark module: its section text, headlines, acceptance rows, failed?"""
    spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # worker processes pickle functions by module name
    t0 = time.perf_counter()
    heads: list[Headline] = []
    accepted: list[dict[str, Any]] = []
    failed = False
    try:
        spec.loader.exec_module(mod)
        if not callable(getattr(mod, "run", None)):  # a standalone script, not a module
            return f"## {name}: no run(); standalone: python benchmarks/{name}.py\n", [], [], False
        out = mod.run()
        rows = out if isinstance(out, list) else [out]
        text = _table(rows)
        if name in ACCEPTANCE:
            accepted = _acceptance(rows)
        try:
            heads = _headlines(name, rows)
        except (KeyError, IndexError, StopIteration, TypeError):
            heads = [(f"{name}: headline figures", "unavailable", "")]
    except Exception:
        failed = True
        text = "FAILED:\n```\n" + traceback.format_exc() + "```"
    wall = time.perf_counter() - t0
    return f"## {name} ({wall:.0f} s)\n\n{text}\n", heads, accepted, failed


def _acceptance_section(accepted: list[dict[str, Any]]) -> str:
    return (
        "## Issue #14 acceptance figures\n\n"
        "CPU figures are this process's CPU time (`time.process_time`); each stands next to "
        "a reference measured in the same run (the machine is shared: ratios travel, "
        "absolute figures drift with the host and its load). Details and the profiles: "
        "`bench_core` and `bench_campaign` below.\n\n" + _table(accepted) + "\n"
    )


def main() -> int:
    os.environ.setdefault("PYBAMM_DISABLE_TELEMETRY", "true")
    sys.path.insert(0, str(HERE.parent))
    sys.path.insert(0, str(HERE))
    only = set(sys.argv[1:])
    names = [n for n in ORDER if (HERE / f"{n}.py").exists() and (not only or n in only)]
    names += sorted(
        p.stem
        for p in HERE.glob("bench_*.py")
        if p.stem not in ORDER and (not only or p.stem in only)
    )
    sections: list[str] = []
    headlines: list[Headline] = []
    accepted: list[dict[str, Any]] = []
    failed = 0
    for name in names:
        section, heads, acc, bad = _run_module(name)
        print(section, flush=True)
        sections.append(section)
        headlines += heads
        accepted += acc
        failed += bad
    summary = (
        "## Every figure in one table\n\n"
        + _table([{"figure": f, "measured": v, "target": t} for f, v, t in headlines])
        + "\n"
    )
    print(summary, flush=True)
    sections.append(summary)
    header = (
        "# Benchmark results\n\n"
        f"- date: {_dt.datetime.now(_dt.UTC).isoformat(timespec='seconds')}\n"
        f"- machine: {platform.machine()}, {os.cpu_count()} cores, {_cpu_model()},"
        f" Python {platform.python_version()}, {platform.platform()}\n"
        f"- command: `make bench` (`python benchmarks/run_all.py {' '.join(sys.argv[1:])}`)\n\n"
    )
    if accepted:
        section = _acceptance_section(accepted)
        print(section, flush=True)
        sections.insert(0, section)
    if not only:
        path = HERE / "RESULTS.md"
        kept = _kept_sections(path.read_text() if path.exists() else "")
        path.write_text(header + "\n".join(sections) + kept)
    return 1 if failed else 0


KEEP_MARK = "<!-- run_all keeps everything below this line -->"
"""Dated sections a session writes by hand (figures of standalone scripts, measured under
stated conditions) live below this mark: a ``make bench`` rewrites what is above it only."""


def _kept_sections(text: str) -> str:
    at = text.find(KEEP_MARK)
    return "\n" + (text[at:] if at >= 0 else KEEP_MARK + "\n")


if __name__ == "__main__":
    raise SystemExit(main())
