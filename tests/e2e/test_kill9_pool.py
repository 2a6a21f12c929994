"""`kill -9` of a server whose calibrate pool runs leaves no process of its tree behind: the
pool worker (parent-death signal, parent watch) and the multiprocessing resource tracker (its
pipe closes) are gone within 5 s."""

from __future__ import annotations

import json
import os
import signal
import time
from collections.abc import Iterator

import httpx
import pytest

from tests.e2e.conftest import Server, serving
from tests.e2e.proc_tree import detcal_processes_of, tree

pytestmark = pytest.mark.e2e


def _start_pool(url: str) -> None:
    """A calibrate body over `offload_bytes` (1 MiB): parsed in a pool worker (a 4xx there)."""
    body = json.dumps({"frames": [{"frame_id": "x" * 64, "detections": []}] * 20_000})
    assert len(body) > 2**20
    r = httpx.post(f"{url}/v1/calibrate", content=body,
                   headers={"content-type": "application/json"}, timeout=60)
    assert r.status_code < 500, r.text


@pytest.fixture(params=[1, 2], ids=["workers1", "workers2"])
def killed_server(request, tmp_path) -> Iterator[Server]:
    srv = Server(tmp_path / "data")
    srv.serve_args = ("--workers", "2") if request.param == 2 else ()
    yield from serving(srv)


def test_kill9_leaves_no_pool_worker_or_tracker(killed_server):
    pid = killed_server.proc.pid
    _start_pool(killed_server.url)
    members = tree(pid)
    children = [p for p in members if p != pid]
    assert len(children) >= 2, f"expected a pool worker and a resource tracker: {members}"
    os.kill(pid, signal.SIGKILL)
    killed_server.proc.wait(10)
    deadline = time.monotonic() + 5.0
    left = detcal_processes_of(children)
    while left and time.monotonic() < deadline:
        time.sleep(0.1)
        left = detcal_processes_of(children)
    for p in left:   # do not leave them running for the rest of the suite
        os.kill(p, signal.SIGKILL)
    assert not left, f"still alive 5 s after kill -9 of the server: {left}"
