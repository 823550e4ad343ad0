"""A charger status reporting more than the configured charger can deliver is rejected and
counted (issue #18 §3: 116 of 5,000 random status frames were accepted as readings of up to
6,468 V / 6,553 A). One check (``contract/charger.py:status_in_range``) serves the python-can
client and the compiled link model."""

from __future__ import annotations

import itertools
from collections.abc import Iterator

import can
import numpy as np
import pytest

from packpilot.contract.charger import status_in_range
from packpilot.io.can import ChargerClient, encode_status, open_bus

_channels = itertools.count()


@pytest.fixture
def pair() -> Iterator[tuple[can.BusABC, can.BusABC]]:
    channel = f"test-range-{next(_channels)}"
    nodes = [open_bus("virtual", channel) for _ in range(2)]
    yield nodes[0], nodes[1]
    for b in nodes:
        b.shutdown()


@pytest.mark.parametrize(
    ("v", "a", "ok"),
    [(60.0, 20.0, True), (66.0, 22.0, True), (0.0, 0.0, True), (6468.0, 1.0, False),
     (50.0, 6553.0, False), (66.1, 1.0, False), (1.0, 22.1, False), (-1.0, 1.0, False)],
)  # fmt: skip
def test_the_range_is_the_rating_plus_ten_percent(v: float, a: float, ok: bool) -> None:
    assert status_in_range(v, a, 60.0, 20.0) is ok


def test_the_client_rejects_an_absurd_status(pair: tuple[can.BusABC, can.BusABC]) -> None:
    bms, charger = pair
    client = ChargerClient(bms, rating=(60.0, 20.0))
    charger.send(encode_status(6468.0, 6553.0, {}))
    assert client.poll(0.0) is None  # nothing plausible arrived
    assert client.counters.implausible == 1 and client.counters.received == 0
    charger.send(encode_status(50.0, 5.0, {}))
    status = client.poll(0.1)
    assert status is not None and status.output_v == 50.0 and status.output_a == 5.0
    charger.send(encode_status(50.0, 6553.0, {}))
    status = client.poll(0.2)  # the last plausible status stands
    assert status is not None and status.output_a == 5.0
    assert client.counters.implausible == 2 and client.counters.received == 1


def test_the_compiled_link_model_rejects_it_too() -> None:
    """``elcon_poll`` reads a queued status through the same check."""
    from packpilot.sim import elcon as m

    prm = np.zeros(m.NP)
    prm[m.P_STATUS_TIMEOUT] = prm[m.P_LINK_TIMEOUT] = 5.0
    prm[m.P_RATED_V], prm[m.P_RATED_A] = 60.0, 20.0
    fs = np.full((1, m.NF), np.nan)
    st = np.zeros((1, m.NI), np.int64)
    st[0, m.I_PEND], st[0, m.I_PEND_V], st[0, m.I_PEND_A] = 1, 64_680, 65_530
    out = (np.zeros(1, np.bool_), np.zeros(1), np.zeros(1), np.zeros((1, 5), np.bool_))
    m.elcon_poll(prm, fs, st, 0.0, out[0], out[1], out[2], out[3], np.zeros(1, np.bool_))
    assert st[0, m.I_CL_IMPL] == 1 and st[0, m.I_CL_RECV] == 0 and not out[0][0]
    st[0, m.I_PEND], st[0, m.I_PEND_V], st[0, m.I_PEND_A] = 1, 500, 50
    m.elcon_poll(prm, fs, st, 0.1, out[0], out[1], out[2], out[3], np.zeros(1, np.bool_))
    assert st[0, m.I_CL_RECV] == 1 and out[0][0] and out[1][0] == 50.0 and out[2][0] == 5.0
