"""The TC/Elcon charger link of P packs as two compiled kernels: the python-can path, modelled.

With ``[can] interface = "virtual"`` every pack's charger is commanded through
:class:`~packpilot.io.can.link.CanChargerLink`: the BMS-side client sends a request frame
(0.1 V / 0.1 A counts, control on/off) every second, the emulated charger node forwards each
valid request to the plant's dock and answers with a status frame every second, both over a
python-can virtual bus. That costs 15-30 µs per pack per step in Python. :class:`ElconLinks`
is the same link for P packs with its state in two arrays over packs and its per-step work
in two kernels (:func:`elcon_poll`, :func:`elcon_send`), and reproduces bit for bit, step
for step, what the python-can path does inside the closed loop, wrapped as the loop wraps it
(:class:`~packpilot.sim.links.ChargerLinks` over
:class:`~packpilot.sim.faults.SilenceableLink` over ``CanChargerLink``):

* the codec's quantization (``round`` half to even on ``value * 10``, clamped to 0..0xFFFF, a
  non-finite setpoint sent as 0 V / 0 A / off), decoding as ``counts / 10``;
* the client's heartbeat cadence (due at ``t >= next - 1e-9``, restarting from now after a
  stall), its status timeout (5 s, ``CanChargerLink``'s default: NaN outputs, offline) and the
  first poll as its time reference;
* the emulator's request forwarding (``charger.request(v, a, enable, t)``: the dock's clamp to
  its rating is done here, as ``ChargerModel.request`` does it), its status cadence, the plant's
  output and flags read when the status frame is built, and the ``communication_timeout`` bit
  it raises itself once no request came for ``heartbeat_timeout_s``;
* the frame in flight: a status frame sent at the end of a step is read at the next poll, even
  while the link is silenced (the wrapper still polls the inner link, and drops the result);
* :class:`ChargerLinks`' tracking: the last status, offline (values kept) once nothing came
  through for ``[charger] heartbeat_timeout_s``, the scenario's default setpoint when no
  controller commanded the charger;
* the frame counters of both nodes (sent, received; nothing malformed can occur here).

Not modelled (they stay with ``CanChargerLink``): the bus itself, frame logs, a named or real
channel other nodes could see, ``inject`` (foreign frames) and ``hang`` (a stalled BMS task).
Between steps at most one frame is in flight (the status frame); a request frame is sent and
consumed within the same ``send``.

State (``NaN`` is ``None`` for times; flags are a 5-bit mask, bit k = ``CHARGER_FLAGS[k]``):
``fs`` (P, NF) float64 and ``st`` (P, NI) int64, columns named ``F_*`` and ``I_*`` below.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from packpilot.config import ScenarioConfig
from packpilot.contract.arrays import CmdArrays, MeasArrays
from packpilot.contract.charger import CHARGER_FLAGS, status_in_range
from packpilot.jit import kernel, kernel_inline
from packpilot.model.pack import Pack

# ------------------------------------------------------------------ the protocol's numbers
# The same as packpilot.io.can (codec PERIOD_S / COUNTS_PER_UNIT / _RAW_MAX, client
# MAX_FRAMES_PER_POLL, CanChargerLink's status_timeout_s default): not imported, so a run on
# the model does not load python-can and cantools; tests/test_elcon_model.py checks they agree.
PERIOD_S = 1.0
COUNTS_PER_UNIT = 10
RAW_MAX = 0xFFFF
DUE_EPS_S = 1e-9
"""A frame is due at ``t >= next - DUE_EPS_S`` (client and emulator)."""
CLIENT_STATUS_TIMEOUT_S = 5.0
"""``CanChargerLink(status_timeout_s=5.0)``: the client reports NaN / offline after this."""
CONTROL_ON = 0
COMM_TIMEOUT_BIT = 1 << CHARGER_FLAGS.index("communication_timeout")

# ------------------------------------------------------------------ state columns
F_REQ_V = 0
"""Client: the setpoint it sends (``client.request``), initially 0 V / 0 A / off."""
F_REQ_A = 1
F_CL_FIRST = 2
"""Client: time of its first poll."""
F_CL_STATUS_T = 3
"""Client: time the last status frame was read."""
F_CL_NEXT_TX = 4
F_CL_V = 5
"""Client: ``last_status`` outputs (decoded)."""
F_CL_A = 6
F_EM_FIRST = 7
"""Emulator: time of its first poll."""
F_EM_REQ_T = 8
"""Emulator: time of the last valid request."""
F_EM_NEXT_TX = 9
F_LK_V = 10
"""ChargerLinks: the last status's outputs."""
F_LK_A = 11
F_LK_SEEN = 12
"""ChargerLinks: time a status last came through."""
NF = 13

I_SILENCED = 0
"""``can_silence``: nothing crosses (the client still reads what is already queued)."""
I_REQ_EN = 1
I_CL_HAS = 2
"""Client: has a ``last_status``."""
I_CL_FLAGS = 3
I_PEND = 4
"""Status frames queued for the client (sent by the emulator, not read yet)."""
I_PEND_V = 5
"""Raw counts and flag bits of the (last) queued status frame."""
I_PEND_A = 6
I_PEND_FLAGS = 7
I_LK_HAS = 8
"""ChargerLinks: has a last status (``m.charger.reported``)."""
I_LK_FLAGS = 9
I_LK_ONLINE = 10
I_CL_SENT = 11
"""Frame counters: client sent (requests) / received (status), emulator sent / received."""
I_CL_RECV = 12
I_EM_SENT = 13
I_EM_RECV = 14
I_CL_IMPL = 15
"""Status frames the client rejected as beyond the charger's rating (``implausible``)."""
NI = 16

P_STATUS_TIMEOUT = 0
"""Client status timeout (s)."""
P_LINK_TIMEOUT = 1
"""ChargerLinks: offline after this long without a status (``heartbeat_timeout_s``)."""
P_HB_TIMEOUT = 2
"""Emulator: heartbeat lost after this long without a request (``heartbeat_timeout_s``)."""
P_PERIOD = 3
P_RATED_V = 4
P_RATED_A = 5
P_DEF_V = 6
"""The scenario's default setpoint (no controller commanded the charger)."""
P_DEF_A = 7
P_DEF_EN = 8
NP = 9


# ------------------------------------------------------------------ codec
@kernel_inline
def raw_count(value: float) -> int:
    """``codec._raw``: ``value`` to an unsigned 16-bit count, ``round`` (half to even) of
    ``value * 10``, clamped to 0..0xFFFF; 0 for a non-finite value. A finite value whose
    ``value * 10`` overflows clamps too (the codec's ``round(inf)`` would raise)."""
    if not math.isfinite(value):
        return 0
    x = value * COUNTS_PER_UNIT
    if x >= RAW_MAX:
        return RAW_MAX
    if not x > 0.0:
        return 0
    r = math.floor(x)
    d = x - r
    if d > 0.5:
        return int(r + 1)
    if d < 0.5:
        return int(r)
    return int(r + (r % 2))


@kernel_inline
def decode_count(raw: int) -> float:
    """``raw / COUNTS_PER_UNIT``: the physical value of a count (98.0, not 98.00000000000001)."""
    return raw / COUNTS_PER_UNIT


_in_range = kernel_inline(status_in_range)
"""The contract's range check of a charger status, compiled (one implementation)."""


@kernel_inline
def _read(prm: Any, fs: Any, st: Any, p: int, t: float) -> None:
    """``ChargerClient.read`` up to the timeout test: first poll, drain the queued status
    (a status beyond the charger's rating is counted and dropped, as the client does)."""
    if math.isnan(fs[p, F_CL_FIRST]):
        fs[p, F_CL_FIRST] = t
    n = st[p, I_PEND]
    v, a = decode_count(st[p, I_PEND_V]), decode_count(st[p, I_PEND_A])
    if n > 0 and not _in_range(v, a, prm[P_RATED_V], prm[P_RATED_A]):
        st[p, I_CL_IMPL] += n
        st[p, I_PEND] = 0
    elif n > 0:
        st[p, I_CL_RECV] += n
        st[p, I_CL_HAS] = 1
        fs[p, F_CL_V] = decode_count(st[p, I_PEND_V])
        fs[p, F_CL_A] = decode_count(st[p, I_PEND_A])
        st[p, I_CL_FLAGS] = st[p, I_PEND_FLAGS]
        fs[p, F_CL_STATUS_T] = t
        st[p, I_PEND] = 0


@kernel_inline
def _next_tx(nxt_s: float, t: float, period_s: float) -> float:
    """The next due time after a frame went out at ``t`` (``nxt_s`` NaN: the first frame);
    after a stall the cadence restarts from now instead of bursting to catch up."""
    nxt = (t if math.isnan(nxt_s) else nxt_s) + period_s
    return nxt if nxt > t else t + period_s


@kernel
def elcon_poll(
    prm: Any,
    fs: Any,
    st: Any,
    t: float,
    reported: Any,
    output_v: Any,
    output_a: Any,
    flags: Any,
    online: Any,
) -> None:
    """``ChargerLinks.poll`` over ``SilenceableLink(CanChargerLink)`` for every pack."""
    for p in range(fs.shape[0]):
        # the client reads (even while silenced: the wrapper polls, then drops the result)
        _read(prm, fs, st, p, t)
        ref = fs[p, F_CL_FIRST] if math.isnan(fs[p, F_CL_STATUS_T]) else fs[p, F_CL_STATUS_T]
        got = True
        if t - ref > prm[P_STATUS_TIMEOUT]:
            sv, sa, sf, son = math.nan, math.nan, 0, False
        elif st[p, I_CL_HAS] != 0:
            sv, sa, sf, son = fs[p, F_CL_V], fs[p, F_CL_A], st[p, I_CL_FLAGS], True
        else:
            sv, sa, sf, son = math.nan, math.nan, 0, False
            got = False
        if st[p, I_SILENCED] != 0:
            got = False
        # ChargerLinks: the last status, offline once nothing came through for the timeout
        if got:
            fs[p, F_LK_SEEN] = t
            st[p, I_LK_HAS] = 1
            fs[p, F_LK_V] = sv
            fs[p, F_LK_A] = sa
            st[p, I_LK_FLAGS] = sf
            st[p, I_LK_ONLINE] = 1 if son else 0
        elif (
            st[p, I_LK_HAS] != 0
            and not math.isnan(fs[p, F_LK_SEEN])
            and t - fs[p, F_LK_SEEN] > prm[P_LINK_TIMEOUT]
            and st[p, I_LK_ONLINE] != 0
        ):
            st[p, I_LK_ONLINE] = 0
        if st[p, I_LK_HAS] == 0:
            reported[p] = False
            output_v[p] = math.nan
            output_a[p] = math.nan
            for k in range(flags.shape[1]):
                flags[p, k] = False
            online[p] = False
            continue
        reported[p] = True
        output_v[p] = fs[p, F_LK_V]
        output_a[p] = fs[p, F_LK_A]
        for k in range(flags.shape[1]):
            flags[p, k] = ((st[p, I_LK_FLAGS] >> k) & 1) != 0
        online[p] = st[p, I_LK_ONLINE] != 0


@kernel
def elcon_send(
    prm: Any,
    fs: Any,
    st: Any,
    t: float,
    cmd_set: Any,
    cmd_v: Any,
    cmd_a: Any,
    cmd_en: Any,
    v_req: Any,
    i_req: Any,
    on_req: Any,
    last_request_s: Any,
    plant_flags: Any,
    out_v: Any,
    out_a: Any,
) -> None:
    """``ChargerLinks.send`` over ``SilenceableLink(CanChargerLink)`` for every pack: the
    client's heartbeat, the emulator forwarding it to the plant's dock and sending its status."""
    for p in range(fs.shape[0]):
        if st[p, I_SILENCED] != 0:
            continue
        # ChargerLinks: the merged command, or the scenario's default; client.set_request
        if cmd_set[p]:
            fs[p, F_REQ_V] = cmd_v[p]
            fs[p, F_REQ_A] = cmd_a[p]
            st[p, I_REQ_EN] = 1 if cmd_en[p] else 0
        else:
            fs[p, F_REQ_V] = prm[P_DEF_V]
            fs[p, F_REQ_A] = prm[P_DEF_A]
            st[p, I_REQ_EN] = 1 if prm[P_DEF_EN] != 0.0 else 0
        # client.poll: the heartbeat when due (encode_request), then read
        if math.isnan(fs[p, F_CL_FIRST]):
            fs[p, F_CL_FIRST] = t
        sent = False
        rq_v = 0
        rq_a = 0
        rq_ctl = 1
        nxt_s = fs[p, F_CL_NEXT_TX]
        if math.isnan(nxt_s) or t >= nxt_s - DUE_EPS_S:
            v = fs[p, F_REQ_V]
            a = fs[p, F_REQ_A]
            finite = math.isfinite(v) and math.isfinite(a)
            rq_v = raw_count(v) if finite else 0
            rq_a = raw_count(a) if finite else 0
            rq_ctl = CONTROL_ON if (st[p, I_REQ_EN] != 0 and finite) else 1
            sent = True
            st[p, I_CL_SENT] += 1
            fs[p, F_CL_NEXT_TX] = _next_tx(nxt_s, t, prm[P_PERIOD])
        _read(prm, fs, st, p, t)
        # emulator.poll: forward the request to the dock, then the status frame when due
        if math.isnan(fs[p, F_EM_FIRST]):
            fs[p, F_EM_FIRST] = t
        if sent:
            st[p, I_EM_RECV] += 1
            fs[p, F_EM_REQ_T] = t
            rv = decode_count(rq_v)
            ra = decode_count(rq_a)
            # ChargerModel.request: min(max(x, 0.0), rated)
            if rv < 0.0:
                rv = 0.0
            if prm[P_RATED_V] < rv:
                rv = prm[P_RATED_V]
            if ra < 0.0:
                ra = 0.0
            if prm[P_RATED_A] < ra:
                ra = prm[P_RATED_A]
            v_req[p] = rv
            i_req[p] = ra
            on_req[p] = rq_ctl == CONTROL_ON
            last_request_s[p] = t
        nxt_s = fs[p, F_EM_NEXT_TX]
        if math.isnan(nxt_s) or t >= nxt_s - DUE_EPS_S:
            bits = 0
            for k in range(plant_flags.shape[1]):
                if plant_flags[p, k]:
                    bits |= 1 << k
            ref = fs[p, F_EM_FIRST] if math.isnan(fs[p, F_EM_REQ_T]) else fs[p, F_EM_REQ_T]
            if t - ref > prm[P_HB_TIMEOUT]:  # heartbeat lost
                bits |= COMM_TIMEOUT_BIT
            st[p, I_PEND] += 1
            st[p, I_PEND_V] = raw_count(out_v[p])
            st[p, I_PEND_A] = raw_count(out_a[p])
            st[p, I_PEND_FLAGS] = bits
            st[p, I_EM_SENT] += 1
            fs[p, F_EM_NEXT_TX] = _next_tx(nxt_s, t, prm[P_PERIOD])


# ------------------------------------------------------------------ the links of P packs
class ElconLinks:
    """The TC/Elcon link of every pack (the ``ChargerLinks`` interface), compiled."""

    def __init__(self, cfg: ScenarioConfig, pack: Pack) -> None:
        c = cfg.charger
        self.pack = pack
        self.n_packs = n = pack.n_packs
        prm = np.zeros(NP)
        prm[P_STATUS_TIMEOUT] = CLIENT_STATUS_TIMEOUT_S
        prm[P_LINK_TIMEOUT] = c.heartbeat_timeout_s
        prm[P_HB_TIMEOUT] = c.heartbeat_timeout_s
        prm[P_PERIOD] = PERIOD_S
        prm[P_RATED_V] = pack.charger.params.rated_v
        prm[P_RATED_A] = pack.charger.params.rated_a
        prm[P_DEF_V] = float(c.voltage_v)
        prm[P_DEF_A] = float(c.current_a)
        prm[P_DEF_EN] = 1.0 if c.enable else 0.0
        self.prm = prm
        self.fs = np.full((n, NF), math.nan)
        self.fs[:, F_REQ_V] = 0.0  # CHARGER_OFF
        self.fs[:, F_REQ_A] = 0.0
        self.st = np.zeros((n, NI), np.int64)

    def __bool__(self) -> bool:
        return self.n_packs > 0

    # ------------------------------------------------------------------ fault hooks
    @property
    def silenced(self) -> bool:
        """Every pack's link silenced (``can_silence``: nothing crosses either way)."""
        return bool(np.all(self.st[:, I_SILENCED] != 0))

    @silenced.setter
    def silenced(self, on: bool) -> None:
        self.st[:, I_SILENCED] = 1 if on else 0

    def silence(self, p: int, on: bool) -> None:
        """Silence (or restore) pack ``p``'s link only."""
        self.st[p, I_SILENCED] = 1 if on else 0

    # ------------------------------------------------------------------ the loop's face
    def poll(self, t_s: float, m: MeasArrays) -> None:
        """Latest status of every charger into ``m`` (offline once silent for the timeout)."""
        if not math.isfinite(t_s):
            raise ValueError(f"poll: simulation time must be finite, got {t_s}")
        ch = m.charger
        elcon_poll(
            self.prm, self.fs, self.st, float(t_s),
            ch.reported, ch.output_v, ch.output_a, ch.flags, ch.online,
        )  # fmt: skip

    def send(self, t_s: float, cmd: CmdArrays) -> None:
        """The merged setpoints (or the default) to every pack's dock over the modelled link."""
        if not math.isfinite(t_s):
            raise ValueError(f"poll: simulation time must be finite, got {t_s}")
        ch = self.pack.charger
        elcon_send(
            self.prm, self.fs, self.st, float(t_s),
            cmd.charger_set, cmd.charger_v, cmd.charger_a, cmd.charger_enable,
            ch.v_req, ch.i_req, ch.on_req, ch.last_request_s, ch.flags, ch.out_v, ch.out_a,
        )  # fmt: skip

    def close(self) -> None:
        pass

    # ------------------------------------------------------------------ inspection
    def counters(self, p: int = 0) -> dict[str, dict[str, int]]:
        """Pack ``p``'s frame counters, as ``client.counters`` / ``emulator.counters`` of a
        ``CanChargerLink`` (``FrameCounters`` fields)."""
        s = self.st[p]

        def node(sent: int, received: int, implausible: int = 0) -> dict[str, int]:
            return {
                "sent": sent,
                "received": received,
                "malformed": 0,
                "unexpected": 0,
                "send_errors": 0,
                "recv_errors": 0,
                "implausible": implausible,
            }

        return {
            "client": node(int(s[I_CL_SENT]), int(s[I_CL_RECV]), int(s[I_CL_IMPL])),
            "emulator": node(int(s[I_EM_SENT]), int(s[I_EM_RECV])),
        }

    def heartbeat_lost(self, t_s: float) -> NDArray[np.bool_]:
        """Per pack: the emulated charger saw no request for ``heartbeat_timeout_s``
        (``ChargerEmulator.heartbeat_lost``)."""
        fs = self.fs
        ref = np.where(np.isnan(fs[:, F_EM_REQ_T]), fs[:, F_EM_FIRST], fs[:, F_EM_REQ_T])
        with np.errstate(invalid="ignore"):
            out: NDArray[np.bool_] = ~np.isnan(ref) & (t_s - ref > self.prm[P_HB_TIMEOUT])
        return out


__all__ = ["ElconLinks", "decode_count", "elcon_poll", "elcon_send", "raw_count"]
