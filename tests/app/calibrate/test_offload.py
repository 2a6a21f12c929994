"""Large calibrate bodies run in a worker process (app.calibrate.runner) and answer exactly what the
in-process path answers: the same bytes for successes and for every kind of error; a worker
that dies fails its request with a 503 and the next request is served by a new worker."""

from __future__ import annotations

import math
import os
import signal
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings

CAL, NUS = "/v1/calibrate", "/v1/calibrate/nuscenes"


@pytest.fixture(scope="module")
def pair(tmp_path_factory, profile_json_given, profile_json_layers
         ) -> Iterator[tuple[TestClient, TestClient]]:
    """(threaded, offloaded) clients over two copies of one seeded store: the first never
    offloads, the second offloads every body to one worker process."""
    from app.store import Store

    clients = []
    with pytest.MonkeyPatch.context():
        for kind, extra in (("threads", {"calibrate_processes": 0}),
                            ("processes", {"offload_bytes": 0})):
            settings = Settings(data_dir=tmp_path_factory.mktemp(kind), admin_token="t" * 32,
                                max_detections=50, **extra)
            store = Store(settings.sqlalchemy_url, settings.dumps_dir)
            store.add_profile("lidar", profile_json_given)
            store.add_profile("layers", profile_json_layers)
            store.close()
            clients.append(TestClient(create_app(settings)).__enter__())
        try:
            yield clients[0], clients[1]
        finally:
            for c in clients:
                c.__exit__(None, None, None)


def _nuscenes(dump, n: int, rotation: list[float] | None = None) -> dict:
    boxes = []
    for i in range(n):
        b = dump.det_boxes[i, -1].tolist()
        boxes.append({"sample_token": "t0", "translation": b[:3], "size": b[3:6],
                      "rotation": rotation or [math.cos(b[6] / 2), 0.0, 0.0,
                                               math.sin(b[6] / 2)],
                      "velocity": b[7:9], "detection_name": dump.classes[0],
                      "detection_score": 0.5, "attribute_name": "",
                      "covariance": dump.det_cov[i].tolist()})
    return {"meta": {"use_lidar": True}, "results": {"t0": boxes}}


def _requests(dump, detection) -> list[tuple[str, dict]]:
    frame = {"frame_id": "f", "detections": [detection(dump, i) for i in range(5)]}
    layered = {"frame_id": "g", "detections": [detection(dump, i, cov=False, layers=True)
                                               for i in range(3)]}
    return [
        ("ok", {"url": CAL, "json": {"frames": [frame], "levels": [0.5, 0.9]}}),
        ("ok layers", {"url": CAL, "json": {"profile": "layers", "frames": [layered]}}),
        ("ok nuscenes", {"url": NUS, "json": _nuscenes(dump, 4), "params": {"levels": [0.9]}}),
        ("422 schema", {"url": CAL, "json": {"frames": [{"frame_id": "f", "detections": [
            {"logits": ["1.5"], "box": [0.0] * 9}]}]}}),
        ("422 profile", {"url": CAL, "json": {"profile": "layers", "frames": [frame]}}),
        ("422 rotation", {"url": NUS, "json": _nuscenes(dump, 2, rotation=[0, 0, 0, 0])}),
        ("404", {"url": CAL, "json": {"profile": "nope", "frames": [frame]}}),
        ("413", {"url": CAL, "json": {"frames": [frame] * 11}}),
        ("422 not json", {"url": CAL, "content": b"{not json",
                          "headers": {"content-type": "application/json"}}),
    ]


def test_offloaded_answers_are_the_threaded_answers(pair, dump_given, detection) -> None:
    threaded, offloaded = pair
    for name, request in _requests(dump_given, detection):
        a, b = threaded.post(**request), offloaded.post(**request)
        assert (a.status_code, a.content) == (b.status_code, b.content), name
        assert a.status_code == int(name[:3]) if name[0].isdigit() else a.status_code == 200
    assert offloaded.app.state.calibrator.worker_pids(), "no body went to a worker"
    assert threaded.app.state.calibrator.worker_pids() == []


def test_a_dead_worker_fails_one_request_with_503_then_a_new_one_serves(
        pair, dump_given, detection) -> None:
    _, offloaded = pair
    body = {"frames": [{"frame_id": "f", "detections": [detection(dump_given, 0)]}]}
    assert offloaded.post(CAL, json=body).status_code == 200
    old = offloaded.app.state.calibrator.worker_pids()
    for pid in old:
        os.kill(pid, signal.SIGKILL)   # as the kernel's OOM killer would
    died = offloaded.post(CAL, json=body)
    assert died.status_code == 503 and "retry" in died.json()["detail"]
    assert [offloaded.post(CAL, json=body).status_code for _ in range(2)] == [200, 200]
    new = offloaded.app.state.calibrator.worker_pids()
    assert new and set(new).isdisjoint(old)


def test_small_bodies_stay_in_the_server_process(client, dump_given, detection) -> None:
    body = {"frames": [{"frame_id": "f", "detections": [detection(dump_given, 0)]}]}
    assert client.post(CAL, json=body).status_code == 200
    assert client.app.state.calibrator.worker_pids() == []


def test_dumps_json_is_strict_for_huge_integers_numpy_and_non_finite() -> None:
    import numpy as np

    from app.http.json_body import dumps_json

    out = dumps_json({"n": 10**30, "a": np.arange(2.0), "s": np.float32(2.5),
                      "x": float("inf")})
    assert out == b'{"n":1000000000000000000000000000000,"a":[0.0,1.0],"s":2.5,"x":null}'
    assert dumps_json({"a": np.arange(2.0)}) == b'{"a":[0.0,1.0]}'
