"""The report's CAN section from a real BLF written by the project's FrameLog and read back with
python-can: frames per id, rate, the longest silence, rejected and error frames."""

from __future__ import annotations

import re
from pathlib import Path

import can

from packpilot.contract.charger import ChargerCommand, ChargerStatus
from packpilot.io.can.bus import FrameLog
from packpilot.io.can.codec import STATUS_ID, encode_request, encode_status
from packpilot.report.html import RunInfo, build_html
from tests.test_report_html import section, synthetic


def write_log(path: Path) -> None:
    """1 Hz requests over 0..99 s with a silence from 40 to 60 s; 1 Hz status replies; one
    status frame too short to decode; one error frame."""
    with FrameLog(path) as log:
        for t in range(100):
            if not 40 < t < 60:
                log.log(encode_request(ChargerCommand(25.2, 5.0, enable=True)), t, rx=False)
            log.log(encode_status(25.0, 4.9, ChargerStatus(25.0, 4.9)), t + 0.5, rx=True)
        log.log(can.Message(arbitration_id=STATUS_ID, data=b"\x00\x01", is_extended_id=True),
                100.0, rx=True)  # fmt: skip
        log.log(can.Message(is_error_frame=True), 101.0, rx=True)


def test_can_section_counts_rates_silence_and_rejects(tmp_path: Path) -> None:
    blf = tmp_path / "run.blf"
    write_log(blf)
    page = build_html(synthetic(50), RunInfo(status="ok", can_log=str(blf)))
    can_html = section(page, "can")
    rows = re.findall(r"<tr><td>(0x[0-9A-F]+)</td>(.*?)</tr>", can_html)
    by_id = {ident: re.findall(r"<td>(.*?)</td>", rest) for ident, rest in rows}
    req, st = by_id["0x1806E5F4"], by_id["0x18FF50E5"]
    assert req[1] == "81" and req[2] == "81 / 0"  # 100 s minus the 19 silent ones, all sent
    assert st[1] == "101" and st[2] == "0 / 101" and st[-1] == "1"  # one rejected
    assert req[5].startswith("20 s from 40 s")  # the longest silence, and when
    assert req[4] == "1"  # median period
    assert "<td>error frames</td><td>1</td>" in can_html
    assert 'data-chart="can-rate"' in can_html


def test_no_log_no_section_and_a_missing_log_is_said(tmp_path: Path) -> None:
    assert '<section id="can">' not in build_html(synthetic(10), RunInfo(status="ok"))
    page = build_html(synthetic(10), RunInfo(status="ok", can_log=str(tmp_path / "gone.blf")))
    assert "was not found" in section(page, "can")
