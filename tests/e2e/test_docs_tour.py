"""The README tour, the docs/api.md curl examples and the OpenAPI examples, against a fresh
`make run` (`detcal serve --bootstrap` on an empty data directory: it writes
`data/admin_token` and fits the default `lidar` profile).

The shell blocks of README.md's "A 5-minute tour" section, then every bash/sh block of
docs/api.md that calls curl against `$DETCAL` (and the block that sets `$DETCAL`), run one
command at a time, in document order, through bash in a scratch directory whose `data/` is the
server's data directory, with `DETCAL` and `TOKEN` set. A command is a step; what a step may
be is explicit (`STEP_KINDS`), and so is everything the test changes in one (`SUBSTITUTIONS`),
the input files it provides (`INPUTS`) and the commands it skips (`SKIPPED`). A block that no
longer splits into such steps fails the test: it never skips. Every curl must exit 0 with an
HTTP status < 400 and a JSON body (except `NON_JSON` routes). A fit job is watched until it
lands, and must succeed. The tour's step 1 runs again once step 4's version is active (it
was once a 422 then) and at the very end. Each README step's time is printed (the tour
promises seconds per step on 2 cores; a figure, not a threshold: no wall-clock limits in
tests).

Then every example of the OpenAPI schema's JSON request bodies (the body schemas' `examples`,
the examples of their parts swapped into the first body, and parameter examples) is sent and
must get a 2xx.
"""

from __future__ import annotations

import copy
import json
import os
import re
import shlex
import shutil
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.docs.test_examples import DOCS, fenced_blocks, python_blocks
from tests.e2e.conftest import ROOT, Server, serving

pytestmark = pytest.mark.e2e

README = ROOT / "README.md"
API_MD = ROOT / "docs" / "api.md"
TOUR_HEADING = "## A 5-minute tour"
SHELL_LANGS = ("sh", "bash", "shell")
NUSC_SAMPLE_FRAMES = 10     # results_nusc.json: the first frames of val.npz (under 8 MiB)
SHIPPED_DUMP = ROOT / "detectors" / "data" / "lidar_val.npz"


@dataclass
class Tour:
    """What later steps need from earlier ones."""

    url: str
    token: str
    workdir: Path
    job_id: str | None = None                   # the latest POST /v1/fit's job
    step1: Step | None = None                   # the README tour's first /v1/calibrate
    ran: list[str] = field(default_factory=list)


def _latest_job(t: Tour) -> str:
    assert t.job_id, "a step names a job before any POST /v1/fit returned one"
    return t.job_id


# Text in a step -> what it becomes. Each must be used by some step (a stale one fails).
SUBSTITUTIONS: dict[str, Callable[[Tour], str]] = {
    "http://127.0.0.1:8000": lambda t: t.url,            # `export DETCAL=...`: the test server
    "detectors/data/lidar_val.npz": lambda t: str(SHIPPED_DUMP),   # run from the clone's root
    "<job_id>": _latest_job,                             # README step 4: the fit just queued
    "6f1c0b9e2d4a4c4f9a3e8d7b1c2a5f60": _latest_job,     # docs/api.md: an example job id
}

# Commands that cannot run headless: the first word -> why it is skipped.
SKIPPED = {
    "xdg-open": "opens a browser; tests/e2e/test_dashboard.py renders the dashboard",
    "open": "opens a browser; tests/e2e/test_dashboard.py renders the dashboard",
}

# Routes whose answer is not JSON: path -> the content type it has instead.
NON_JSON = {"/metrics": "text/plain"}


def _nusc_from_val(workdir: Path, results: str, gt: str | None, frames: int | None) -> None:
    from calibrators import load_dump, save_nuscenes

    dump = load_dump(SHIPPED_DUMP)
    if frames is not None:
        dump = dump.select_frames(np.arange(dump.n_frames) < frames)
    save_nuscenes(dump, workdir / results, None if gt is None else workdir / gt)


# Input files the doc examples read and no earlier step writes: name -> how to make it.
INPUTS: dict[str, Callable[[Path], None]] = {
    "val.npz": lambda w: shutil.copyfile(SHIPPED_DUMP, w / "val.npz"),
    "results_nusc.json": lambda w: _nusc_from_val(w, "results_nusc.json", None,
                                                  NUSC_SAMPLE_FRAMES),
    "val_nusc.json": lambda w: _nusc_from_val(w, "val_nusc.json", "val_nusc_gt.json", None),
    "val_nusc_gt.json": lambda w: _nusc_from_val(w, "val_nusc.json", "val_nusc_gt.json", None),
}

# bash around every step: errors stop it, and curl shows them, fails on a status >= 400 (with
# the body) and writes the response headers where the test reads the status and content type.
PREAMBLE = """set -euo pipefail
curl() { command curl --show-error --fail-with-body --dump-header "$DOCTOUR_HEADERS" "$@"; }
"""


# -- parsing -------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Step:
    """One shell command of a doc: where it is, its text as written, and its kind."""

    where: str
    text: str

    @property
    def words(self) -> list[str]:
        return shlex.split(self.text, comments=True)

    @property
    def kind(self) -> str:
        return STEP_KINDS.get(self.words[0], "unknown")

    @property
    def route(self) -> str:
        """The path of the `$DETCAL` URL a curl step calls (no query)."""
        urls = [w for w in self.words if w.startswith("$DETCAL")]
        assert len(urls) == 1, f"{self.where}: expected one $DETCAL URL in {self.text!r}"
        return urls[0][len("$DETCAL"):].split("?")[0] or "/"

    @property
    def output_file(self) -> str | None:
        words = self.words
        for i, w in enumerate(words[:-1]):
            if w in ("-o", "--output"):
                return words[i + 1]
        return None


STEP_KINDS = {"export": "export", "curl": "curl", ".venv/bin/detcal": "detcal",
              "detcal": "detcal", **{name: "skip" for name in SKIPPED}}


def split_commands(code: str, where: Callable[[int], str]) -> list[Step]:
    """The commands of a shell block: one per line, a line ending in `\\` or an open quote
    going on; comments dropped. Refuses what it cannot split (an unterminated quote)."""
    steps: list[Step] = []
    buf: list[str] = []
    quote: str | None = None
    line = start = 1
    i = 0

    def flush() -> None:
        text = "".join(buf).strip()
        if text:
            steps.append(Step(where(start), text))
        buf.clear()

    while i < len(code):
        c = code[i]
        if not "".join(buf).strip() and not c.isspace():
            start = line
        if quote == "'":
            quote = None if c == "'" else quote
            buf.append(c)
        elif quote == '"':
            if c == "\\" and i + 1 < len(code):
                buf.append(c)
                i += 1
                c = code[i]
            elif c == '"':
                quote = None
            buf.append(c)
        elif c == "\\" and code[i + 1:i + 2] == "\n":
            buf.append("\\\n")
            i += 1
            c = "\n"
        elif c in "'\"":
            quote = c
            buf.append(c)
        elif c == "#" and (not buf or buf[-1].isspace()):
            while i + 1 < len(code) and code[i + 1] != "\n":
                i += 1
        elif c == "\n":
            flush()
        else:
            buf.append(c)
        line += c == "\n"
        i += 1
    if quote is not None:
        raise AssertionError(f"{where(start)}: unterminated {quote} quote in the shell block")
    flush()
    return steps


def _blocks(path: Path, text: str, offset: int) -> list[Step]:
    rel = path.relative_to(ROOT).as_posix()
    steps: list[Step] = []
    for block in fenced_blocks(text):
        if block.lang not in SHELL_LANGS:
            continue
        if path == API_MD and not (("curl" in block.code and "$DETCAL" in block.code)
                                   or "export DETCAL=" in block.code):
            continue
        first = offset + block.line
        steps += split_commands(block.code, lambda n, first=first: f"{rel}:{first + n - 1}")
    return steps


def tour_steps() -> list[Step]:
    """The commands of README.md's tour section, then docs/api.md's curl examples."""
    text = README.read_text(encoding="utf-8")
    head, sep, rest = text.partition(f"\n{TOUR_HEADING}\n")
    assert sep, f"README.md has no '{TOUR_HEADING}' section"
    section = rest.split("\n## ", 1)[0]
    offset = head.count("\n") + 2                 # README line of the section's first line - 1
    readme = _blocks(README, section, offset)
    assert readme, f"README.md's '{TOUR_HEADING}' has no shell block"
    api = _blocks(API_MD, API_MD.read_text(encoding="utf-8"), 0)
    assert api, "docs/api.md has no curl example"
    return readme + api


# -- running -------------------------------------------------------------------------------------
def _substitute(step: Step, tour: Tour, used: set[str]) -> str:
    text = step.text
    for key, value in SUBSTITUTIONS.items():
        if key in text:
            used.add(key)
            text = text.replace(key, value(tour))
    left = re.findall(r"<[A-Za-z_]+>", text)
    assert not left, f"{step.where}: no substitution for {left} in {step.text!r}"
    return text


def _bash(tour: Tour, text: str, headers: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "DETCAL": tour.url, "TOKEN": tour.token,
           "DOCTOUR_HEADERS": str(headers)}
    return subprocess.run(["bash", "-c", PREAMBLE + text], cwd=tour.workdir, env=env,
                          capture_output=True, text=True, timeout=300, check=False)


def _last_response(headers: Path) -> tuple[int, str]:
    """Status and content type of the final response in a `--dump-header` file."""
    blocks = [b for b in re.split(r"\r?\n\r?\n", headers.read_text(errors="replace"))
              if b.startswith("HTTP/")]
    assert blocks, "curl wrote no response headers"
    lines = blocks[-1].splitlines()
    ctype = next((v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])
                  if k.strip().lower() == "content-type"), "")
    return int(lines[0].split()[1]), ctype


def run_step(step: Step, tour: Tour, used: set[str]) -> Any:
    """Run one step; its parsed JSON answer for a curl step, else None."""
    if step.kind == "skip":
        tour.ran.append(f"skipped {step.where} ({SKIPPED[step.words[0]]})")
        return None
    text = _substitute(step, tour, used)
    for name, make in INPUTS.items():
        if re.search(rf"@{re.escape(name)}\b", text) and not (tour.workdir / name).exists():
            make(tour.workdir)
    headers = tour.workdir / ".headers"
    headers.unlink(missing_ok=True)
    if step.kind == "export":
        names = [w.split("=", 1)[0] for w in step.words[1:] if "=" in w]
        assert names, f"{step.where}: an export that sets nothing: {step.text!r}"
        text += "\nprintf '%s\\n' " + " ".join(f'"${n}"' for n in names)
    proc = _bash(tour, text, headers)
    context = (f"{step.where}: `{text}` exited {proc.returncode}\nstdout: "
               f"{proc.stdout[-3000:]}\nstderr: {proc.stderr[-3000:]}")
    status, ctype = _last_response(headers) if headers.exists() else (None, "")
    if status is not None:
        context += f"\nHTTP {status} ({ctype})"
    assert proc.returncode == 0, context
    tour.ran.append(f"{step.where}: {text.splitlines()[0][:100]}")
    if step.kind == "export":
        expected = {"DETCAL": tour.url, "TOKEN": tour.token}
        got = dict(zip(names, proc.stdout.splitlines(), strict=True))
        for name, value in got.items():
            assert value == expected.get(name, value), f"{step.where}: {name}={value!r}"
        return None
    if step.kind != "curl":
        return None
    assert status is not None and status < 400, context
    out = step.output_file
    body = (tour.workdir / out).read_text() if out else proc.stdout
    route = step.route
    if route in NON_JSON:
        assert ctype.startswith(NON_JSON[route]), context
        return None
    assert ctype.startswith("application/json"), context
    try:
        return json.loads(body)
    except json.JSONDecodeError as exc:
        raise AssertionError(f"{context}\nnot JSON: {exc}") from exc


def watch_job(step: Step, tour: Tour, used: set[str], answer: dict,
              timeout_s: float = 120.0) -> dict:
    """Run a `GET /v1/jobs/{id}` step again until its job lands; it must succeed."""
    deadline = time.monotonic() + timeout_s
    while answer["state"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, f"{step.where}: job still {answer['state']}"
        time.sleep(0.2)
        answer = run_step(step, tour, used)
    assert answer["state"] == "succeeded", f"{step.where}: {answer}"
    return answer


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


def _resolve(spec: dict, node: dict) -> dict:
    while "$ref" in node:
        node = spec["components"]["schemas"][node["$ref"].rsplit("/", 1)[1]]
    return node


def _examples(node: dict) -> list:
    """A schema's or parameter's own examples (also those of its anyOf/oneOf branches)."""
    out = list(node.get("examples", []) if isinstance(node.get("examples"), list) else [])
    if isinstance(node.get("examples"), dict):          # media type / parameter: name -> {value}
        out += [e["value"] for e in node["examples"].values() if "value" in e]
    if "example" in node:
        out.append(node["example"])
    for branch in node.get("anyOf", []) + node.get("oneOf", []):
        out += _examples(branch)
    return out


def _parts(spec: dict, schema: dict, value: Any, path: tuple) -> Iterator[tuple[tuple, Any]]:
    """(path, example) of every sub-schema of `schema` below the body, walking `value`."""
    schema = _resolve(spec, schema)
    if path:
        for ex in _examples(schema):
            yield path, ex
    for branch in schema.get("anyOf", []) + schema.get("oneOf", []):
        if "$ref" in branch or "properties" in branch or "items" in branch:
            yield from _parts(spec, {**branch, "examples": []}, value, path)
    if isinstance(value, dict):
        props = schema.get("properties", {})
        for key, sub in props.items():
            yield from _parts(spec, sub, value.get(key), (*path, key))
        extra = schema.get("additionalProperties")
        if isinstance(extra, dict):
            for key in value.keys() - props.keys():
                yield from _parts(spec, extra, value[key], (*path, key))
    elif isinstance(value, list) and value and isinstance(schema.get("items"), dict):
        yield from _parts(spec, schema["items"], value[0], (*path, 0))


def _set(body: Any, path: tuple, value: Any) -> Any:
    body = copy.deepcopy(body)
    node = body
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return body


# Path parameters that have no example of their own, for an operation that has some.
FILL = {"version": "1"}


def openapi_requests(spec: dict) -> list[tuple[str, str, dict, Any]]:
    """(method, path, query, json body) for every example of the JSON request bodies and of
    the parameters; refuses an operation it cannot fill."""
    requests: list[tuple[str, str, dict, Any]] = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            media = op.get("requestBody", {}).get("content", {}).get("application/json")
            bodies: list[Any] = []
            if media is not None:
                schema = media["schema"]
                bodies = _examples(media) + _examples(_resolve(spec, schema))
                assert bodies, f"{method.upper()} {path}: a JSON body without an example"
                for part_path, ex in _parts(spec, schema, bodies[0], ()):
                    bodies.append(_set(bodies[0], part_path, ex))
            params = op.get("parameters", [])
            with_examples = [(p, ex) for p in params for ex in _examples(p)
                             + _examples(p.get("schema", {}))]
            if not bodies and not with_examples:
                continue
            defaults = {}
            for p in params:
                if p.get("required"):
                    own = _examples(p) + _examples(p.get("schema", {}))
                    assert own or p["name"] in FILL, f"{method.upper()} {path}: no {p['name']}"
                    defaults[p["name"]] = str(own[0]) if own else FILL[p["name"]]
            body = bodies[0] if bodies else None
            variants = [(defaults, b) for b in bodies]
            variants += [({**defaults, p["name"]: ex}, body) for p, ex in with_examples]
            for values, b in variants:
                url = path
                query = {}
                for p in params:
                    if p["name"] not in values:
                        continue
                    if p["in"] == "path":
                        url = url.replace("{" + p["name"] + "}", str(values[p["name"]]))
                    else:
                        query[p["name"]] = values[p["name"]]
                key = (method, url, json.dumps(query, sort_keys=True), json.dumps(b))
                if key not in {(m, u, json.dumps(q, sort_keys=True), json.dumps(x))
                               for m, u, q, x in requests}:
                    requests.append((method, url, query, b))
    return requests


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
