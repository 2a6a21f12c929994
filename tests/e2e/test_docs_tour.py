"""The README tour, the docs/api.md curl examples and the OpenAPI examples, against a fresh
`make run` (`detcal serve --bootstrap` on an empty data directory: it writes
`data/admin_token` and fits the default `lidar` profile).

The shell blocks of README.md's "A 5-minute tour" section, then every bash/sh block of
docs/api.md that calls curl against `$DETCAL` (and the block that sets `$DETCAL`), run one
command at a time, in document order, through bash in a scratch directory whose `data/` is the
server's data directory, with `DETCAL` and `TOKEN` set. A command is a step; what a step may
be is explicit (`STEP_KINDS`), and so is everything the test changes in one (`SUBSTITUTIONS`),
the input files it provides (`INPUTS`) and the commands it skips (`SKIPPED`): all in
tests/e2e/doc_steps.py. A block that no longer splits into such steps fails the test: it never
skips. Every curl must exit 0 with an HTTP status < 400 and a JSON body (except `NON_JSON`
routes). A fit job is watched until it lands, and must succeed. The tour's step 1 runs again
once step 4's version is active (it was once a 422 then) and at the very end. Each README
step's time is printed (the tour promises seconds per step on 2 cores; a figure, not a
threshold: no wall-clock limits in tests).

Then every example of the OpenAPI schema's JSON request bodies (the body schemas' `examples`,
the examples of their parts swapped into the first body, and parameter examples) is sent and
must get a 2xx (the requests: tests/e2e/openapi_examples.py).
"""

from __future__ import annotations

import json
import re
import shutil
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.docs.test_examples import DOCS, python_blocks
from tests.e2e.conftest import Server, serving
from tests.e2e.doc_steps import API_MD, SUBSTITUTIONS, Tour, run_step, tour_steps, watch_job
from tests.e2e.openapi_examples import openapi_requests

pytestmark = pytest.mark.e2e


# -- the server ----------------------------------------------------------------------------------
class BootstrapServer(Server):
    """What `make run` starts: `detcal serve --bootstrap`, no token configured (it writes
    `data/admin_token`), on a fresh data directory."""

    serve_args = ("--bootstrap",)
    token_env = None
    ready_path = "/readyz"

    def start(self, timeout_s: float = 120.0) -> None:
        super().start(timeout_s)

    @property
    def token(self) -> str:
        return (self.data_dir / "admin_token").read_text().strip()


@pytest.fixture(scope="module")
def fresh(tmp_path_factory: pytest.TempPathFactory) -> Iterator[BootstrapServer]:
    """A `make run` server whose data directory is `data/` of the steps' working directory."""
    srv = BootstrapServer(tmp_path_factory.mktemp("docs_tour") / "work" / "data")
    srv.data_dir.parent.mkdir(parents=True)
    yield from serving(srv)


@pytest.fixture(scope="module")
def client(fresh: BootstrapServer) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=fresh.url, timeout=60.0,
                      headers={"Authorization": f"Bearer {fresh.token}"}) as c:
        yield c


def _landed(client: httpx.Client, job_id: str, timeout_s: float = 120.0) -> dict:
    """Poll a job with `client`'s own token (the bootstrapped server's) until it lands."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        body = client.get(f"/v1/jobs/{job_id}").json()
        if body["state"] in ("succeeded", "failed"):
            return body
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not land in {timeout_s} s")


# -- the tests -----------------------------------------------------------------------------------
def test_tour_blocks_split_into_known_steps():
    """Parsing alone (no server): every step is of a known kind, and the tour has the steps
    the run below relies on."""
    steps = tour_steps()
    unknown = [f"{s.where}: {s.text!r}" for s in steps if s.kind == "unknown"]
    assert not unknown, f"steps of no known kind (teach STEP_KINDS): {unknown}"
    readme = [s for s in steps if s.where.startswith("README.md")]
    curls = [s.route for s in readme if s.kind == "curl"]
    assert curls[:2] == ["/v1/calibrate", "/v1/detect"] and "/v1/fit" in curls, curls
    # the fit reads the shipped dump (no slow step writes one); large answers in summary form
    fit = next(s for s in readme if s.kind == "curl" and s.route == "/v1/fit")
    assert "dump=@detectors/data/lidar_val.npz" in fit.text
    for route in ("/v1/jobs/<job_id>", "/v1/profiles/lidar/health"):
        step = next(s for s in readme if s.kind == "curl" and s.route == route)
        assert "?fields=" in step.text, step


@pytest.mark.skipif(shutil.which("curl") is None,
                    reason="curl is not installed: the README and docs/api.md examples are "
                           "curl commands")
def test_readme_tour_and_api_examples_run_in_order(fresh: BootstrapServer, client):
    tour = Tour(url=fresh.url, token=fresh.token, workdir=fresh.data_dir.parent)
    used: set[str] = set()
    steps = tour_steps()
    unknown = [f"{s.where}: {s.text!r}" for s in steps if s.kind == "unknown"]
    assert not unknown, f"steps of no known kind (teach STEP_KINDS): {unknown}"
    timings: list[str] = []
    for step in steps:
        start = time.monotonic()
        answer = run_step(step, tour, used)
        took = time.monotonic() - start
        if step.where.startswith("README.md"):
            timings.append(f"{took:6.2f} s  {step.where}: {step.text.splitlines()[0][:80]}")
        if step.kind != "curl":
            continue
        route = step.route
        if route == "/v1/calibrate" and tour.step1 is None:
            tour.step1 = step
        if route == "/v1/fit":
            tour.job_id = answer["job_id"]
        if route.startswith("/v1/jobs/"):
            job = watch_job(step, tour, used, answer)
            if job.get("activate") and job["profile"]["name"] == "lidar":
                # Issue 11: once step 4's version is active, step 1 must still be served.
                active = client.get("/v1/profiles/lidar").json()["active_version"]
                assert active == job["profile"]["version"], job.get("activation")
                run_step(tour.step1, tour, used)
    assert set(SUBSTITUTIONS) <= used, f"substitutions no step needs: {set(SUBSTITUTIONS) - used}"
    # Every fit the docs queued landed.
    for job in client.get("/v1/jobs", params={"limit": 50}).json():
        landed = _landed(client, job["id"])
        assert landed["state"] == "succeeded", landed
    assert tour.step1 is not None
    run_step(tour.step1, tour, used)          # step 1 once more, after everything
    print("\n".join(tour.ran))
    print("README tour steps:\n" + "\n".join(timings))


def test_server_python_examples_run(fresh: BootstrapServer, monkeypatch, tmp_path):
    """The docs' python blocks that call the server (`os.environ["DETCAL"]`: e.g. the Arrow
    client of docs/api.md) run against the fresh server, each doc's blocks in one namespace."""
    docs = {doc: python_blocks(doc, server=True) for doc in DOCS}
    docs = {doc: blocks for doc, blocks in docs.items() if blocks}
    assert API_MD in docs, "docs/api.md has no python client example"
    monkeypatch.setenv("DETCAL", fresh.url)
    monkeypatch.chdir(tmp_path)
    for doc, blocks in docs.items():
        namespace: dict[str, object] = {"__name__": "__main__"}
        for block in blocks:
            source = "\n" * (block.line - 1) + block.code   # line numbers are the markdown's
            exec(compile(source, str(doc), "exec"), namespace)
        if doc == API_MD:   # the Arrow client's answer
            out = namespace["out"]
            assert out.num_rows == 300 and "ellipse_0.9" in out.column_names  # type: ignore[attr-defined]


def test_openapi_examples_are_served(fresh: BootstrapServer, client):
    spec = client.get("/openapi.json").json()
    if len(client.get("/v1/profiles/lidar").json()["versions"]) < 2:
        # The examples name lidar@2; the tour above fits it (this test alone: fit it here).
        from app.fitting.bootstrap import shipped_dump

        dump = shipped_dump("lidar")
        assert dump is not None, "the shipped lidar dump is missing"
        r = client.post("/v1/fit", files={"dump": ("val.npz", dump.read_bytes())},
                        data={"name": "lidar"})
        assert r.status_code == 202, r.text
        assert _landed(client, r.json()["job_id"])["state"] == "succeeded"
    requests = openapi_requests(spec)
    json_ops = {(m, p) for p, ops in spec["paths"].items() for m, op in ops.items()
                if "application/json" in op.get("requestBody", {}).get("content", {})}
    sent = {(m, u) for m, u, _, _ in requests}
    assert json_ops and all(   # a path with parameters is sent with them filled in
        any(m == method and re.fullmatch(re.sub(r"\{[^/]+\}", "[^/]+", path), u)
            for m, u in sent) for method, path in json_ops), json_ops
    failed = []
    for method, url, query, body in requests:
        r = client.request(method, url, params=query, json=body)
        ok = 200 <= r.status_code < 300
        if ok and r.headers.get("content-type", "").startswith("application/json"):
            r.json()
        if not ok:
            failed.append(f"{method.upper()} {url} {query} {json.dumps(body)[:300]} -> "
                          f"{r.status_code} {r.text[:500]}")
    assert not failed, "\n".join(failed)
    print(f"\n{len(requests)} OpenAPI example requests, all 2xx")
