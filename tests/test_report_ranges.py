"""The report's chart ranges (#29): the battery voltage chart spans the batteries even when the
bus drops to 0 V (the drops shaded and named), and the CAN rate chart shows a steady 1 Hz
message as a steady line, not a band between 0 and 2 frames per bin."""

from __future__ import annotations

import base64
import zlib

import numpy as np
import pytest

from packpilot.report import sections as S
from packpilot.report.can_log import CanLogStats, IdStats, _rate_chart, rate_window_s
from packpilot.report.charts import Chart, Store


def test_voltage_axis_spans_the_batteries_and_marks_the_bus_drops() -> None:
    t = np.arange(0.0, 1000.0, 0.5)
    a = 25.2 - 4.4 * t / 1000.0
    b = a - 0.3
    bus = a - 0.05
    bus[(t >= 300) & (t < 320)] = 0.0  # the bus dropped twice
    bus[(t >= 700) & (t < 701)] = 0.0
    chart = Chart("voltage", "Battery voltage and bus (V)", "V")
    cap = S._range_on_batteries(chart, t, np.stack([a, b], 1), bus)
    assert chart.y_range is not None
    lo, hi = chart.y_range
    assert 20.0 < lo < float(b.min()) and float(a.max()) < hi < 25.6  # not from 0 V
    assert [(round(x), round(y)) for x, y, _ in chart.bands] == [(300, 320), (700, 701)]
    assert "0:05:00.0–0:05:20.0" in cap and "down to 0.0 V" in cap
    # a bus that stays on the batteries' scale marks nothing
    quiet = Chart("v2", "x", "V")
    assert S._range_on_batteries(quiet, t, np.stack([a, b], 1), a - 0.05) == ""
    assert quiet.bands == [] and quiet.y_range == chart.y_range


def test_can_rate_of_a_1_hz_message_is_a_steady_line() -> None:
    rng = np.random.default_rng(1)
    stats = CanLogStats(path=None)  # type: ignore[arg-type]
    for ident, phase in ((0x100, 0.0), (0x101, 0.5)):
        s = IdStats(ident, False, f"id{ident:x}")
        s.times = list(np.arange(0.0, 3600.0, 1.0) + phase + rng.normal(0, 0.01, 3600))
        stats.ids[ident] = s
    store = Store(np.arange(1, dtype=np.intp))
    chart = _rate_chart(stats, store)
    assert chart.title.endswith(f"(mean over the last {rate_window_s(3600.0):g} s)")
    for series in chart.series:
        rec = store.data[series.key]
        # decode the stored series as report.js does: deltas of q-quanta
        d = np.frombuffer(zlib.decompress(base64.b64decode(rec["z"])), "<i4")
        y = np.cumsum(d) * rec["q"]
        assert y.size > 100 and np.abs(y - 1.0).max() <= 0.1 + 1e-9, (y.min(), y.max())
    assert chart.series[1].dash and not chart.series[0].dash  # equal lines both visible


@pytest.mark.parametrize("span", [60.0, 5400.0, 36000.0])
def test_rate_window_is_whole_seconds_and_at_least_10(span: float) -> None:
    w = rate_window_s(span)
    assert w >= 10 and w == int(w) and w >= span / 300
