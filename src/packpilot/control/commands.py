"""How controllers write into the shared step: command opinions merged as they are written,
events emitted as codes, status channels stored as numbers. Compiled; called from every rule.

Merging is the left fold of the controllers' outputs in their run order ("off wins"):

* a switch path is on only if every controller with an opinion wants it on;
* the charger takes the latest command, but is off if any commanding controller disabled it
  (so a safety layer can always stop it);
* balancer currents, the aux relay and the aux DC/DC take the latest opinion.

A controller writes each of its opinions once per step (call a ``put_*`` once per battery).
"""

from __future__ import annotations

import math

import numpy as np

from packpilot.contract.arrays import CmdArrays, EventBuf
from packpilot.jit import kernel

# ------------------------------------------------------------------------------ commands


@kernel
def put_chg(cmd: CmdArrays, p: int, i: int, on: bool) -> None:
    """Charge path of battery ``i`` of pack ``p``: AND with earlier opinions."""
    old = cmd.chg_on[p, i]
    cmd.chg_on[p, i] = 1 if on and old != 0 else 0


@kernel
def put_dsg(cmd: CmdArrays, p: int, i: int, on: bool) -> None:
    """Discharge path of battery ``i`` of pack ``p``: AND with earlier opinions."""
    old = cmd.dsg_on[p, i]
    cmd.dsg_on[p, i] = 1 if on and old != 0 else 0


@kernel
def put_charger(cmd: CmdArrays, p: int, voltage_v: float, current_a: float, enable: bool) -> None:
    """Charger setpoint: the latest wins, but off if any commanding controller said off."""
    if cmd.charger_set[p] and not (cmd.charger_enable[p] and enable):
        cmd.charger_v[p] = 0.0
        cmd.charger_a[p] = 0.0
        cmd.charger_enable[p] = False
    else:
        cmd.charger_v[p] = voltage_v
        cmd.charger_a[p] = current_a
        cmd.charger_enable[p] = enable
    cmd.charger_set[p] = True


@kernel
def put_charger_off(cmd: CmdArrays, p: int) -> None:
    put_charger(cmd, p, 0.0, 0.0, False)


@kernel
def put_balancer(cmd: CmdArrays, p: int, i: int, g: int, current_a: float) -> None:
    """Equalizer current into group ``g`` of battery ``i`` (the latest controller's row wins;
    call :func:`claim_balancer` first so groups it leaves out read 0)."""
    cmd.balancer_a[p, i, g] = current_a


@kernel
def claim_balancer(cmd: CmdArrays, p: int) -> None:
    """Start this controller's balancer opinion for pack ``p``: every group 0 A."""
    cmd.balancer_a[p].fill(0.0)
    cmd.balancer_set[p] = True


@kernel
def put_aux_relay(cmd: CmdArrays, p: int, closed: bool) -> None:
    cmd.aux_relay[p] = 1 if closed else 0


@kernel
def put_aux_charge(cmd: CmdArrays, p: int, current_a: float) -> None:
    cmd.aux_charge_set[p] = True
    cmd.aux_charge_a[p] = current_a


# ------------------------------------------------------------------------------ events


@kernel
def emit(ev: EventBuf, p: int, src: int, code: int, battery: int, t_s: float) -> int:
    """Append an event; returns the row to write its numbers into (``ev.val[k, slot]``).

    Unused slots read NaN. When the buffer is full the event is counted in ``dropped`` and the
    scratch row is returned, so the caller's writes are harmless.
    """
    cap = ev.pack.shape[0] - 1
    k = ev.n[0]
    if k >= cap:
        ev.dropped[0] += 1
        k = cap
    else:
        ev.n[0] = k + 1
    ev.pack[k] = p
    ev.src[k] = src
    ev.code[k] = code
    ev.battery[k] = battery
    ev.t_s[k] = t_s
    ev.val[k].fill(np.nan)
    return int(k)


# ------------------------------------------------------------------------------ numbers


@kernel
def finite(x: float) -> bool:
    return math.isfinite(x)


@kernel
def fmin(a: float, b: float) -> float:
    """Python's ``min(a, b)``: the first argument on ties and NaN comparisons."""
    return b if b < a else a


@kernel
def fmax(a: float, b: float) -> float:
    """Python's ``max(a, b)``: the first argument on ties and NaN comparisons."""
    return b if b > a else a


__all__ = [
    "claim_balancer",
    "emit",
    "finite",
    "fmax",
    "fmin",
    "put_aux_charge",
    "put_aux_relay",
    "put_balancer",
    "put_charger",
    "put_charger_off",
    "put_chg",
    "put_dsg",
]
