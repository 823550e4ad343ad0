"""The BMU's own supply (issue #15 §3): how long the aux battery of ``examples/evtol_charging``
keeps the battery-pack management unit (BMU) powered while undocked, and what a brown-out does.

Plant only (no controller: undocked, the charging method by default never charges the aux
battery, so the BMU load is its only draw): the scenario with the dock absent, every traction
relay and the aux relay closed, no traction load, stepped at ``--dt`` until the BMU browns out.

    python benchmarks/bench_bmu.py [--dt 10] [--soc0 0.25]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from packpilot.config import load_config
from packpilot.model.pack import Pack

SCENARIO = Path(__file__).resolve().parent.parent / "examples" / "evtol_charging.toml"


def run(
    dt_s: float = 10.0, soc0: float | None = None, limit_s: float = 7 * 86400.0
) -> dict[str, float]:
    cfg = load_config(SCENARIO)
    charger = cfg.charger.model_copy(update={"present": False})
    pack_cfg = cfg.pack
    if soc0 is not None:
        bats = [
            b.model_copy(update={"soc0": soc0}) if b.role == "aux" else b
            for b in pack_cfg.batteries
        ]
        pack_cfg = pack_cfg.model_copy(update={"batteries": bats})
    cfg = cfg.model_copy(update={"charger": charger, "pack": pack_cfg})
    pack = Pack(cfg)
    a = pack.aux_index
    assert a is not None
    pack.set_gates(np.ones_like(pack.chg_on), np.ones_like(pack.dsg_on))
    zero = np.zeros(1)
    t_out = float("nan")
    open_after_steps = -1
    v_out = float("nan")
    while pack.t_s < limit_s:
        iv = pack.step(dt_s, "none", zero)
        if not pack.bmu_on[0]:
            t_out = pack.t_s
            v_out = float(iv.battery_v[0, a])
            # the step that browned out left every switch open
            open_after_steps = 0 if not (pack.chg_on.any() or pack.dsg_on.any()) else -1
            break
    soc, _ = pack.cell_states()
    aux_soc = float(soc[0, pack.cell_string == a].min())
    return {
        "cutoff_v": pack.bmu_cutoff_v,
        "bms_load_w": cfg.aux.bms_load_w,
        "brownout_s": t_out,
        "brownout_h": t_out / 3600.0,
        "aux_v_at_brownout": v_out,
        "aux_soc_at_brownout": aux_soc,
        "steps_to_open_all": float(open_after_steps),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--dt", type=float, default=10.0)
    ap.add_argument("--soc0", type=float, default=None, help="aux SOC at the start")
    args = ap.parse_args()
    for k, v in run(args.dt, args.soc0).items():
        print(f"{k:>22}: {v:.4g}")


if __name__ == "__main__":
    main()
