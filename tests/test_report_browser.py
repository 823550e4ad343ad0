"""The HTML report in a real headless Chromium with no network: every section, every image.

Chromium comes from Debian (``make browser``, which ``make test`` runs first). Networking is
cut twice over: a proxy that does not exist and a host resolver that resolves nothing, so an
image that needed the network would fail to decode and the marker would say so.
"""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from packpilot.report.html import SECTION_IDS

CHROMIUM = Path("/usr/bin/chromium")
ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "examples"

pytestmark = pytest.mark.skipif(
    not CHROMIUM.exists(),
    reason="headless Chromium not installed at /usr/bin/chromium (run `make browser`)",
)

RICH_PROTECTION = """
[protection]
parameters = [
  { name = "P1", cutoff_v = 4.0, t_max_s = 4.0 },
  { name = "P2", cutoff_v = 3.9, t_max_s = 6.0 },
  { name = "P3", cutoff_v = 3.8, t_max_s = 8.0 },
]
"""


def chromium(profile: Path, *args: str) -> subprocess.CompletedProcess[str]:
    cmd = [
        str(CHROMIUM),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--proxy-server=http://127.0.0.1:9",  # nothing listens there: no network at all
        "--host-resolver-rules=MAP * ~NOTFOUND",
        f"--user-data-dir={profile}",
        "--virtual-time-budget=5000",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A recorded run with events, protection and sequencing, reported by the CLI."""
    tmp = tmp_path_factory.mktemp("browser")
    text = (EXAMPLES / "sequencing_dual_hover.toml").read_text(encoding="utf-8")
    cfg = tmp / "rich.toml"
    cfg.write_text(
        text.replace('controller = ["sequencing"]', 'controller = ["protection", "sequencing"]')
        + RICH_PROTECTION,
        encoding="utf-8",
    )
    db, out = tmp / "run.sqlite", tmp / "report.html"
    env = {**os.environ, "PYBAMM_DISABLE_TELEMETRY": "true", "MPLBACKEND": "Agg"}
    for args in (
        ["simulate", str(cfg), "--duration", "30", "--db", str(db), "--no-progress", "--json"],
        ["report", str(db), "--out", str(out)],
    ):
        r = subprocess.run(
            [sys.executable, "-m", "packpilot.cli", *args],
            capture_output=True,
            text=True,
            timeout=180,
            env=env,
            cwd=ROOT,
        )
        assert r.returncode == 0, r.stderr
    return out


def test_every_section_renders_and_every_image_decodes(report: Path, tmp_path: Path) -> None:
    n_img = report.read_text(encoding="utf-8").count("<img ")
    assert n_img >= 5
    r = chromium(tmp_path / "profile", "--dump-dom", report.resolve().as_uri())
    assert r.returncode == 0, r.stderr[-2000:]
    dom = r.stdout
    for sid in SECTION_IDS:
        assert re.search(rf'<section id="{sid}">\s*<h2>', dom), sid
    m = re.search(r'data-images-ok="(\d+)/(\d+)"', dom)
    assert m, "the load marker never ran (page did not finish loading?)"
    assert (int(m.group(1)), int(m.group(2))) == (n_img, n_img)
    assert "ProtectionTripped" in dom and "Parallel discharge sequencing" in dom


def test_screenshot_has_the_page(report: Path, tmp_path: Path) -> None:
    shot = tmp_path / "report.png"
    r = chromium(
        tmp_path / "profile",
        f"--screenshot={shot}",
        "--window-size=1280,4000",
        "--hide-scrollbars",
        report.resolve().as_uri(),
    )
    assert r.returncode == 0, r.stderr[-2000:]
    raw = shot.read_bytes()
    assert raw[:8] == b"\x89PNG\r\n\x1a\n"
    assert struct.unpack(">II", raw[16:24]) == (1280, 4000)
    assert len(raw) > 100_000  # a page of plots and tables, not a blank canvas
