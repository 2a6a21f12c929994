"""docs/architecture.md names only modules and folders that exist, and its calibrate-path
figures are the limits tests/app/test_calibrate_path.py holds."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")


def test_every_path_the_page_names_exists():
    paths = set(re.findall(r"`((?:app|calibrators|detectors|tests)/[\w/.]*)`", PAGE))
    assert len(paths) > 30
    missing = sorted(p for p in paths if not (ROOT / p).exists())
    assert missing == []


def test_every_module_of_a_folder_row_exists():
    """In the tree table, each `name` in a folder's row is a module of that folder."""
    missing = []
    for folder, cell in re.findall(r"^\| `((?:app|calibrators)/[\w/]+)/` \| (.*) \|$", PAGE, re.M):
        for name in re.findall(r"`(_?[a-z][\w]*)\*?`", cell):
            stem = name.rstrip("*")
            if not list((ROOT / folder).glob(f"{stem}*.py")):
                missing.append(f"{folder}/{stem}")
    assert missing == []


def test_the_limits_match_the_test_that_measures_them():
    source = (ROOT / "tests" / "app" / "test_calibrate_path.py").read_text(encoding="utf-8")
    modules = int(re.search(r"^MAX_MODULES = (\d+)", source, re.M).group(1))
    packages = int(re.search(r"^MAX_PACKAGES = (\d+)", source, re.M).group(1))
    assert f"above {modules} modules or {packages} packages" in PAGE
