"""`detcal calibrate --levels`: ellipses per level in the written results document, from a
conformal and a version-1 thesis profile (the profiles of tests/app/conftest.py), and bad
levels refused with one line and exit status 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from app.cli.main import main
from calibrators.io import save_dump, save_nuscenes
from calibrators.profile import CalibrationProfile
from tests.app.cli.detcal_process import detcal

LEVEL_KEYS = {"semi_major", "semi_minor", "angle", "method", "group", "guarantee",
              "calibration_n"}


@pytest.fixture(scope="module")
def workdir(tmp_path_factory, dump_given, conformal_json, thesis_json) -> Path:
    path = tmp_path_factory.mktemp("levels")
    save_dump(path / "val.npz", dump_given)
    save_nuscenes(dump_given, path / "res.json")
    (path / "conformal.json").write_text(conformal_json)
    (path / "thesis.json").write_text(thesis_json)
    return path


@pytest.mark.parametrize("source", ["val.npz", "res.json"])
def test_cli_calibrate_writes_ellipses_per_level(workdir, dump_given, conformal_json, source):
    out = f"out-{source}.json"
    levels = (0.5, 0.8, 0.9, 0.95)   # groups of >= 30 points serve up to 30/31 at least
    result = detcal("calibrate", source, "--profile", "conformal.json", "--levels",
                    *map(str, levels), "--out", out, cwd=workdir)
    assert result.returncode == 0, result.stderr
    doc = json.loads((workdir / out).read_text())
    boxes = [b for frame in doc["results"].values() for b in frame]
    assert len(boxes) == dump_given.n_detections
    ref = CalibrationProfile.from_json(conformal_json).calibrate(
        layer_logits=dump_given.det_logits, boxes=dump_given.final_boxes,
        covariances=dump_given.det_cov, ego_xy=dump_given.ego_xy(dump_given.det_frame),
        levels=levels)
    np.testing.assert_allclose([b["detection_score"] for b in boxes], ref.scores)
    np.testing.assert_allclose([b["detection_score_raw"] for b in boxes], ref.scores_raw)
    np.testing.assert_allclose([b["covariance"] for b in boxes], ref.covariances)
    for j, box in enumerate(boxes):
        assert list(box["ellipses"]) == ["0.5", "0.8", "0.9", "0.95"]
        major = [e["semi_major"] for e in box["ellipses"].values()]
        assert major == sorted(major)
        for q, e in zip(levels, box["ellipses"].values(), strict=True):
            assert set(e) == LEVEL_KEYS and e["method"] == "conformal"
            assert e["group"] == ref.region_groups[j]
            assert e["semi_major"] == pytest.approx(ref.regions[q].semi_major[j])
            assert e["angle"] == pytest.approx(ref.regions[q].angle[j])


@pytest.mark.parametrize("levels", [(), ("0.5", "0.9", "0.95", "0.99")])
def test_cli_calibrate_version_1_profile_default_and_given_levels(workdir, levels):
    flags = ("--levels", *levels) if levels else ()
    result = detcal("calibrate", "val.npz", "--profile", "thesis.json", *flags, "--out",
                    "v1.json", cwd=workdir)
    assert result.returncode == 0, result.stderr
    doc = json.loads((workdir / "v1.json").read_text())
    keys = list(levels) or ["0.95"]
    for box in (b for frame in doc["results"].values() for b in frame):
        assert {"detection_score", "detection_score_raw", "covariance"} <= set(box)
        assert list(box["ellipses"]) == keys
        assert all(e["method"] == "gaussian" and e["group"] is None
                   for e in box["ellipses"].values())
        major = [e["semi_major"] for e in box["ellipses"].values()]
        assert major == sorted(major)


@pytest.mark.parametrize(("levels", "message"), [
    (["0"], "--levels[0] = 0.0 is not a level in (0, 1)"),
    (["0.5", "1"], "--levels[1] = 1.0"),
    (["nan"], "--levels[0] = nan"),
    (["-0.1"], "--levels[0] = -0.1"),
    (["abc"], "--levels must be numbers"),
    (["0.5", "0.5"], "--levels[1] = 0.5 repeats --levels[0]"),
    ([str(round(0.04 * k, 2)) for k in range(1, 22)], "--levels has 21 entries"),
])
def test_cli_bad_levels_exit_2_with_one_line(workdir, levels, message, capsys, monkeypatch):
    monkeypatch.chdir(workdir)   # the subprocess's handler code, run in-process
    assert main(["calibrate", "val.npz", "--profile", "conformal.json", "--levels", *levels,
                 "--out", "bad.json"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "error" in lines[0] and message in lines[0], lines
    assert not (workdir / "bad.json").exists()


def test_cli_bad_levels_exit_2_as_a_process(workdir):
    result = detcal("calibrate", "val.npz", "--profile", "conformal.json", "--levels", "1.5",
                    cwd=workdir)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "detcal calibrate: error: --levels[0] = 1.5 is not a level in (0, 1)"]
