"""`detcal calibrate` keeps every detection's identity: any permutation of an NPZ dump's
detections and frames, of a Parquet dataset's, or of a results document's tokens and boxes,
gives every detection the same served values (issue 27: the dump path paired a frame-grouped
document with the dump's arrays by position and wrote scores onto the wrong boxes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings

from app.cli.main import main
from calibrators import apply_profile
from calibrators.io import save_dump, save_nuscenes, save_parquet
from calibrators.profile import CalibrationProfile
from tests.identity_cases import (
    CASES,
    assert_same_boxes,
    awkward,
    document_by_row,
    document_values,
    permuted_document,
    shuffled,
)

SETTINGS = settings(max_examples=6, deadline=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture])
LEVELS = ["--levels", "0.5", "0.9"]


@pytest.fixture(scope="module")
def profile_file(tmp_path_factory, profile_json_given) -> Path:
    path = tmp_path_factory.mktemp("identity") / "profile.json"
    path.write_text(profile_json_given)
    return path


@pytest.fixture(scope="module")
def base(dump_given):
    """The first 8 frames of the conftest dump (quick to calibrate)."""
    keep = np.zeros(dump_given.n_frames, dtype=bool)
    keep[:8] = True
    return dump_given.select_frames(keep)


def _calibrate(src: Path, profile: Path, out: Path, *extra: str) -> dict:
    assert main(["calibrate", str(src), "--profile", str(profile), *LEVELS, "--out", str(out),
                 *extra]) == 0
    return json.loads(out.read_text())


def test_a_grouped_dump_is_served_what_the_library_computes(tmp_path, base, profile_file,
                                                           capsys):
    save_dump(tmp_path / "d.npz", base)
    doc = _calibrate(tmp_path / "d.npz", profile_file, tmp_path / "out.json")
    ref = apply_profile(base, CalibrationProfile.from_json(profile_file.read_text()),
                        levels=[0.5, 0.9])
    boxes = {b["detection_row"]: b for frame in doc["results"].values() for b in frame}
    assert sorted(boxes) == list(range(base.n_detections))
    for i, box in boxes.items():
        assert box["sample_token"] == str(base.frame_ids[base.det_frame[i]])
        assert box["detection_score"] == ref.scores[i]
        assert box["detection_score_raw"] == ref.scores_raw[i]
        assert box["covariance"] == ref.covariances[i].tolist()
        assert box["ellipses"]["0.9"]["semi_major"] == ref.regions[0.9].semi_major[i]
    summary = capsys.readouterr().err.strip()
    assert summary.startswith(f"detcal calibrate: {base.n_detections} detections in "
                              f"{base.n_frames} frames") and str(tmp_path / "out.json") in summary


@SETTINGS
@given(case=CASES)
def test_npz_permuted_serves_every_detection_the_same(tmp_path, base, profile_file, case):
    dump = awkward(base, case)
    moved, perm = shuffled(dump, case["seed"])
    save_dump(tmp_path / "a.npz", dump)
    save_dump(tmp_path / "b.npz", moved)
    doc_a = _calibrate(tmp_path / "a.npz", profile_file, tmp_path / "a.json")
    doc_b = _calibrate(tmp_path / "b.npz", profile_file, tmp_path / "b.json")
    assert document_values(doc_a) == document_values(doc_b)   # every box, its own values
    a, b = document_by_row(doc_a), document_by_row(doc_b)
    assert len(b) == moved.n_detections
    assert all(b[j] == a[int(perm[j])] for j in range(len(perm)))


@SETTINGS
@given(case=CASES)
def test_parquet_permuted_serves_every_detection_the_same(tmp_path, base, profile_file, case):
    dump = awkward(base, case)
    moved, perm = shuffled(dump, case["seed"])
    for name, d in (("a", dump), ("b", moved)):
        out = tmp_path / name
        if out.exists():
            import shutil

            shutil.rmtree(out)
        save_parquet(out, d, rows_per_part=50)
    a = _calibrate(tmp_path / "a", profile_file, tmp_path / "a.json")
    b = _calibrate(tmp_path / "b", profile_file, tmp_path / "b.json")
    # a Parquet dataset stores whole frames in its own row order: each box (token, centre,
    # size, logits) must carry the values it is served in the unpermuted dataset
    assert document_values(a) == document_values(b)
    assert sum(map(len, b["results"].values())) == moved.n_detections


@SETTINGS
@given(case=CASES)
def test_results_document_permuted_serves_every_box_the_same(tmp_path, base, profile_file,
                                                              case):
    save_nuscenes(awkward(base, case), tmp_path / "a.json")
    doc = json.loads((tmp_path / "a.json").read_text())
    moved, order = permuted_document(doc, case["seed"])
    (tmp_path / "b.json").write_text(json.dumps(moved))
    a = _calibrate(tmp_path / "a.json", profile_file, tmp_path / "a.out.json")
    b = _calibrate(tmp_path / "b.json", profile_file, tmp_path / "b.out.json")
    assert list(b["results"]) == list(moved["results"])       # every token, empty ones too
    assert_same_boxes(a, b, order)
