"""Parallel-discharge sequencing vs direct parallel, closed loop on the uav_5ah plant (issue #15).

Scenarios (``examples/sequencing_*.toml``): two 6S 5 Ah 20 mOhm batteries 2 V apart on a 20 A
hover (``dual_hover_2V``) and on a 30 A hover (``hover_30A``); four batteries with a spread in
SOC and resistance on a 20-minute mission (``four_spread``); a fresh battery hot-inserted at
t = 300 s (``hot_insert``). Strategies: ``direct`` (no controller, every FET on: the
baseline), ``sequencing`` (the scenario's ``[sequencing]`` section, no comparator) and
``sequencing+comp`` (the same with the plant's reverse-current comparator fitted,
``[pack.switch] reverse_comparator = true``, trip 1 A).

Figures per run (issue #15 section 1; goals in :data:`GOALS`):

* ``meet_s`` - first time the batteries' open-circuit voltages (the plant's OCV at their SOC
  and temperature) are all within ``v_co`` of each other: "the voltages meet". With unequal
  resistances (four_spread) co-discharging batteries settle at an OCV spread of about
  I_load / N x (R_max - R_min), which is added to ``v_co`` there.
* ``co_share`` - share of the loaded time (load > 1 A) after ``meet_s`` in which every
  present battery discharges with both FETs on (goal >= 0.90).
* ``sw_per_min`` - FET gate changes (charge and discharge, all batteries) per minute of
  loaded time from 10 s after the load starts to the first brown-out: the whole hover, gusts
  included (four_spread: the whole mission, bursts and landing) (goal <= 1).
* ``peak_share`` - largest per-battery discharge current over the load current after
  ``meet_s`` (no goal: once every battery is engaged the split is the plant's; direct
  parallel gives the demo 0.695 after the same meet, issue #24 item 8); ``peak_share_held``
  the same only at steps where the controller held a battery out (goal <= 0.6; 0 when it
  never did); ``peak_share_join`` the same from the first
  period in which every battery discharged (``join_s``); ``peak_share_all`` over the whole
  run (1.0 while R1 has one battery carry the load alone, by design). All three only where the
  load draws more than ``SHARE_MIN_LOAD_A`` (5 A).
* ``rev_peak_a`` / ``rev_1a_s`` - largest current into any battery while no charger is on, and
  the longest uninterrupted time with more than 1 A into one battery (goal: at most one
  control period plus the FET delay, 0.1 s here; the plant applies commands at the next step).
* ``cross_mah_h`` - charge pushed into batteries (no charger) per hour of run (goal <= 1 mAh).
* ``heat_j`` / ``heat_ratio``, ``energy_wh`` / ``energy_ratio`` - ohmic (R0) heat of the cells
  and energy delivered, against direct parallel in the same scenario (less heat).
  ``energy_to_brownout_ratio`` - energy delivered up to the first load brown-out against
  direct parallel's up to its own: the goal (>= 99 %; issue #15's decision, in issue #24:
  after the load's lock-out the flight is over, and pulsing a locked-out load is not energy
  delivered). ``energy_ratio`` (whole run) and ``energy_budget_ratio`` (equal cumulative
  brown-out budget) are shown for information (see docs/parallel_discharge.md).

Run: ``python benchmarks/bench_sequencing.py``.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from packpilot.config import ScenarioConfig, load_config
from packpilot.sim.quality import SEQUENCING_GOALS as GOALS
from packpilot.sim.quality import SHARE_MIN_LOAD_A
from packpilot.sim.quality import sequencing_figures as summarize
from packpilot.sim.quality import sequencing_verdicts as verdicts
from packpilot.sim.runner import Runner

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
SCENARIOS = {
    "dual_hover_2V": "sequencing_dual_hover.toml",
    "hover_30A": "sequencing_hover_30a.toml",
    "four_spread": "sequencing_four_spread.toml",
    "hot_insert": "sequencing_hot_insert.toml",
}
STRATEGIES = ("direct", "sequencing", "sequencing+comp")
__all__ = ["GOALS", "SHARE_MIN_LOAD_A", "run", "run_case", "scenario", "summarize", "verdicts"]
"""The figures (``summarize``) and the goals (``GOALS``) live in :mod:`packpilot.sim.quality`,
shared with the HTML report's sequencing section."""


def scenario(name: str, strategy: str, **sim: Any) -> ScenarioConfig:
    """The scenario file with the strategy's controller list and switch (and [sim] overrides)."""
    cfg = load_config(EXAMPLES / SCENARIOS[name])
    controller: list[str] = [] if strategy == "direct" else ["sequencing"]
    switch = cfg.pack.switch.model_copy(
        update={"reverse_comparator": strategy == "sequencing+comp"}
    )
    return cfg.model_copy(
        update={
            "controller": controller,
            "pack": cfg.pack.model_copy(update={"switch": switch}),
            "sim": cfg.sim.model_copy(update={"progress": False, **sim}),
        }
    )


def run_case(name: str, strategy: str, **sim: Any) -> dict[str, Any]:
    cfg = scenario(name, strategy, **sim)
    t0 = time.perf_counter()
    res = Runner(cfg).run()
    row = {"scenario": name, "strategy": strategy, **summarize(cfg, res)}
    row["wall_s"] = time.perf_counter() - t0
    return row


def run(scenarios: tuple[str, ...] = tuple(SCENARIOS)) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in scenarios:
        base = run_case(name, "direct")
        rows.append(base)
        for strategy in STRATEGIES[1:]:
            rows.append(run_case(name, strategy))
        for row in rows[-len(STRATEGIES) :]:
            row["energy_ratio"] = row["energy_wh"] / base["energy_wh"]
            row["energy_to_brownout_ratio"] = (
                row["energy_to_brownout_wh"] / base["energy_to_brownout_wh"]
            )
            row["energy_budget_ratio"] = row["energy_budget_wh"] / base["energy_budget_wh"]
            row["heat_ratio"] = row["heat_j"] / base["heat_j"]
    return rows


COLUMNS = (
    ("scenario", "{}"),
    ("strategy", "{}"),
    ("meet_s", "{:.1f}"),
    ("co_share", "{:.3f}"),
    ("sw_per_min", "{:.2f}"),
    ("steady_min", "{:.1f}"),
    ("peak_share", "{:.3f}"),
    ("peak_share_held", "{:.3f}"),
    ("join_s", "{:.1f}"),
    ("peak_share_join", "{:.3f}"),
    ("peak_share_all", "{:.3f}"),
    ("rev_peak_a", "{:.2f}"),
    ("rev_1a_s", "{:.2f}"),
    ("rev_0.5a_s", "{:.2f}"),
    ("cross_mah_h", "{:.2f}"),
    ("energy_wh", "{:.2f}"),
    ("energy_ratio", "{:.4f}"),
    ("energy_budget_ratio", "{:.4f}"),
    ("energy_to_brownout_ratio", "{:.4f}"),
    ("heat_j", "{:.0f}"),
    ("heat_ratio", "{:.3f}"),
    ("unsupplied_s", "{:.1f}"),
    ("first_brownout_s", "{:.1f}"),
    ("diode_j", "{:.2f}"),
    ("joins", "{}"),
    ("reverse_events", "{}"),
    ("risk_events", "{}"),
    ("wall_s", "{:.1f}"),
)


def main() -> None:
    rows = run()
    header = [c for c, _ in COLUMNS]
    cells = [
        [fmt.format(r[c]) if r.get(c) is not None else "-" for c, fmt in COLUMNS] for r in rows
    ]
    widths = [max(len(h), *(len(row[i]) for row in cells)) for i, h in enumerate(header)]
    print("  ".join(h.rjust(w) for h, w in zip(header, widths, strict=True)))
    for row in cells:
        print("  ".join(c.rjust(w) for c, w in zip(row, widths, strict=True)))
    print()
    for r in rows:
        if r["strategy"] != "direct":
            v = verdicts(r)
            print(r["scenario"], r["strategy"], {k: f"{v[k]} ({GOALS[k]})" for k in v})


if __name__ == "__main__":
    main()
