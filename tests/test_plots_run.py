"""Run figures: the file is written in the asked format and the figure carries what it should."""

from __future__ import annotations

import base64
import math
import struct
from pathlib import Path

import numpy as np
import pytest

from packpilot.contract.bms import Event
from packpilot.contract.record import BATTERY_CHANNELS, Result, StepSample, Trace
from packpilot.errors import InputError
from packpilot.report.plots import figure_png_base64, plot_run, run_figure

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
CH = {c: i for i, c in enumerate(BATTERY_CHANNELS)}


def synthetic_result(n: int = 600, dt_s: float = 1.0, events: list[Event] | None = None) -> Result:
    """Two batteries discharging unequally into a load, a realistic-looking trace."""
    samples = []
    for k in range(n):
        t = k * dt_s
        bat = np.zeros((2, len(BATTERY_CHANNELS)))
        for b, (soc0, share) in enumerate(((0.9, 0.6), (0.7, 0.4))):
            soc = soc0 - 0.2 * k / n
            bat[b, CH["soc"]] = soc
            bat[b, CH["voltage_v"]] = 21.0 + 4.0 * soc
            bat[b, CH["current_a"]] = 20.0 * share
            bat[b, CH["temp_c"]] = 25.0 + 5.0 * (1 - math.exp(-k / 200)) * share
        samples.append(StepSample(k, t, 23.5, 20.0, 20.0, 0.0, 0.0, bat, np.full((2, 2), 3.7)))
    evs = events if events is not None else [
        Event(120.0, "ProtectionTripped", 1, "UV"),
        Event(120.0, "StageChanged", 0),
        Event(400.0, "Fault", None, "charger lost"),
    ]  # fmt: skip
    return Result(["left", "right"], Trace.from_samples(samples), evs, {}, run_id=7)


def png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG_MAGIC
    w, h = struct.unpack(">II", data[16:24])
    return int(w), int(h)


def test_plot_run_writes_plausible_png(tmp_path: Path) -> None:
    out = tmp_path / "run.png"
    plot_run(synthetic_result(), out)
    data = out.read_bytes()
    assert png_size(data) == (1200, 1080)
    assert 20_000 < len(data) < 2_000_000


def test_plot_run_svg_by_suffix(tmp_path: Path) -> None:
    out = tmp_path / "run.SVG"
    plot_run(synthetic_result(), out)
    text = out.read_text(encoding="utf-8")
    assert "<svg" in text[:2000] and len(text) > 10_000


def test_plot_run_rejects_unknown_suffix(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"run\.jpeg"):
        plot_run(synthetic_result(), tmp_path / "run.jpeg")


def test_figure_content() -> None:
    fig = run_figure(synthetic_result())
    axes = fig.get_axes()
    assert [a.get_ylabel().split("\n")[0] for a in axes] == [
        "voltage (V)",
        "current (A)",
        "SOC (%)",
        "temperature (°C)",
    ]
    assert axes[-1].get_xlabel() == "time (min)"  # 600 s spans more than 5 min
    legend = axes[0].get_legend()
    assert legend is not None
    assert [t.get_text() for t in legend.get_texts()] == ["left", "right", "bus"]
    # SOC is plotted in percent
    soc_line = axes[2].get_lines()[0]
    assert soc_line.get_ydata()[0] == pytest.approx(90.0)  # type: ignore[index]
    # three events -> three dotted lines on each panel, two labels (120 s events share one)
    for ax in axes:
        assert sum(1 for ln in ax.get_lines() if ln.get_linestyle() == ":") == 3
    labels = [t.get_text() for t in axes[0].texts]
    assert labels[1] == "Fault"
    # the two 120 s events share one label, shortened so it stays inside the panel
    assert labels[0].startswith("ProtectionTripped right, Stage") and labels[0].endswith("…")
    assert len(labels) == 2 and len(labels[0]) == 34
    names = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert names == ["ProtectionTripped (1)", "StageChanged (1)", "Fault (1)"]


def test_many_events_only_in_legend() -> None:
    evs = [Event(float(t), "StateChanged", t % 2) for t in range(0, 600, 10)]
    fig = run_figure(synthetic_result(events=evs))
    assert len(fig.get_axes()[0].texts) == 0
    assert [t.get_text() for leg in fig.legends for t in leg.get_texts()] == ["StateChanged (60)"]


def test_time_unit_follows_span() -> None:
    assert run_figure(synthetic_result(n=100)).get_axes()[-1].get_xlabel() == "time (s)"
    long = synthetic_result(n=100, dt_s=360.0)  # 10 h
    assert run_figure(long).get_axes()[-1].get_xlabel() == "time (h)"


def test_nan_channels_and_empty_runs_still_plot(tmp_path: Path) -> None:
    res = synthetic_result(n=50)
    res.trace.battery[:, 1, CH["temp_c"]] = np.nan  # a dead sensor
    res.trace.bus_v[:] = np.nan
    plot_run(res, tmp_path / "nan.png")
    assert png_size((tmp_path / "nan.png").read_bytes()) == (1200, 1080)
    empty = Result(
        ["a"],
        Trace(
            t_s=np.empty(0),
            bus_v=np.empty(0),
            load_demand_a=np.empty(0),
            load_a=np.empty(0),
            charger_v=np.empty(0),
            charger_a=np.empty(0),
            battery=np.empty((0, 1, len(BATTERY_CHANNELS))),
            group_v=np.empty((0, 1, 0)),
            status={},
        ),
        [],
        {},
    )
    plot_run(empty, tmp_path / "empty.png")
    assert (tmp_path / "empty.png").stat().st_size > 1000


def test_figure_png_base64() -> None:
    fig = run_figure(synthetic_result(n=30))
    text = figure_png_base64(fig, dpi=50)
    assert text.isascii()
    assert png_size(base64.b64decode(text)) == (500, 450)


def test_routine_balancing_updates_are_counted_not_drawn() -> None:
    """#29: the demo's 136 BalancingUpdated lines covered every panel in grey."""
    evs = [Event(float(t), "BalancingUpdated", 0) for t in range(0, 600, 5)]
    evs.append(Event(300.0, "ProtectionTripped", 1, "UV"))
    fig = run_figure(synthetic_result(events=evs))
    for ax in fig.get_axes()[:4]:
        assert sum(1 for ln in ax.get_lines() if ln.get_linestyle() == ":") == 1
    names = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert names == ["BalancingUpdated (120, not drawn)", "ProtectionTripped (1)"]


def test_voltage_panel_spans_the_batteries_when_the_bus_drops() -> None:
    """#29: demo.png ran from 0 to 25 V because the bus dropped to 0 V twice."""
    res = synthetic_result()
    res.trace.bus_v[100:120] = 0.0
    fig = run_figure(res)
    ax_v = fig.get_axes()[0]
    lo, hi = ax_v.get_ylim()
    volts = res.trace.channel("voltage_v")
    assert float(np.nanmin(volts)) - 0.5 < lo < float(np.nanmin(volts))
    assert float(np.nanmax(volts)) < hi < float(np.nanmax(volts)) + 0.5
    assert "bus off scale" in [t.get_text() for t in ax_v.get_legend().get_texts()]
