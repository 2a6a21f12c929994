"""POST /v1/fit with hostile dumps (issue 11): each is a 422 at the upload field, naming the
array or key path, before anything large is allocated and before a job is queued."""

from __future__ import annotations

import json
import tracemalloc

import numpy as np
import pytest

from tests.calibrators.io.dump_cases import arrays, devkit_box, hostile_npz

ADMIN = {"Authorization": "Bearer test-admin-token-0123456789"}


def post_traced(client, **kw) -> tuple[object, int]:
    """The response to POST /v1/fit and the peak bytes Python allocated while serving it."""
    tracemalloc.start()
    try:
        r = client.post("/v1/fit", headers=ADMIN, **kw)
        return r, tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def assert_refused(client, r, field: str, *fragments: str, status: int = 422) -> None:
    assert r.status_code == status, r.text
    (item,) = r.json()["detail"]
    assert item["loc"] == ["body", field], item
    for fragment in fragments:
        assert fragment in item["msg"], item["msg"]
    assert client.get("/v1/jobs", headers=ADMIN).json() == []  # refused before a job was queued


def test_declared_shape_of_10_to_the_12_is_a_413_not_a_memory_error(empty_client, settings):
    """Over the per-request limits (issue 25): 413, from the headers, naming key and shape."""
    data = hostile_npz(arrays(), {"det_logits": ((10**12, 3, 10), "<f8", 0)})
    r, peak = post_traced(empty_client, files={"dump": ("bomb.npz", data)})
    assert_refused(empty_client, r, "dump", "det_logits", "(1000000000000, 3, 10)", "limit",
                   status=413)
    assert str(settings.data_dir.resolve()) not in r.text
    assert peak < 16 * 2**20


def test_deflated_zeros_over_the_limit_are_refused_without_inflating(settings):
    """64 MB of zeros in det_logits (about 64 kB uploaded) against a 4 MiB limit
    (DETCAL_MAX_DUMP_BYTES)."""
    from fastapi.testclient import TestClient

    from app.main import create_app

    limited = settings.model_copy(update={"max_dump_bytes": 4 * 2**20,
                                          "max_fit_detections": 10**6})
    data = hostile_npz(arrays(), {"det_logits": ((266_667, 3, 10), "<f8", 64_000_080)})
    assert len(data) < 200_000
    with TestClient(create_app(limited)) as client:
        r, peak = post_traced(client, files={"dump": ("bomb.npz", data)})
        assert_refused(client, r, "dump", "det_logits", "more than the limit of 4194304",
                       status=413)
    assert peak < 16 * 2**20


@pytest.mark.parametrize("content, fragments", [
    ({**arrays(), "det_logits": arrays()["det_logits"] + 1j}, ("det_logits", "complex")),
    ({**arrays(), "det_frame": arrays()["det_frame"][:5]},
     ("det_frame has 5 rows but det_logits has 12",)),
    ({**arrays(), "classes": np.array(["car", "pedestrian", "traffic_cone"], dtype=object)},
     ("classes", "unpickling")),
])
def test_bad_arrays_are_named(empty_client, content, fragments):
    r = empty_client.post("/v1/fit", headers=ADMIN,
                          files={"dump": ("x.npz", hostile_npz(content))})
    assert_refused(empty_client, r, "dump", *fragments)


def test_a_file_that_is_not_a_zip_says_so(empty_client, settings):
    r = empty_client.post("/v1/fit", headers=ADMIN, files={"dump": ("x.npz", b"hello" * 20)})
    assert_refused(empty_client, r, "dump", "not a zip file")
    assert "pickle" not in r.text and str(settings.data_dir.resolve()) not in r.text


def _pair(meta: dict | None = None, box: dict | None = None, raw: str | None = None) -> dict:
    b = {**devkit_box("a", "car", (1.0, 1.0, 0.0), num_pts=3), **(box or {})}
    results = raw or json.dumps({"meta": meta or {}, "results": {"a": [b]}})
    gt = json.dumps({"meta": {}, "results": {"a": [devkit_box("a", "car", (1, 1, 0), -1.0)]}})
    return {"files": {"results": ("r.json", results.encode()), "gt": ("g.json", gt.encode())}}


DEEP = '{"meta": {"x": ' + "[" * 3000 + "]" * 3000 + '}, "results": {"a": []}}'


@pytest.mark.parametrize("upload, fragment", [
    (_pair(meta={"classes": 5}), "meta.classes must be a non-empty list of strings, got 5"),
    (_pair(meta={"classes": None}), "meta.classes must be a non-empty list of strings, got null"),
    (_pair(meta={"cov_dims": 7}), "meta.cov_dims must be a non-empty list of strings, got 7"),
    (_pair(box={"detection_name": ["car"]}), "results['a'][0].detection_name must be one of"),
    (_pair(box={"num_pts": None}), "results['a'][0].num_pts must be a whole number"),
    (_pair(box={"num_pts": [1]}), "results['a'][0].num_pts must be a whole number"),
    (_pair(raw=json.dumps({"meta": {}, "results": {"a": [devkit_box(
        "a", "car", (1, 1, 0), num_pts="BIG")]}}).replace('"BIG"', "1e400")),
     "results['a'][0].num_pts must be a whole number"),
    (_pair(raw=DEEP), "results file nests arrays/objects 33 deep"),
], ids=["classes-5", "classes-null", "cov-dims-7", "name-list", "num-pts-null", "num-pts-list",
        "num-pts-1e400", "nested-3000"])
def test_malformed_nuscenes_uploads_are_422s(empty_client, upload, fragment):
    r = empty_client.post("/v1/fit", headers=ADMIN, **upload)
    assert_refused(empty_client, r, "results", fragment)
