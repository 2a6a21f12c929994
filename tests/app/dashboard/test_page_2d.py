"""The dashboard of a 2-D profile: its panels drawn from the held-out report with the report's
own figures (scores, reliability per category, D-ECE over position, coverage per category ×
size with intervals, one held-out image with its boxes and regions), a report from before
these panels still renders, and a real headless Chromium shows the page (screenshot).

`DETCAL_UPDATE_SCREENSHOT=1` copies the screenshot to docs/dashboard_2d.png.
"""

from __future__ import annotations

import html
import json
import os
import re
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.dashboard.panels2d import MAX_CLASS_PANELS
from app.main import create_app
from app.settings import Settings
from app.store import Store
from calibrators.boxes2d import (
    Detections2D,
    Profile2D,
    fit_profile_2d,
    parse_instances,
    synthetic_coco,
)

CHROMIUM = os.environ.get("DETCAL_CHROMIUM", "/usr/bin/chromium")
DOC_SHOT = Path(__file__).resolve().parents[3] / "docs" / "dashboard_2d.png"


@pytest.fixture(scope="module")
def profile_2d() -> Profile2D:
    """A 2-D profile fit on 800 synthetic images, half of them held out for the report."""
    results, instances = synthetic_coco(800, seed=0)
    return fit_profile_2d(Detections2D.from_coco(results), parse_instances(instances),
                          holdout=0.5)


def page_of(settings: Settings, profile_json: str) -> str:
    """The dashboard's HTML with `profile_json` as the default profile's version 1."""
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile(settings.default_profile, profile_json)
    store.close()
    with TestClient(create_app(settings)) as c:
        r = c.get("/")
    assert r.status_code == 200
    return r.text


@pytest.fixture
def page(settings: Settings, profile_2d: Profile2D) -> Iterator[str]:
    yield page_of(settings, profile_2d.to_json())


def section(page: str, start: str, end: str = "<h3") -> str:
    body = page[page.index(start):]
    return body[:body.index(end, len(start))]


def test_every_panel_is_drawn_from_the_report(page, profile_2d):
    held = profile_2d.report["holdout"]
    assert "not yet available" not in page and "not drawn" not in page
    assert "2-D boxes" in page and f"{profile_2d.score_method}" in page
    for label in ("Reliability (all categories)", "Reliability per class",
                  "Calibration over the image position", "Held-out image"):
        assert f'aria-label="{label}' in page, label
    scores = section(page, "<table class='scores-2d'>", "</table>")
    assert f"{held['ece']['raw']:.4g}" in scores and f"{held['d_ece']['calibrated']:.4g}" in scores
    per_class = section(page, 'aria-label="Reliability per class"', "</svg>")
    assert per_class.count(" TPs)<") == min(len(held["per_class"]), MAX_CLASS_PANELS)


def test_the_coverage_table_prints_the_reports_figures(page, profile_2d):
    table = profile_2d.report["holdout"]["regions"]["per_class_size"]
    body = section(page, "<table class='coverage coverage-2d'>", "</table>")
    printed = re.findall(r"<tr><td>(?:<b>)?([^<]+)(?:</b>)?</td><td>([^<]*)</td><td>(\d+)</td>"
                         r"((?:<td class='[^']*'>.*?</td>){4})", body)
    assert len(printed) == len(table["rows"]) + 1
    for (name, size, count, cells), row in zip(printed, [table["overall"], *table["rows"]],
                                               strict=True):
        assert int(count) == row["count"]
        assert name == row.get("class", "all")
        lo, hi = row.get("size_range", (None, None))
        assert size == ("" if lo is None else f"{lo:g}+ px" if hi is None
                        else f"{lo:g}–{hi:g} px")
        shares = re.findall(r"<td class='([^']*)'>([\d.]+) <span class='ci'>\[([\d.]+), "
                            r"([\d.]+)\]</span></td>", cells)
        assert len(shares) == 4
        for (cls, value, lo, hi), cov, (a, b) in zip(shares, row["coverage"], row["interval"],
                                                   strict=True):
            assert value == f"{cov:.3g}" and (lo, hi) == (f"{a:.2f}", f"{b:.2f}")
            assert (cls == "small") == (row["count"] < 30)      # grey: too few to judge
    assert "pooled" in body or "cell" in body


def test_the_heat_map_and_the_image_hold_the_reports_figures(page, profile_2d):
    held = profile_2d.report["holdout"]
    cells = re.findall(r'<rect class="cell" data-part="(\w+)" data-row="(\d)" data-col="(\d)" '
                       r'data-value="([^"]*)"', page)
    pos = held["position"]
    assert len(cells) == 2 * len(pos["count"]) ** 2
    for part, r, c, value in cells:
        want = pos[f"d_ece_{part}"][int(r)][int(c)]
        assert (value == "" and want is None) or float(value) == want
    sample = held["sample"]
    canvas = section(page, 'aria-label="Held-out image', "</svg>")
    assert f'viewBox="0 0 {sample["width"]:g} {sample["height"]:g}"' in canvas
    assert canvas.count('<g class="det"') == len(sample["detections"])
    assert canvas.count('class="truth"') == len(sample["truth"])
    assert canvas.count('class="band"') == sum(d["outer"] is not None
                                               for d in sample["detections"])
    for d in sample["detections"]:
        assert html.escape(f"{d['category']} {d['score']:.2f}") in canvas


def test_an_old_report_without_the_panel_data_still_renders(settings, profile_2d):
    data = json.loads(profile_2d.to_json())
    held = data["report"]["holdout"]
    for key in ("reliability", "position", "sample"):
        del held[key]
    del held["regions"]["per_class_size"]
    page = page_of(settings, json.dumps(data))
    assert page.count("not drawn") == 4
    for what in ("reliability diagrams", "calibration over position",
                 "coverage per category × size", "sample image"):
        assert f"has no {what}" in page
    assert "<table class='scores-2d'>" in page and 'class="plot' not in page


def test_a_profile_without_held_out_images_says_so(settings):
    results, instances = synthetic_coco(200, seed=3)
    profile = fit_profile_2d(Detections2D.from_coco(results), parse_instances(instances))
    page = page_of(settings, profile.to_json())
    assert "no held-out report" in page and "2-D boxes" in page


@pytest.mark.e2e
def test_chromium_shows_the_2d_panels(page, tmp_path):
    """The page in a real headless Chromium: no script or console error, every figure laid
    out, no two labels of the image overlapping; the screenshot for the docs."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"{CHROMIUM} is absent: `apt-get install -y chromium`")
    from playwright.sync_api import sync_playwright

    shot = tmp_path / "dashboard_2d.png"
    errors: list[str] = []
    boxes = ("els => els.map(e => {const r = e.getBoundingClientRect(); "
             "return [r.x, r.y, r.width, r.height]})")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM,
                                    args=["--no-sandbox", "--disable-gpu"])
        tab = browser.new_page(viewport={"width": 1400, "height": 1000})
        tab.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        tab.on("pageerror", lambda e: errors.append(str(e)))
        tab.set_content(page, wait_until="load")
        figures = tab.eval_on_selector_all("#report svg.plot", boxes)
        labels = tab.eval_on_selector_all("svg.image2d text.label", boxes)
        cells = tab.eval_on_selector_all("rect.cell", boxes)
        tab.locator("#report").screenshot(path=str(shot))
        browser.close()
    assert not errors, errors
    assert len(figures) == 4 and all(w > 200 and h > 150 for _, _, w, h in figures), figures
    assert len(cells) == 50 and all(w > 20 and h > 15 for _, _, w, h in cells)
    assert labels and all(w > 10 for _, _, w, _ in labels)
    for i, a in enumerate(labels):
        for b in labels[i + 1:]:
            assert not (a[0] < b[0] + b[2] and b[0] < a[0] + a[2] and a[1] < b[1] + b[3]
                        and b[1] < a[1] + a[3]), (a, b)
    assert shot.stat().st_size > 10_000
    if os.environ.get("DETCAL_UPDATE_SCREENSHOT"):
        shutil.copyfile(shot, DOC_SHOT)
