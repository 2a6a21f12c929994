"""Mutated Arrow streams against a running `detcal serve`, with what a hostile client must not
achieve measured alongside: a 5xx or a dropped connection, a 200 whose stream fails
`validate(full=True)`, a server process that dies, a request that raises the server tree's
peak resident memory by more than its budget, `/healthz` slowed for everyone else (polled
from another thread the whole time)."""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np
import pyarrow as pa

from calibrators.io.arrow_batch import ARROW_STREAM
from tests.arrow_mutator import COMPRESSIONS, mutate, request_batch, stream
from tests.e2e.conftest import ADMIN, Server, wait_job
from tests.e2e.proc_tree import PeakProbe, alive, tree


@contextmanager
def fitted_server(data_dir: Path, dump_npz: bytes, workers: int = 1) -> Iterator[Server]:
    """A running `detcal serve` (`workers` uvicorn workers) on `data_dir` whose profile `lidar`
    is fit on `dump_npz`; stopped on exit."""
    srv = Server(data_dir)
    srv.serve_args = ("--workers", str(workers)) if workers > 1 else ()
    srv.start()
    try:
        r = httpx.post(f"{srv.url}/v1/fit", headers=ADMIN, files={"dump": ("v.npz", dump_npz)},
                       data={"name": "lidar"}, timeout=60)
        assert r.status_code == 202, r.text
        with httpx.Client(base_url=srv.url, timeout=30) as http:
            assert wait_job(http, r.json()["job_id"])["state"] == "succeeded"
        yield srv
    finally:
        srv.stop()


@dataclass
class FuzzReport:
    """What `fuzz` saw. statuses: response status counts (0: transport error); failures:
    what broke a rule (the mutation and why); max_rise_mb: the largest peak RSS rise of the
    server tree over one request; health_ms: /healthz latencies."""

    cases: int = 0
    statuses: Counter = field(default_factory=Counter)
    failures: list[str] = field(default_factory=list)
    max_rise_mb: float = 0.0
    health_ms: list[float] = field(default_factory=list)
    seconds: float = 0.0

    def health_p99_ms(self) -> float:
        """99th percentile of the /healthz latencies, ms."""
        return float(np.percentile(self.health_ms, 99)) if self.health_ms else float("nan")

    def summary(self) -> str:
        """One line for logs and the closing note."""
        return (f"{self.cases} cases in {self.seconds:.1f} s: statuses {dict(self.statuses)}, "
                f"{len(self.failures)} failures, max RSS rise {self.max_rise_mb:.1f} MB, "
                f"/healthz p99 {self.health_p99_ms():.1f} ms, max "
                f"{max(self.health_ms, default=float('nan')):.1f} ms over "
                f"{len(self.health_ms)} polls")


class HealthPoller(threading.Thread):
    """GET /healthz every `every_s` until stopped, recording each latency (a failure counts
    as 10 s)."""

    def __init__(self, url: str, every_s: float = 0.02) -> None:
        super().__init__(daemon=True)
        self.url, self.every_s = url, every_s
        self.latencies_ms: list[float] = []
        self.stop = threading.Event()

    def run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=10.0) as client:
            while not self.stop.wait(self.every_s):
                t0 = time.perf_counter()
                try:
                    ok = client.get("/healthz").status_code == 200
                except httpx.HTTPError:
                    ok = False
                self.latencies_ms.append((time.perf_counter() - t0) * 1e3 if ok else 1e4)


def bases(dump, sizes: tuple[int, ...] = (1, 40, 300, 2500)) -> list[tuple[bytes, pa.Schema]]:
    """Valid request streams to mutate: every column variant, codec, one or two batches."""
    out = []
    for n in sizes:
        for variant in range(4):
            batch = request_batch(dump, n, variant=variant)
            for codec in COMPRESSIONS:
                parts = [batch] if n < 2 else [batch.slice(0, n // 3), batch.slice(n // 3)]
                out.append((stream(parts, codec), batch.schema))
    return out


def fuzz(url: str, server_pid: int, dump, cases: int, seed: int, *,
         budget_mb: float = 256.0, time_limit_s: float | None = None) -> FuzzReport:
    """Send `cases` mutated streams (seeded) to the server at `url` whose main process is
    `server_pid`, one at a time, checking each answer (module docstring)."""
    rng = np.random.default_rng(seed)
    streams = bases(dump)
    members = tree(server_pid)
    probe = PeakProbe(members)
    report = FuzzReport()
    poller = HealthPoller(url)
    poller.start()
    t0 = time.monotonic()
    try:
        with httpx.Client(base_url=url, timeout=60.0) as client:
            for k in range(cases):
                if time_limit_s is not None and time.monotonic() - t0 > time_limit_s:
                    break
                data, schema = streams[int(rng.integers(len(streams)))]
                bad, what = mutate(data, schema, rng)
                probe.start()
                status = _send(client, bad)
                rise = probe.rise_mb()
                report.cases += 1
                report.statuses[status[0]] += 1
                report.max_rise_mb = max(report.max_rise_mb, rise)
                problem = status[1] or (f"RSS rise {rise:.0f} MB" if rise > budget_mb else "")
                if problem:
                    report.failures.append(f"case {k} ({what}): {problem}")
                if status[0] == 0 and not alive(server_pid):
                    report.failures.append(f"case {k} ({what}): the server died")
                    break
    finally:
        poller.stop.set()
        poller.join()
        report.seconds = time.monotonic() - t0
        report.health_ms = poller.latencies_ms
    dead = [p for p in members if not alive(p)]
    if dead:
        report.failures.append(f"server processes gone: {dead}")
    return report


def _send(client: httpx.Client, data: bytes) -> tuple[int, str]:
    """(status or 0, what was wrong with the answer or '')."""
    try:
        r = client.post("/v1/calibrate", content=data,
                        headers={"content-type": ARROW_STREAM})
    except httpx.HTTPError as exc:
        return 0, f"transport error {type(exc).__name__}: {exc}"
    if r.status_code >= 500:
        return r.status_code, f"{r.status_code}: {r.text[:200]}"
    if r.status_code == 200:
        try:
            with pa.ipc.open_stream(r.content) as reader:
                for batch in reader:
                    batch.validate(full=True)
        except (pa.ArrowException, ValueError) as exc:
            return 200, f"200 whose stream fails validate(full=True): {exc}"
    return r.status_code, ""
