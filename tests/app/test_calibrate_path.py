"""How many product modules a calibrate request runs through, from its router to its response
(issue 28: the path stays short enough to read; docs/architecture.md walks it).

Measured, not declared: a profiler records every function of `app/` and `calibrators/` that
runs during one warm request (the profile parsed and cached by an earlier one). The middleware
stack every request passes is left out: a module of `app/http/` (the shared HTTP plumbing)
counts only when `GET /healthz` runs none of it, any other module when a function of it runs
that `/healthz` does not (so the Arrow route, below FastAPI's routing, counts on the Arrow
path). What remains is the route and everything below it. A package is a folder of the tree
(`app/calibrate`, `calibrators/profile`, ...)."""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from calibrators.io import calibrated_document
from calibrators.io.arrow_batch import ARROW_STREAM, write_stream

ROOT = Path(__file__).resolve().parents[2]
#: The most modules (files) and packages (folders) a calibrate request may run through.
MAX_MODULES = 22
MAX_PACKAGES = 11


class ModuleRecorder:
    """Records the product functions (`module.py:name`) that run while `on` is set, in every thread
    (threads started before `install()` are not seen: install it before the app starts)."""

    def __init__(self) -> None:
        self.on = False
        self.seen: set[str] = set()

    def _profile(self, frame, event, arg):   # noqa: ANN001, ANN202 - sys.setprofile's hook
        if self.on and event == "call":
            path = frame.f_code.co_filename
            if path.startswith(str(ROOT)):
                rel = Path(path).relative_to(ROOT).as_posix()
                if rel.split("/")[0] in ("app", "calibrators"):
                    self.seen.add(f"{rel}:{frame.f_code.co_name}")

    def install(self) -> None:
        threading.setprofile(self._profile)
        sys.setprofile(self._profile)

    def remove(self) -> None:
        sys.setprofile(None)
        threading.setprofile(None)

    def modules(self, send: Callable[[], object]) -> set[str]:
        """The functions one call of `send` (after two warm-up calls) runs."""
        send()
        send()
        self.seen = set()
        self.on = True
        try:
            response = send()
        finally:
            self.on = False
        assert response.status_code == 200, response.text[:300]
        return set(self.seen)


def modules_of(functions: set[str]) -> set[str]:
    return {f.split(":")[0] for f in functions}


def route_modules(functions: set[str], shared: set[str]) -> set[str]:
    """The modules of `functions` a request runs beyond the middleware (`shared`: what
    `/healthz` runs)."""
    plumbing = {m for m in modules_of(shared) if m.startswith("app/http/")}
    return modules_of(functions - shared) - plumbing


def packages(modules: set[str]) -> set[str]:
    return {m.rsplit("/", 1)[0] for m in modules}


@pytest.fixture
def path_client(seeded) -> Iterator[tuple[TestClient, ModuleRecorder]]:
    recorder = ModuleRecorder()
    recorder.install()
    try:
        with TestClient(create_app(seeded)) as client:
            yield client, recorder
    finally:
        recorder.remove()


def _arrow_body(dets: list[dict]) -> bytes:
    columns = {"frame_id": pa.array(["f0"] * len(dets)), "id": pa.array(range(len(dets)))}
    for key in ("logits", "box", "covariance"):
        flat = np.asarray([d[key] for d in dets], dtype=np.float64).reshape(len(dets), -1)
        columns[key] = pa.FixedSizeListArray.from_arrays(pa.array(flat.ravel()), flat.shape[1])
    return write_stream(pa.RecordBatch.from_pydict(columns))


def _paths(client: TestClient, recorder: ModuleRecorder, dump_given) -> dict[str, set[str]]:
    dets = [{"id": i, "logits": dump_given.det_logits[i, -1].tolist(),
             "box": dump_given.det_boxes[i, -1].tolist(),
             "covariance": dump_given.det_cov[i].tolist()} for i in range(20)]
    shared = recorder.modules(lambda: client.get("/healthz"))
    json_body = {"frames": [{"frame_id": "f0", "detections": dets}]}
    out = {"json": recorder.modules(lambda: client.post("/v1/calibrate", json=json_body))}
    served = client.post("/v1/calibrate", json=json_body).json()
    results = {"f0": [{"sample_token": "f0", "translation": [*d["box"][:2], d["box"][2]],
                       "size": d["box"][3:6], "rotation": [1.0, 0.0, 0.0, 0.0],
                       "velocity": d["box"][7:9], "detection_name": "car",
                       "detection_score": r["score_raw"], "attribute_name": "",
                       "covariance": d["covariance"]}
                      for d, r in zip(dets, served["frames"][0]["detections"], strict=True)]}
    doc = {"meta": {"use_lidar": True}, "results": results}
    out["nuscenes"] = recorder.modules(lambda: client.post("/v1/calibrate/nuscenes", json=doc))
    body = _arrow_body(dets)
    out["arrow"] = recorder.modules(lambda: client.post(
        "/v1/calibrate", content=body, headers={"content-type": ARROW_STREAM}))
    return {kind: route_modules(functions, shared) for kind, functions in out.items()}


def test_a_calibrate_request_runs_through_few_modules(path_client, dump_given):
    client, recorder = path_client
    for kind, mods in _paths(client, recorder, dump_given).items():
        print(f"\n{kind}: {len(mods)} modules in {len(packages(mods))} packages")
        for m in sorted(mods):
            print("  ", m)
        assert ("app/calibrate/arrow_route.py" if kind == "arrow" else "app/routers/calibrate.py"
                ) in mods
        assert len(packages(mods)) <= MAX_PACKAGES, sorted(packages(mods))
        assert len(mods) <= MAX_MODULES, sorted(mods)


def test_the_recorder_sees_a_module_that_runs():
    recorder = ModuleRecorder()
    recorder.install()
    try:
        class Ok:
            status_code = 200
        mods = recorder.modules(lambda: (calibrated_document([], {}, None), Ok())[1])
    finally:
        recorder.remove()
    assert "calibrators/io/nuscenes_batch.py:calibrated_document" in mods
