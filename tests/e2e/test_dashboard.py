"""The dashboard rendered by a real headless Chromium (Debian's /usr/bin/chromium).

Playwright drives the browser when it can launch it (console errors are collected); otherwise
the browser's own `--dump-dom` and `--screenshot` are used.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.e2e

CHROMIUM = os.environ.get("DETCAL_CHROMIUM", "/usr/bin/chromium")
DOC_SHOT = Path(__file__).resolve().parents[2] / "docs" / "dashboard.png"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage"]

if not Path(CHROMIUM).exists():
    pytest.skip(f"{CHROMIUM} is absent: `apt-get install -y chromium` (make test does)",
                allow_module_level=True)


def _playwright_page(url: str, shot: Path) -> tuple[str, list[str]] | None:
    """DOM and console errors via Playwright, or None if it cannot drive this Chromium."""
    try:
        from playwright.sync_api import Error, sync_playwright
    except ImportError:
        return None
    errors: list[str] = []
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS[1:])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto(url, wait_until="load")
            page.wait_for_selector("svg.plot")
            page.screenshot(path=str(shot), full_page=True)
            dom = page.content()
            browser.close()
    except Error:
        return None
    return dom, errors


def _cli_page(url: str, shot: Path, profile_dir: Path) -> tuple[str, list[str]]:
    """DOM via --dump-dom, screenshot via --screenshot; console errors from the log."""
    base = [CHROMIUM, *FLAGS, f"--user-data-dir={profile_dir}", "--enable-logging=stderr",
            "--v=0"]
    dom = subprocess.run([*base, "--dump-dom", url], capture_output=True, text=True,
                         timeout=120)
    subprocess.run([*base, "--window-size=1400,2600", f"--screenshot={shot}", url],
                   capture_output=True, text=True, timeout=120)
    errors = re.findall(r"CONSOLE\(\d+\)\].*", dom.stderr)
    errors += [line for line in dom.stderr.splitlines() if "Uncaught" in line]
    return dom.stdout, errors


def test_dashboard_renders_plots_without_console_errors(server, http, fitted, tmp_path):
    http.get("/healthz")
    shot = tmp_path / "dashboard.png"
    got = _playwright_page(server.url + "/", shot)
    if got is None:
        got = _cli_page(server.url + "/", shot, tmp_path / "chromium-profile")
    dom, errors = got
    assert not errors, errors
    for section in ("health", "requests", "profiles", "active", "report", "bev", "jobs"):
        assert f'id="{section}"' in dom, section
    assert "lidar@1" in dom
    plots = re.findall(r"<svg[^>]*class=\"plot\"", dom)
    assert len(plots) >= 4, len(plots)               # reliability, curves, residuals, per class
    for label in ("Reliability (all classes)", "Average calibration curves", "Residual plot",
                  "Reliability per class"):
        assert f'aria-label="{label}"' in dom, label
    assert "Served ellipses: coverage per class × range" in dom   # the served levels hold?
    assert re.search(r"<th>50%</th><th>90%</th><th>95%</th><th>99%</th>", dom)
    assert not re.search(r"""(src|href)=["']?(https?:)?//""", dom)   # offline: nothing fetched
    assert shot.exists() and shot.stat().st_size > 10_000
    if os.environ.get("DETCAL_UPDATE_SCREENSHOT"):
        shutil.copyfile(shot, DOC_SHOT)
