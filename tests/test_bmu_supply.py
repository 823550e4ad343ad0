"""The BMU's own supply from the aux battery (issue #15 §3): brown-out opens every switch within
the step, restart only above cut-off + hysteresis, the BMU load, the aux relay gates its DC/DC."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from packpilot.config import ScenarioConfig, load_config
from packpilot.model.pack import Pack
from packpilot.sim.loop import ClosedLoop

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "evtol_charging.toml"


def scenario(**aux: Any) -> ScenarioConfig:
    cfg = load_config(EXAMPLE)
    return cfg.model_copy(
        update={
            "aux": cfg.aux.model_copy(update=aux),
            "charger": cfg.charger.model_copy(update={"present": False}),
        }
    )


def closed_pack(**aux: Any) -> Pack:
    pack = Pack(scenario(**aux))
    pack.set_gates(np.ones_like(pack.chg_on), np.ones_like(pack.dsg_on))
    return pack


def aux_v(pack: Pack, v: float) -> np.ndarray:
    bv = np.zeros((pack.n_packs, pack.n_strings))
    assert pack.aux_index is not None
    bv[:, pack.aux_index] = v
    return bv


def test_default_cutoff_is_the_aux_cells_v_min() -> None:
    pack = Pack(scenario())
    assert pack.bmu_cutoff_v == pytest.approx(4 * 2.5)  # 4S LFP, 2.5 V per cell


def test_brownout_opens_every_switch_within_the_step() -> None:
    pack = closed_pack(bmu_cutoff_v=14.0)  # above the 4S LFP battery's voltage
    pack.set_aux_charge(np.array([5.0]))
    assert pack.chg_on.all() and pack.dsg_on.all()
    iv = pack.step(2.0, "none", np.zeros(1))
    assert not pack.bmu_on[0] and pack.bmu_changed[0]
    assert not pack.chg_on.any() and not pack.dsg_on.any()  # every relay, the aux one too
    assert pack.aux_charge_a[0] == 0.0
    # and the next period runs with them open: no traction current, the BMU draws nothing
    iv = pack.step(2.0, "none", np.zeros(1))
    assert np.all(iv.string_a[0] == 0.0)
    assert not pack.bmu_changed[0]


def test_a_browned_out_bmu_drives_nothing() -> None:
    pack = closed_pack(bmu_cutoff_v=14.0)
    pack.step(2.0, "none", np.zeros(1))
    pack.set_gates(np.ones_like(pack.chg_on), np.ones_like(pack.dsg_on))  # a command arrives
    pack.set_aux_charge(np.array([5.0]))
    pack.hold_unpowered()  # what SimulatedPlant.apply does after the commands
    assert not pack.chg_on.any() and not pack.dsg_on.any() and pack.aux_charge_a[0] == 0.0


def test_restart_only_above_cutoff_plus_hysteresis() -> None:
    pack = closed_pack()  # cut-off 10 V, hysteresis 0.5 V
    pack._bmu_supply(aux_v(pack, 10.0))
    assert pack.bmu_on[0]  # at the cut-off: still powered (below it browns out)
    pack._bmu_supply(aux_v(pack, 9.99))
    assert not pack.bmu_on[0] and pack.bmu_changed[0]
    assert not pack.chg_on.any() and not pack.dsg_on.any()
    for v in (10.0, 10.3, 10.49):
        pack._bmu_supply(aux_v(pack, v))
        assert not pack.bmu_on[0] and not pack.bmu_changed[0], v
    pack._bmu_supply(aux_v(pack, 10.5))
    assert pack.bmu_on[0] and pack.bmu_changed[0]
    assert not pack.chg_on.any()  # restarted with every switch still open
    pack._bmu_supply(aux_v(pack, 10.2))  # between cut-off and restart: stays powered
    assert pack.bmu_on[0]


def test_the_bmu_load_drains_the_aux_battery_only_while_powered() -> None:
    pack = closed_pack()
    a = pack.aux_index
    assert a is not None
    iv = pack.step(2.0, "none", np.zeros(1))
    v = iv.battery_v[0, a]
    assert iv.string_a[0, a] == pytest.approx(15.0 / v, rel=0.02)  # 15 W BMU, discharge > 0
    pack.bmu_on[:] = False
    iv = pack.step(2.0, "none", np.zeros(1))
    assert iv.string_a[0, a] == pytest.approx(0.0, abs=1e-12)


def test_the_aux_dcdc_charges_only_through_the_aux_relay() -> None:
    pack = closed_pack()
    a = pack.aux_index
    assert a is not None
    pack.set_aux_charge(np.array([5.0]))
    pack.chg_on[:, a] = False
    pack.dsg_on[:, a] = False
    pack.step(2.0, "none", np.zeros(1))
    assert pack.aux_input()[0] == 0.0
    iv = pack.step(2.0, "none", np.zeros(1))
    assert iv.string_a[0, a] > 0.0  # only the BMU load
    pack.chg_on[:, a] = True
    pack.dsg_on[:, a] = True
    assert pack.aux_input()[0] == 5.0
    iv = pack.step(2.0, "none", np.zeros(1))
    assert iv.string_a[0, a] < -3.0  # charged by the DC/DC from the bus


def test_brownout_and_restart_are_logged() -> None:
    pack = closed_pack()
    loop: Any = SimpleNamespace(plant=SimpleNamespace(pack=pack))
    pack._bmu_supply(aux_v(pack, 9.9))
    (p, e), = ClosedLoop._bmu_events(loop, 100.0)
    assert (p, e.kind, e.data["aux_v"], e.data["cutoff_v"]) == (0, "BmuBrownOut", 9.9, 10.0)
    pack._bmu_supply(aux_v(pack, 10.6))
    (p, e), = ClosedLoop._bmu_events(loop, 200.0)
    assert e.kind == "BmuRestarted"


def test_closed_loop_brownout_opens_every_relay_in_the_step_it_happens() -> None:
    """evtol_charging, aux at SOC 0, dock gone at 20 s, every traction relay closed at 30 s:
    the BMU browns out (at empty since issue #24: the 20 s on the dock put ~0.03 Ah in, a
    couple of minutes for the 15 W BMU; before, it ran the LFP battery below empty down to
    its 10 V cut-off, ~45 min) and the trace row of that very step shows all open."""
    from packpilot.sim.runner import Runner

    cfg = load_config(EXAMPLE)
    bats = [
        b.model_copy(update={"soc0": 0.0}) if b.role == "aux" else b for b in cfg.pack.batteries
    ]
    cfg = cfg.model_copy(
        update={
            "pack": cfg.pack.model_copy(update={"batteries": bats}),
            "charger": cfg.charger.model_copy(update={"disconnect_s": 20.0}),
            "sim": cfg.sim.model_copy(update={"duration_s": 4000.0}),
        }
    )

    def close_all(runner: Runner, t: float) -> None:
        if 30.0 <= t < 32.0:
            pk = runner.plant.pack
            pk.set_gates(np.ones_like(pk.chg_on), np.ones_like(pk.dsg_on))

    res = Runner(cfg, progress=False, hooks=[close_all]).run()
    (e,) = [e for e in res.events if e.kind.startswith("Bmu")]
    assert e.kind == "BmuBrownOut" and "empty" in e.message and e.t_s > 32.0
    k = int(np.searchsorted(res.trace.t_s, e.t_s))
    chg, dsg = res.trace.channel("chg_on"), res.trace.channel("dsg_on")
    assert chg[k - 1, :6].all() and dsg[k - 1, :6].all()  # closed until that step
    assert not chg[k:].any() and not dsg[k:].any()  # open from its end on, and stay open


# --------------------------------------------------------------------------- issue #24 item 5


def aux_soc(pack: Pack) -> float:
    soc, _ = pack.cell_states()
    return float(soc[0, pack.cell_string == pack.aux_index].min())


def test_the_aux_battery_never_goes_below_empty() -> None:
    """Issue #24 item 5: an LFP aux battery at SOC 0 still shows more than the BMU's cut-off,
    and the 15 W BMU ran it to -5 %. Now the BMU's draw stops at empty (its protection) and
    the BMU browns out there, whatever the terminal voltage says."""
    cfg = scenario()
    bats = [
        b.model_copy(update={"soc0": 0.0005}) if b.role == "aux" else b
        for b in cfg.pack.batteries
    ]
    pack = Pack(cfg.model_copy(update={"pack": cfg.pack.model_copy(update={"batteries": bats})}))
    lowest = 1.0
    for _ in range(60):  # 0.0005 x 20 Ah at 15 W / ~12 V lasts ~29 s
        pack.step(2.0, "none", np.zeros(1))
        lowest = min(lowest, aux_soc(pack))
    assert lowest >= 0.0
    assert not pack.bmu_on[0]  # browned out at empty ...
    assert pack.battery_v_aux()[0] >= pack.bmu_cutoff_v  # ... above the voltage cut-off


def docked_browned_out(**aux: Any) -> Pack:
    """evtol_charging, docked, its aux battery empty and the BMU browned out."""
    cfg = load_config(EXAMPLE)
    bats = [
        b.model_copy(update={"soc0": 0.0}) if b.role == "aux" else b for b in cfg.pack.batteries
    ]
    cfg = cfg.model_copy(
        update={
            "aux": cfg.aux.model_copy(update=aux),
            "pack": cfg.pack.model_copy(update={"batteries": bats}),
        }
    )
    pack = Pack(cfg)
    pack.bmu_on[:] = False  # browned out before the dock came
    pack.hold_unpowered()
    return pack


def test_the_dock_restarts_the_bmu_and_charges_the_aux_battery_by_itself() -> None:
    """Issue #24 item 5: the dock supplies the BMU (and charges the aux battery) without the
    BMU's help: with every switch open and nothing commanded, a docked browned-out BMU is
    powered again after one period and the aux battery takes the dock path's current."""
    pack = docked_browned_out()
    a = pack.aux_index
    assert a is not None and pack.dock_supplies_bmu()[0]
    soc0 = aux_soc(pack)
    iv = pack.step(2.0, "none", np.zeros(1))
    assert pack.bmu_on[0] and pack.bmu_changed[0]
    assert not pack.chg_on.any() and not pack.dsg_on.any()  # nothing was closed for it
    assert iv.string_a[0, a] == pytest.approx(-1.0, rel=0.05)  # the dock path's 1 A
    for _ in range(30):
        pack.step(2.0, "none", np.zeros(1))
    assert aux_soc(pack) > soc0
    assert pack.bmu_w()[0] == 0.0  # the BMU runs from the dock, not from the aux battery


def test_without_the_dock_path_a_browned_out_bmu_stays_down() -> None:
    """``dock_powers_bmu = false``: the BMU lives on the aux battery alone (the behaviour
    before issue #24): docking changes nothing for a browned-out BMU."""
    pack = docked_browned_out(dock_powers_bmu=False)
    for _ in range(5):
        iv = pack.step(2.0, "none", np.zeros(1))
    assert not pack.bmu_on[0]
    assert iv.string_a[0, pack.aux_index] == pytest.approx(0.0, abs=1e-12)


def test_closed_loop_the_dock_brings_a_browned_out_bmu_back_and_the_pack_charges() -> None:
    """Issue #24 item 5's acceptance, closed loop: the aux battery nearly empty and no dock,
    the BMU browns out (at empty, ~2 min) and every switch opens; the dock connects at 600 s,
    powers the BMU, which restarts and charges the aux battery and the pack to full. While it
    was down the charging method logged nothing (before, it logged idle -> rest -> S20 as if
    charging, with every switch held open, and the aux battery stayed at -5 %). evtol_charging
    with 2 Ah traction batteries and a 10 A dock (same C-rates, 50 x shorter)."""
    import tomllib

    from packpilot.config import parse_config
    from packpilot.sim.runner import Runner

    data = tomllib.loads(EXAMPLE.read_text())
    for b in data["pack"]["batteries"]:
        if b.get("role") == "aux":
            b["soc0"] = 0.002
        else:
            b["capacity_ah"] = 2.0
    data["charger"].update({"current_a": 10.0, "connect_s": 600.0})
    data["charging"].update({"charger_current_limit_a": 10.0, "termination_current_a": 0.2})
    data["sim"].update({"dt_s": 1.0, "duration_s": 6000.0, "progress": False})
    runner = Runner(parse_config(data), progress=False)
    res = runner.run()
    kinds = [(e.t_s, e.kind) for e in res.events]
    out = next(t for t, k in kinds if k == "BmuBrownOut")
    back = next(t for t, k in kinds if k == "BmuRestarted")
    assert out < 599.0 <= back <= 600.0  # the step ending at 600 s, when the dock connects
    assert not [k for t, k in kinds if out < t < back]  # a browned-out BMU logs nothing
    stages = [e.data["stage"] for e in res.events if e.kind == "StageChanged" and e.t_s > back]
    assert stages[0] == "rest" and stages[1] in ("S20", "S30", "S40")  # a fresh session
    assert [k for _, k in kinds].count("ChargeComplete") == 1
    tr = list(runner.traction)
    soc = res.trace.channel("soc")
    a = res.battery_names.index("AUX")
    assert soc[-1, tr].min() > 0.97
    assert soc[:, a].min() >= 0.0  # never below empty
    assert soc[-1, a] > 0.05  # charged from the dock (its path, then the BMU's DC/DC)
    k = int(np.searchsorted(res.trace.t_s, out)) + 1
    j = int(np.searchsorted(res.trace.t_s, back))
    assert not res.trace.channel("chg_on")[k:j].any()  # every switch open while down


def test_the_dock_alone_restarts_the_bmu_with_the_aux_battery_still_empty() -> None:
    """The restart comes from the dock's supply itself, not from the charge its aux path puts
    in (``dock_aux_charge_a = 0``): the aux battery stays empty, the BMU is powered anyway, and
    it draws nothing from the aux battery."""
    pack = docked_browned_out(dock_aux_charge_a=0.0)
    pack.step(2.0, "none", np.zeros(1))
    assert pack.bmu_on[0] and pack.bmu_changed[0]
    assert aux_soc(pack) <= 1e-6  # still empty
    pack.step(2.0, "none", np.zeros(1))
    assert pack.bmu_on[0] and aux_soc(pack) >= 0.0


def test_closed_loop_a_browned_out_bmu_logs_no_stage_while_docked() -> None:
    """``dock_powers_bmu = false`` (no dock path), the aux battery nearly empty: the BMU
    browns out undocked (~2 min); the dock connects at 200 s and cannot bring it back. Nothing
    of the BMU runs, so the charging method logs no stage it cannot act on (before issue #24:
    idle -> rest -> S20 with every switch held open) and sends no heartbeat (no charge)."""
    import tomllib

    from packpilot.config import parse_config
    from packpilot.sim.runner import Runner

    data = tomllib.loads(EXAMPLE.read_text())
    for b in data["pack"]["batteries"]:
        if b.get("role") == "aux":
            b["soc0"] = 0.002
    data["aux"]["dock_powers_bmu"] = False
    data["charger"]["connect_s"] = 200.0
    data["sim"].update({"dt_s": 1.0, "duration_s": 400.0, "progress": False})
    res = Runner(parse_config(data), progress=False).run()
    out = next(e.t_s for e in res.events if e.kind == "BmuBrownOut")
    assert 30.0 < out < 200.0
    assert [e.kind for e in res.events if e.t_s > out] == []
    assert res.trace.charger_a.max() < 0.01  # no heartbeat ever reached the dock
