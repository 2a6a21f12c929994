"""Issue 25, item 2: per-request limits on feedback and fit uploads (refused from the NPZ's
headers before anything is inflated), and degenerate feedback (zero-size boxes, no true
positive at all) refused whole, so it never touches a version's health."""

from __future__ import annotations

import time

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from calibrators.data import synthetic_dump
from tests.app.conftest import ADMIN
from tests.app.feedback_frames import feedback_frames, npz_bytes
from tests.zeros_npz import zeros_npz

FB, HEALTH = "/v1/feedback", "/v1/profiles/lidar/health"


@pytest.fixture(scope="module")
def bomb() -> bytes:
    """6.5M detections of zeros, under 1 MiB (942 MiB inflated: under 1 GiB)."""
    return zeros_npz(6_500_000)


@pytest.fixture(scope="module")
def labelled():
    return synthetic_dump(n_frames=24, seed=11)


def _frames_total(client: TestClient) -> int:
    return client.get(HEALTH).json()["window"]["frames"]


def test_the_65m_detection_zeros_upload_is_413_before_it_inflates(client, bomb):
    assert len(bomb) < 2**20
    start = time.monotonic()
    r = client.post(FB, headers=ADMIN, files={"dump": ("fb.npz", bomb)})
    took = time.monotonic() - start
    assert r.status_code == 413, r.text
    print(f"413 in {took:.3f} s")
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "dump"]
    assert "DETCAL_MAX_DUMP_BYTES" in detail["msg"] or "DETCAL_MAX_FEEDBACK" in detail["msg"]
    assert _frames_total(client) == 0


def test_the_detection_limit_holds_below_the_byte_limit(seeded: Settings, labelled):
    small = seeded.model_copy(update={"max_feedback_detections": 50})
    with TestClient(create_app(small)) as client:
        r = client.post(FB, headers=ADMIN, files={"dump": ("fb.npz", npz_bytes(labelled))})
        assert r.status_code == 413, r.text
        assert "DETCAL_MAX_FEEDBACK_DETECTIONS" in r.json()["detail"][0]["msg"]
        r = client.post(FB, headers=ADMIN, json={"frames": feedback_frames(labelled)})
        assert r.status_code == 413, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "frames"]
        one = feedback_frames(labelled)[:1]
        assert client.post(FB, headers=ADMIN, json={"frames": one}).status_code == 200


def test_a_fit_upload_over_the_limit_is_413_and_queues_nothing(seeded: Settings, bomb):
    with TestClient(create_app(seeded)) as client:
        start = time.monotonic()
        r = client.post("/v1/fit", headers=ADMIN, files={"dump": ("v.npz", bomb)})
        assert r.status_code == 413 and time.monotonic() - start < 1.0, r.text
        assert client.get("/v1/jobs", headers=ADMIN).json() == []
    small = seeded.model_copy(update={"max_fit_detections": 10})
    with TestClient(create_app(small)) as client:
        r = client.post("/v1/fit", headers=ADMIN,
                        files={"dump": ("v.npz", npz_bytes(synthetic_dump(n_frames=3)))})
        assert r.status_code == 413, r.text
        assert "DETCAL_MAX_FIT_DETECTIONS" in r.json()["detail"][0]["msg"]


def test_zero_size_boxes_are_refused_and_not_recorded(client):
    r = client.post(FB, headers=ADMIN, files={"dump": ("fb.npz", zeros_npz(2000, n_frames=40))})
    assert r.status_code == 422, r.text
    assert "zero size" in r.json()["detail"][0]["msg"]
    assert _frames_total(client) == 0


def test_feedback_without_a_single_true_positive_is_refused(client, labelled):
    frames = feedback_frames(labelled)
    for frame in frames:   # every ground-truth box moved 50 m away: nothing matches
        for gt in frame["ground_truth"]:
            gt["box"][0] += 50.0
    for _ in range(3):
        r = client.post(FB, headers=ADMIN, json={"frames": frames})
        assert r.status_code == 422, r.text
        assert "no true positive" in r.json()["detail"][0]["msg"]
    doc = client.get(HEALTH).json()
    assert doc["window"]["frames"] == 0 and doc["status"] == "insufficient"
    r = client.post(FB, headers=ADMIN, json={"frames": feedback_frames(labelled)})
    assert r.status_code == 200 and r.json()["status"] == "ok", r.text


def test_frames_without_ground_truth_are_still_evidence(client, labelled):
    """Only the pairing of detections and ground truth with no match at all is refused."""
    frames = feedback_frames(labelled)
    for frame in frames:
        frame["ground_truth"] = []
    r = client.post(FB, headers=ADMIN, json={"frames": frames})
    assert r.status_code == 200, r.text
    assert r.json()["tp"] == 0 and np.isfinite(r.json()["frames_total"])


def test_a_nuscenes_pair_over_the_json_limit_is_413(seeded: Settings):
    from tests.calibrators.io.dump_cases import devkit_box

    box = devkit_box("a", "car", (1.0, 1.0, 0.0), num_pts=3)
    results = ('{"meta": {}, "results": {"a": [' + ", ".join([json_box(box)] * 400) + "]}}"
               ).encode()
    gt = b'{"meta": {}, "results": {"a": []}}'
    small = seeded.model_copy(update={"max_json_dump_bytes": len(results)})
    with TestClient(create_app(small)) as client:
        r = client.post("/v1/fit", headers=ADMIN, files={"results": ("r.json", results),
                                                         "gt": ("g.json", gt)})
        assert r.status_code == 413, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "results"]
        assert "DETCAL_MAX_JSON_DUMP_BYTES" in r.text
        assert client.get("/v1/jobs", headers=ADMIN).json() == []


def json_box(box: dict) -> str:
    import json

    return json.dumps(box)


def test_a_zip_directory_of_70000_members_is_refused_unparsed(client):
    """A central directory of millions of entries would take gigabytes to parse: the count
    the end record declares (zip64 here) is read first."""
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as archive:
        for i in range(70_000):
            archive.writestr(f"m{i}.npy", b"")
    start = time.monotonic()
    r = client.post(FB, headers=ADMIN, files={"dump": ("fb.npz", buf.getvalue())})
    assert r.status_code == 422 and time.monotonic() - start < 1.0, r.text
    assert "declares 70000 members" in r.json()["detail"][0]["msg"]
