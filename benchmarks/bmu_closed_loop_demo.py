"""Closed-loop brown-out in evtol_charging (issue #15 §3): the aux battery starts at SOC 0, the
dock leaves at 20 s, a hook closes every traction relay at 30 s (undocked, the charging method
has no opinion on them), and the 15 W BMU runs the aux battery down to its cut-off. Prints the
BmuBrownOut event and the gates of the trace rows around it (a row is the state at the end of
the step that starts at its time).

    python benchmarks/bmu_closed_loop_demo.py
"""
import time

import numpy as np

from packpilot.config import load_config
from packpilot.sim.runner import Runner

cfg = load_config("examples/evtol_charging.toml")
bats = [b.model_copy(update={"soc0": 0.0}) if b.role == "aux" else b for b in cfg.pack.batteries]
cfg = cfg.model_copy(update={
    "pack": cfg.pack.model_copy(update={"batteries": bats}),
    "charger": cfg.charger.model_copy(update={"disconnect_s": 20.0}),
    "sim": cfg.sim.model_copy(update={"duration_s": 6000.0}),
})
t0 = time.time()
def close_all(runner, t):
    # undocked at 30 s: something (here: this hook) closes every relay; the charging method
    # has no opinion on them undocked, so they stay closed until the brown-out
    if 30.0 <= t < 32.0:
        pk = runner.plant.pack
        pk.set_gates(np.ones_like(pk.chg_on), np.ones_like(pk.dsg_on))

r = Runner(cfg, progress=False, hooks=[close_all])
res = r.run()
ev = [e for e in res.events if e.kind.startswith("Bmu")]
for e in ev:
    print(e.t_s, e.kind, e.message, e.data)
tr = res.trace
t = tr.t_s
chg = tr.channel("chg_on")
dsg = tr.channel("dsg_on")
change = np.flatnonzero(np.any(chg[1:] != chg[:-1], axis=1)) + 1
print("gate changes at", [(float(t[j]), chg[j].astype(int).tolist()) for j in change])
tb = ev[0].t_s if ev else None
if tb is not None:
    k = int(np.searchsorted(t, tb))
    print("sample times around:", t[k-1:k+2])
    for j in range(k-1, k+2):
        print(t[j], "chg", chg[j].astype(int), "dsg", dsg[j].astype(int))
print("wall", time.time() - t0)
