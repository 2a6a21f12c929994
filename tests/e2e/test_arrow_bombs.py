"""The hostile Arrow bodies of issue 25 against a real server: the three bombs get a 4xx/413
while the server tree's peak RSS rises by at most 64 MB; the streams that crashed the server
(corrupt string offsets, inline and in a worker thread) and the one that echoed its memory get
a 422 naming the column, and the server keeps answering; the four 500s are 4xx."""

from __future__ import annotations

import time
from collections.abc import Iterator

import httpx
import pytest

from calibrators.io.arrow_batch import ARROW_STREAM
from tests import arrow_bombs as bombs
from tests.e2e.arrow_fuzz import fitted_server
from tests.e2e.conftest import Server
from tests.e2e.proc_tree import PeakProbe, alive, tree

pytestmark = pytest.mark.e2e
BOMB_BUDGET_MB = 64


@pytest.fixture(scope="module")
def bomb_server(tmp_path_factory, dump_npz) -> Iterator[Server]:
    with fitted_server(tmp_path_factory.mktemp("bombs") / "data", dump_npz) as srv:
        yield srv


def _post(srv: Server, data: bytes) -> tuple[httpx.Response, float]:
    """The response to `data` and the server tree's peak RSS rise over it, MB."""
    probe = PeakProbe(tree(srv.proc.pid))
    probe.start()
    r = httpx.post(f"{srv.url}/v1/calibrate", content=data,
                   headers={"content-type": ARROW_STREAM}, timeout=60)
    return r, probe.rise_mb()


@pytest.mark.parametrize(("name", "status", "loc"), [
    ("zstd_bomb", 413, ["body"]),
    ("frame_id_bomb", 422, ["body", "frame_id", 0]),
    ("rows_bomb", 413, ["body"]),
])
def test_bombs_are_refused_within_64_mb(bomb_server, dump, name, status, loc):
    data = bombs.rows_bomb() if name == "rows_bomb" else getattr(bombs, name)(dump)
    r, rise = _post(bomb_server, data)
    print(f"\n{name}: {len(data)} bytes -> {r.status_code}, peak RSS rise {rise:.1f} MB")
    assert r.status_code == status and r.json()["detail"][0]["loc"] == loc, r.text
    assert rise <= BOMB_BUDGET_MB


@pytest.mark.parametrize(("build", "loc"), [
    (lambda d: bombs.segfault(d), ["body", "label"]),
    (lambda d: bombs.segfault(d, rows=3_000), ["body", "label"]),
    (bombs.echo_leak, ["body", "frame_id"]),
    (bombs.zero_rows, ["body"]),
    (bombs.dictionary_index, ["body", "label"]),
    (bombs.zstd_prefix, ["body", "logits"]),
    (bombs.short_id, ["body", "id"]),
], ids=["segfault", "segfault-threaded", "echo", "zero-rows", "dictionary", "prefix", "id"])
def test_the_crash_the_echo_and_the_500s_are_422s(bomb_server, dump, build, loc):
    data = build(dump)
    r, _ = _post(bomb_server, data)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == loc, r.text
    assert alive(bomb_server.proc.pid)
    assert httpx.get(f"{bomb_server.url}/healthz", timeout=5).status_code == 200


def test_a_heavy_compressed_body_runs_off_the_event_loop(bomb_server, dump):
    from tests.e2e.arrow_fuzz import HealthPoller

    data = bombs.heavy_valid(dump)
    poller = HealthPoller(bomb_server.url, every_s=0.01)
    poller.start()
    try:
        t0 = time.perf_counter()
        r, rise = _post(bomb_server, data)
        took = time.perf_counter() - t0
    finally:
        poller.stop.set()
        poller.join()
    print(f"\nheavy: {len(data)} bytes -> {r.status_code} in {took:.2f} s, peak RSS rise "
          f"{rise:.0f} MB, /healthz max {max(poller.latencies_ms):.1f} ms over "
          f"{len(poller.latencies_ms)} polls")
    assert r.status_code == 200, r.text
    assert max(poller.latencies_ms) < max(100.0, took * 1e3 / 3)
    assert rise <= 256
