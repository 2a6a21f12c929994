"""/docs and /redoc render in a real headless Chromium with every non-loopback request refused:
Swagger UI and ReDoc come from the installed package, never from a CDN."""

from __future__ import annotations

import os
from pathlib import Path
from urllib.parse import urlparse

import pytest

pytestmark = pytest.mark.e2e

CHROMIUM = os.environ.get("DETCAL_CHROMIUM", "/usr/bin/chromium")
FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage"]

if not Path(CHROMIUM).exists():
    pytest.skip(f"{CHROMIUM} is absent: `apt-get install -y chromium` (make test does)",
                allow_module_level=True)
sync_api = pytest.importorskip("playwright.sync_api")


def _render(url: str, selector: str, shot: Path) -> tuple[str, list[str], list[str]]:
    """The page's text once `selector` shows, the refused requests ("type url"), page
    errors."""
    refused: list[str] = []
    errors: list[str] = []

    def offline(route) -> None:
        host = urlparse(route.request.url).hostname
        if host in ("127.0.0.1", "localhost"):
            route.continue_()
        else:
            refused.append(f"{route.request.resource_type} {route.request.url}")
            route.abort("internetdisconnected")

    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=FLAGS)
        page = browser.new_page(viewport={"width": 1300, "height": 900})
        page.route("**/*", offline)
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(url, wait_until="load")
        page.wait_for_selector(selector, timeout=30_000)
        page.screenshot(path=str(shot))
        text = page.inner_text("body")
        browser.close()
    return text, refused, errors


def test_swagger_ui_renders_the_operations_offline(server, tmp_path):
    text, refused, errors = _render(server.url + "/docs", ".opblock-summary-path",
                                    tmp_path / "docs.png")
    assert not errors, errors
    for path in ("/v1/calibrate", "/v1/fit", "/v1/jobs/{job_id}", "/healthz"):
        assert path in text, path
    assert not refused, refused          # nothing asked of the internet
    assert (tmp_path / "docs.png").stat().st_size > 10_000


def test_redoc_renders_the_operations_offline(server, tmp_path):
    text, refused, errors = _render(server.url + "/redoc", "[data-section-id^='operation/']",
                                    tmp_path / "redoc.png")
    assert not errors, errors
    for path in ("/v1/calibrate", "/v1/fit", "/v1/jobs/{job_id}"):
        assert path in text.replace("\u200b", ""), path
    # ReDoc's footer asks for its own logo from its CDN and drops the image when that fails;
    # nothing the page needs (script, style, font, the schema) comes from outside.
    assert all(r.startswith("image ") for r in refused), refused
