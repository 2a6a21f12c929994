"""`detcal serve --workers 2`: two uvicorn worker processes behind one port answer as one
server: /metrics from either sums both workers' counters (Prometheus multiprocess mode), and a
version activated through one worker is what every worker serves next."""

from __future__ import annotations

import re
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor

import httpx
import pytest

from tests.e2e.conftest import TOKEN, Server, serving

pytestmark = pytest.mark.e2e

ADMIN = {"Authorization": f"Bearer {TOKEN}"}


class WorkersServer(Server):
    serve_args = ("--workers", "2")


@pytest.fixture(scope="module")
def two_workers(tmp_path_factory, dump) -> Iterator[WorkersServer]:
    from app.settings import Settings
    from app.store import Store
    from calibrators.fit import fit_profile

    data = tmp_path_factory.mktemp("workers") / "data"
    settings = Settings(data_dir=data)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    text = fit_profile(dump, cov_source="given").to_json()
    store.add_profile("lidar", text)                    # v1, active
    store.add_profile("lidar", text, activate=False)    # v2
    store.close()
    yield from serving(WorkersServer(data))


def _frame(dump, n: int) -> dict:
    return {"frame_id": "f", "detections": [
        {"logits": dump.det_logits[i, -1].tolist(), "box": dump.det_boxes[i, -1].tolist(),
         "covariance": dump.det_cov[i].tolist()} for i in range(n)]}


def _sample(text: str, name: str, **labels: str) -> float:
    total = 0.0
    for line in text.splitlines():
        if not line.startswith(name + "{"):
            continue
        if all(f'{k}="{v}"' in line for k, v in labels.items()):
            total += float(line.rsplit(" ", 1)[1])
    return total


def test_metrics_sum_every_worker_and_activation_reaches_every_worker(two_workers, dump):
    url = two_workers.url
    body = {"frames": [_frame(dump, 3)]}

    def calibrate(_: int) -> int:
        with httpx.Client(base_url=url, timeout=30.0) as c:
            return c.post("/v1/calibrate", json=body).json()["profile"]["version"]

    # the kernel spreads connections over the two workers' accept queues, but nothing makes
    # it: send rounds of requests until both workers have counted some (each writes its own
    # counter file), then check that every scrape sums both
    files = two_workers.data_dir / "prometheus"
    rounds = 0
    while rounds < 20:
        rounds += 1
        with ThreadPoolExecutor(4) as pool:
            assert set(pool.map(calibrate, range(40))) == {1}
        pids = {f.stem.rsplit("_", 1)[1] for f in files.glob("counter_*.db")}
        if len(pids) >= 2:
            break
    assert len(pids) >= 2, f"one worker served {40 * rounds} requests: {pids}"
    want = (120.0 * rounds, 40.0 * rounds)
    scrapes = []
    for _ in range(8):        # fresh connections: any worker may answer
        text = httpx.get(f"{url}/metrics", timeout=10.0).text
        scrapes.append((_sample(text, "detcal_detections_calibrated_total", profile="lidar"),
                        _sample(text, "detcal_http_requests_total", route="/v1/calibrate")))
        assert re.search(r"^detcal_active_profile_version\{.*\} 1\.0$", text, re.M), text[-500:]
    assert set(scrapes) == {want}, scrapes
    r = httpx.post(f"{url}/v1/profiles/lidar/2/activate", headers=ADMIN, timeout=10.0)
    assert r.status_code == 200, r.text
    with ThreadPoolExecutor(4) as pool:
        assert set(pool.map(calibrate, range(20))) == {2}
