"""Every response of the service validates against the model its route declares for that status.

`CASES` sends, for every route of the app, a request for its success status and one for each
error status it declares (and the cheap ones it answers anyway, 422); each body is validated
against `route.response_model` (success), `route.responses[status]["model"]`, or
`ErrorResponse` for a 422 FastAPI documents by itself, and must dump back to the same JSON
(so no undeclared key slips through). A route added without cases, or a status declared
without one, fails `test_every_route_and_declared_status_has_a_case`.

The fit-job runner is not started (the cases look at responses, not fits) and the bundled
detector is the real bundled lidar detector (torch, CPU).
"""

from __future__ import annotations

import io
import math
import os
import signal
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.responses import JSONResponse
from fastapi.routing import APIRoute
from fastapi.testclient import TestClient
from pydantic import TypeAdapter

from app.bundled_detectors import DetectorService
from app.fitting.runner import JobRunner
from app.main import create_app
from app.schemas.types import ErrorResponse
from app.settings import Settings
from app.store import Store
from tests.app.conftest import ADMIN, TOKEN

WRONG_TOKEN = {"Authorization": "Bearer not-the-token"}
TEXT = {"content-type": "text/plain"}
SMALL_LIMIT = 2000    # bytes: the `small` app refuses larger bodies (413)


def api_routes(app: FastAPI) -> Iterator[Any]:
    """Every APIRoute of `app` as served: the path with its router's prefix, and the
    router's `responses` merged into the route's (FastAPI >= 0.137 keeps included routers
    as a tree: `iter_route_contexts` flattens it; before, `app.routes` was flat)."""
    try:
        from fastapi.routing import iter_route_contexts
    except ImportError:   # FastAPI < 0.137.2
        yield from (r for r in app.routes if isinstance(r, APIRoute))
        return
    for context in iter_route_contexts(app.routes):
        if isinstance(context.original_route, APIRoute):
            yield context


def declared_model(route: Any, status: int) -> Any:
    """The model `route` declares for `status`; None for a success without a JSON model."""
    declared = route.responses.get(status) or route.responses.get(str(status)) or {}
    if "model" in declared:
        return declared["model"]
    if status == (route.status_code or 200):
        return route.response_model
    if status == 422:   # request validation: documented by FastAPI on every route
        return ErrorResponse
    raise AssertionError(f"{sorted(route.methods)} {route.path} answered {status}, a status it "
                         f"does not declare")


@dataclass
class World:
    """Clients over three stores and what the requests are built from."""

    clients: dict[str, TestClient]
    dump: Any
    detection: Callable[..., dict]
    npz: bytes
    job_id: str

    def frames(self, n: int = 2) -> list[dict]:
        return [{"frame_id": "f0", "detections": [self.detection(self.dump, i)
                                                  for i in range(n)]}]

    def nuscenes(self, n: int = 2, rotation: list[float] | None = None) -> dict:
        """A results document of `n` dump detections (logits and covariance kept)."""
        boxes = []
        for i in range(n):
            logits = self.dump.det_logits[i, -1]
            b = self.dump.det_boxes[i, -1].tolist()
            label = int(np.argmax(logits))
            boxes.append({
                "sample_token": "tok0", "translation": b[:3], "size": b[3:6],
                "rotation": rotation or [math.cos(b[6] / 2), 0.0, 0.0, math.sin(b[6] / 2)],
                "velocity": b[7:9], "detection_name": self.dump.classes[label],
                "detection_score": float(1 / (1 + math.exp(-logits[label]))),
                "attribute_name": "", "detection_logits": logits.tolist(),
                "covariance": self.dump.det_cov[i].tolist()})
        return {"meta": {"use_lidar": True}, "results": {"tok0": boxes}}

    def upload(self) -> dict:
        return {"files": {"dump": ("val.npz", self.npz)}}

    def worker_killed(self, request: dict) -> dict:
        """`request`, after the offload app's calibrate worker was started and killed."""
        client = self.clients["offload"]
        assert client.post(CAL, json={"frames": self.frames(1)}).status_code == 200
        pids = client.app.state.calibrator.worker_pids()
        assert pids, "the calibrate worker did not start"
        for pid in pids:
            os.kill(pid, signal.SIGKILL)
            _wait_gone(pid)
        return request


def _wait_gone(pid: int, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        time.sleep(0.01)


@dataclass(frozen=True)
class Case:
    """One request: `path` is the route's template, `request(world)` the TestClient kwargs
    (`url` included); `client` picks the store: seeded, empty, small (tiny body limits) or
    offload (seeded; every calibrate body goes to a worker process)."""

    method: str
    path: str
    status: int
    request: Callable[[World], dict]
    client: str = "seeded"
    detectors: str | None = None   # "unavailable": no weights, the detector service answers 503


def url(u: str, **kw: Any) -> Callable[[World], dict]:
    return lambda w: {"url": u, **kw}


CAL, NUS, DET, FIT = "/v1/calibrate", "/v1/calibrate/nuscenes", "/v1/detect", "/v1/fit"
JOB, VERSIONS = "/v1/jobs/{job_id}", "/v1/profiles/{name}"
VERSION, ACTIVATE = "/v1/profiles/{name}/{version}", "/v1/profiles/{name}/{version}/activate"

CASES = [
    Case("GET", "/healthz", 200, url("/healthz")),
    Case("GET", "/readyz", 200, url("/readyz")),
    Case("GET", "/readyz", 503, url("/readyz"), client="empty"),
    Case("GET", "/metrics", 200, url("/metrics")),
    Case("GET", "/", 200, url("/"), client="empty"),
    # the API docs, served from the installed fastapi-offline package (HTML, no model)
    Case("GET", "/docs", 200, url("/docs")),
    Case("GET", "/docs/oauth2-redirect", 200, url("/docs/oauth2-redirect")),
    Case("GET", "/redoc", 200, url("/redoc")),
    Case("POST", CAL, 200, lambda w: {"url": CAL, "json": {"frames": w.frames()}}),
    Case("POST", CAL, 404, lambda w: {"url": CAL, "json": {"profile": "nope",
                                                           "frames": w.frames()}}),
    Case("POST", CAL, 413, lambda w: {"url": CAL, "json": {"frames": w.frames(10)}},
         client="small"),
    Case("POST", CAL, 415, url(CAL, content=b"{}", headers=TEXT)),
    Case("POST", CAL, 406, lambda w: {"url": CAL, "json": {"frames": w.frames()}, "headers": {
        "accept": "application/vnd.apache.arrow.stream"}}),
    Case("POST", CAL, 422, url(CAL, json={"frames": []})),
    Case("POST", CAL, 200, lambda w: {"url": CAL, "json": {"frames": w.frames()}},
         client="offload"),
    Case("POST", CAL, 503, lambda w: w.worker_killed({"url": CAL, "json": {
        "frames": w.frames()}}), client="offload"),
    Case("POST", NUS, 200, lambda w: {"url": NUS, "json": w.nuscenes()}),
    Case("POST", NUS, 503, lambda w: w.worker_killed({"url": NUS, "json": w.nuscenes()}),
         client="offload"),
    Case("POST", NUS, 404, lambda w: {"url": NUS, "json": w.nuscenes(),
                                      "params": {"profile": "nope"}}),
    Case("POST", NUS, 413, lambda w: {"url": NUS, "json": w.nuscenes(10)}, client="small"),
    Case("POST", NUS, 415, url(NUS, content=b"{}", headers=TEXT)),
    Case("POST", NUS, 422, lambda w: {"url": NUS, "json": w.nuscenes(rotation=[0, 0, 0, 0])}),
    Case("POST", DET, 200, url(DET, json={"sensor": "lidar", "seed": 3})),
    Case("POST", DET, 404, url(DET, json={"seed": 3, "profile": "nope"})),
    Case("POST", DET, 413, url(DET, json={"points": [[0.5, 0.5, 0.5, 0.5]] * 200}),
         client="small"),
    Case("POST", DET, 415, url(DET, content=b"{}", headers=TEXT)),
    Case("POST", DET, 422, url(DET, json={"seed": 1, "points": [[0.0, 0.0, 0.0, 1.0]]})),
    Case("POST", DET, 503, url(DET, json={"seed": 3}), detectors="unavailable"),
    Case("POST", FIT, 202, lambda w: {"url": FIT, "headers": ADMIN, "data": {"name": "up"},
                                      **w.upload()}),
    Case("POST", FIT, 401, lambda w: {"url": FIT, **w.upload()}),
    Case("POST", FIT, 403, lambda w: {"url": FIT, "headers": WRONG_TOKEN, **w.upload()}),
    Case("POST", FIT, 413, lambda w: {"url": FIT, "headers": ADMIN, **w.upload()},
         client="small"),
    Case("POST", FIT, 422, url(FIT, headers=ADMIN, data={"name": "up"})),
    Case("GET", "/v1/jobs", 200, url("/v1/jobs", headers=ADMIN)),
    Case("GET", "/v1/jobs", 401, url("/v1/jobs")),
    Case("GET", "/v1/jobs", 403, url("/v1/jobs", headers=WRONG_TOKEN)),
    Case("GET", "/v1/jobs", 422, url("/v1/jobs", params={"limit": 0}, headers=ADMIN)),
    Case("GET", JOB, 200, lambda w: {"url": f"/v1/jobs/{w.job_id}", "headers": ADMIN}),
    Case("GET", JOB, 401, lambda w: {"url": f"/v1/jobs/{w.job_id}"}),
    Case("GET", JOB, 403, lambda w: {"url": f"/v1/jobs/{w.job_id}", "headers": WRONG_TOKEN}),
    Case("GET", JOB, 404, url("/v1/jobs/" + "0" * 32, headers=ADMIN)),
    Case("GET", JOB, 422, url("/v1/jobs/xyz", headers=ADMIN)),
    Case("GET", "/v1/profiles", 200, url("/v1/profiles")),
    Case("GET", VERSIONS, 200, url("/v1/profiles/lidar")),
    Case("GET", VERSIONS, 404, url("/v1/profiles/nope")),
    Case("GET", VERSIONS, 422, url("/v1/profiles/no*pe")),
    Case("GET", VERSION, 200, url("/v1/profiles/lidar/1")),
    Case("GET", VERSION, 404, url("/v1/profiles/lidar/9")),
    Case("GET", VERSION, 422, url("/v1/profiles/lidar/0")),
    Case("POST", ACTIVATE, 200, url("/v1/profiles/lidar/1/activate", headers=ADMIN)),
    Case("POST", ACTIVATE, 401, url("/v1/profiles/lidar/1/activate")),
    Case("POST", ACTIVATE, 403, url("/v1/profiles/lidar/1/activate", headers=WRONG_TOKEN)),
    Case("POST", ACTIVATE, 404, url("/v1/profiles/lidar/9/activate", headers=ADMIN)),
    Case("POST", ACTIVATE, 422, url("/v1/profiles/lidar/0/activate", headers=ADMIN)),
]


# -- issue 14: feedback, health, aliases, audit ---------------------------------------------
FB, HEALTH, AUDIT = "/v1/feedback", "/v1/profiles/{name}/health", "/v1/audit"
ALIASES, ALIAS = "/v1/profiles/{name}/aliases", "/v1/profiles/{name}/aliases/{alias}"


def _feedback(w: World, n: int = 2, **kw: Any) -> dict:
    from tests.app.feedback_frames import feedback_frames

    frames = feedback_frames(w.dump.select_frames(np.arange(w.dump.n_frames) < n))
    return {"url": FB, "headers": ADMIN, "json": {"frames": frames}, **kw}


def _aliased(w: World, request: dict) -> dict:
    """`request`, after alias `gone` of lidar was set."""
    w.clients["seeded"].put("/v1/profiles/lidar/aliases/gone", headers=ADMIN,
                            json={"version": 1})
    return request


CASES += [
    Case("POST", FB, 200, _feedback),
    Case("POST", FB, 401, lambda w: {**_feedback(w), "headers": {}}),
    Case("POST", FB, 403, lambda w: {**_feedback(w), "headers": WRONG_TOKEN}),
    Case("POST", FB, 404, lambda w: _feedback(w, json={"profile": "nope", "frames": [
        {"detections": [], "ground_truth": []}]})),
    Case("POST", FB, 413, lambda w: _feedback(w, 10), client="small"),
    Case("POST", FB, 415, url(FB, headers={**ADMIN, **TEXT}, content=b"{}")),
    Case("POST", FB, 422, url(FB, headers=ADMIN, files={"dump": ("x.npz", b"nope")})),
    Case("GET", HEALTH, 200, url("/v1/profiles/lidar/health")),
    Case("GET", HEALTH, 404, url("/v1/profiles/nope/health")),
    Case("GET", HEALTH, 422, url("/v1/profiles/lidar/health", params={"version": 0})),
    Case("GET", ALIASES, 200, url("/v1/profiles/lidar/aliases")),
    Case("GET", ALIASES, 404, url("/v1/profiles/nope/aliases")),
    Case("GET", ALIASES, 422, url("/v1/profiles/no*pe/aliases")),
    Case("PUT", ALIAS, 200, url("/v1/profiles/lidar/aliases/challenger", headers=ADMIN,
                                json={"version": 1})),
    Case("PUT", ALIAS, 401, url("/v1/profiles/lidar/aliases/c", json={"version": 1})),
    Case("PUT", ALIAS, 403, url("/v1/profiles/lidar/aliases/c", headers=WRONG_TOKEN,
                                json={"version": 1})),
    Case("PUT", ALIAS, 404, url("/v1/profiles/lidar/aliases/c", headers=ADMIN,
                                json={"version": 9})),
    Case("PUT", ALIAS, 415, url("/v1/profiles/lidar/aliases/c", headers={**ADMIN, **TEXT},
                                content=b"{}")),
    Case("PUT", ALIAS, 422, url("/v1/profiles/lidar/aliases/c", headers=ADMIN,
                                json={"version": 0})),
    Case("DELETE", ALIAS, 200, lambda w: _aliased(w, {
        "url": "/v1/profiles/lidar/aliases/gone", "headers": ADMIN})),
    Case("DELETE", ALIAS, 401, url("/v1/profiles/lidar/aliases/gone")),
    Case("DELETE", ALIAS, 403, url("/v1/profiles/lidar/aliases/gone", headers=WRONG_TOKEN)),
    Case("DELETE", ALIAS, 404, url("/v1/profiles/lidar/aliases/ghost", headers=ADMIN)),
    Case("DELETE", ALIAS, 409, url("/v1/profiles/lidar/aliases/champion", headers=ADMIN)),
    Case("DELETE", ALIAS, 422, url("/v1/profiles/lidar/aliases/9abc", headers=ADMIN)),
    Case("GET", AUDIT, 200, url(AUDIT, headers=ADMIN)),
    Case("GET", AUDIT, 401, url(AUDIT)),
    Case("GET", AUDIT, 403, url(AUDIT, headers=WRONG_TOKEN)),
    Case("GET", AUDIT, 422, url(AUDIT, headers=ADMIN, params={"limit": 0})),
]

def _store(settings: Settings, *profiles: tuple[str, str]) -> Store:
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    for name, text in profiles:
        store.add_profile(name, text)
    return store


@pytest.fixture(scope="module")
def world(tmp_path_factory, dump_given, detection, npz_bytes, profile_json_given,
          profile_json_layers) -> Iterator[World]:
    """Apps over a seeded store (with a succeeded fit job), an empty one, and a seeded one
    with small body limits."""
    seeded = [("lidar", profile_json_given), ("layers", profile_json_layers)]
    settings = {kind: Settings(data_dir=tmp_path_factory.mktemp(kind), admin_token=TOKEN,
                               **limits)
                for kind, limits in (("seeded", {}), ("empty", {}), (
                    "small", {"max_request_bytes": SMALL_LIMIT,
                              "max_upload_bytes": SMALL_LIMIT}), ("offload", {"offload_bytes": 0}))}
    store = _store(settings["seeded"], *seeded)
    dump = store.put_dump(io.BytesIO(npz_bytes), "npz")
    job = store.create_job("fitted", {"threshold": 2.0}, dump.sha256)
    claimed = store.claim_job()
    assert claimed is not None and claimed.id == job.id
    store.complete_job(job.id, profile_json_given)
    store.close()
    _store(settings["empty"]).close()
    _store(settings["small"], *seeded).close()
    _store(settings["offload"], *seeded).close()
    with pytest.MonkeyPatch.context() as mp, ExitStack() as stack:
        mp.setattr(JobRunner, "start", lambda self: None)
        clients = {}
        for kind, s in settings.items():
            app = create_app(s)
            clients[kind] = stack.enter_context(TestClient(app, raise_server_exceptions=False))
        yield World(clients, dump_given, detection, npz_bytes, job.id)


def _route(app: FastAPI, method: str, path: str) -> Any:
    found = [r for r in api_routes(app) if r.path == path and method in r.methods]
    assert len(found) == 1, f"{method} {path}: {len(found)} routes"
    return found[0]


@pytest.mark.parametrize("case", CASES, ids=[f"{c.method} {c.path} {c.status}" for c in CASES])
def test_response_validates_against_the_declared_model(world, case, monkeypatch, tmp_path):
    client = world.clients[case.client]
    route = _route(client.app, case.method, case.path)
    if case.detectors == "unavailable":   # the real service, its weights folder empty
        from detectors import registry

        monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
        monkeypatch.setattr(client.app.state, "detectors", DetectorService())
    kwargs = case.request(world)
    r = client.request(case.method, **kwargs)
    assert r.status_code == case.status, r.text
    assert route.path_regex.match(r.request.url.path), (r.request.url.path, route.path)
    model = declared_model(route, case.status)
    media = r.headers.get("content-type", "").split(";")[0]
    if model is None:   # no JSON model declared: the route must not answer JSON either
        assert media != "application/json", f"{case.path} answers JSON without a model"
        assert not issubclass(route.response_class, JSONResponse)
        return
    assert media == "application/json", media
    adapter = TypeAdapter(model)
    value = adapter.validate_json(r.content)
    assert adapter.dump_python(value, mode="json", exclude_unset=True) == r.json(), (
        f"the body has keys or values {model} does not declare")


def test_every_route_and_declared_status_has_a_case(world):
    app = world.clients["seeded"].app
    declared: dict[tuple[str, str], set[int]] = {}
    for route in api_routes(app):
        statuses = {route.status_code or 200}
        statuses |= {int(s) for s, spec in route.responses.items() if "model" in spec}
        for method in route.methods:
            declared[(method, route.path)] = statuses
    covered: dict[tuple[str, str], set[int]] = defaultdict(set)
    for case in CASES:
        covered[(case.method, case.path)].add(case.status)
    assert len(declared) >= 13
    assert set(covered) == set(declared), (
        f"routes without cases: {sorted(set(declared) - set(covered))}; cases without a "
        f"route: {sorted(set(covered) - set(declared))}")
    missing = {f"{m} {p}": sorted(s - covered[(m, p)]) for (m, p), s in declared.items()
               if s - covered[(m, p)]}
    assert not missing, f"declared statuses without a case: {missing}"
