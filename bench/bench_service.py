"""Latency and throughput of POST /v1/calibrate (one 300-detection frame) against a bare
FastAPI echo endpoint receiving the same JSON, both real uvicorn processes on loopback.

    .venv/bin/python -m bench.bench_service [--requests 300] [--concurrency 4]

Server time is read from each response's `Server-Timing` header (the same middleware in
both apps); client latency includes transfer. Writes the `service` section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(url: str, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            httpx.get(url, timeout=1.0)
            return
        except httpx.TransportError:
            time.sleep(0.1)
    raise RuntimeError(f"{url} did not come up")


def _payload(n: int = 300) -> tuple[dict, str]:
    """A 300-detection frame from a synthetic dump, and the profile JSON fit on that dump."""
    from calibrators.fit import fit_profile
    from calibrators.synthetic import synthetic_dump

    dump = synthetic_dump(n_frames=40, seed=3)
    profile = fit_profile(dump, cov_source="given")
    idx = np.arange(n) % dump.n_detections
    dets = [{"id": int(i), "logits": dump.det_logits[i, -1].tolist(),
             "box": dump.det_boxes[i, -1].tolist(), "covariance": dump.det_cov[i].tolist()}
            for i in idx]
    return {"frames": [{"frame_id": "bench", "detections": dets}]}, profile.to_json()


def _measure(client: httpx.Client, url: str, body: bytes, n: int, concurrency: int) -> dict:
    headers = {"content-type": "application/json"}
    for _ in range(20):                                   # warm-up
        client.post(url, content=body, headers=headers).raise_for_status()
    server, latency = [], []
    for _ in range(n):
        t0 = time.perf_counter()
        r = client.post(url, content=body, headers=headers)
        latency.append((time.perf_counter() - t0) * 1000.0)
        r.raise_for_status()
        server.append(float(r.headers["server-timing"].split("dur=")[1]))

    def one(_: int) -> None:
        client.post(url, content=body, headers=headers).raise_for_status()

    t0 = time.perf_counter()
    with ThreadPoolExecutor(concurrency) as pool:
        list(pool.map(one, range(n)))
    rps = n / (time.perf_counter() - t0)
    return {"server_p50": float(np.median(server)), "server_p95": float(np.percentile(server, 95)),
            "latency_p50": float(np.median(latency)),
            "latency_p95": float(np.percentile(latency, 95)), "rps": rps}


def main(argv: list[str] | None = None) -> int:
    """Run both servers, measure, print the ratio and record it."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=300)
    ap.add_argument("--concurrency", type=int, default=4)
    args = ap.parse_args(argv)

    from app.settings import Settings
    from app.store import Store

    payload, profile_json = _payload()
    body = json.dumps(payload).encode()
    procs = []
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp) / "data")
        store = Store(settings.sqlalchemy_url, settings.dumps_dir)
        store.add_profile("lidar", profile_json)
        store.close()
        p_app, p_echo = _port(), _port()
        env = {**os.environ, "DETCAL_ADMIN_TOKEN": "bench"}
        detcal = ROOT / ".venv" / "bin" / "detcal"
        cmd = [str(detcal)] if detcal.exists() else [sys.executable, "-m", "app.cli"]
        try:
            procs.append(subprocess.Popen(
                [*cmd, "serve", "--port", str(p_app), "--data-dir", str(settings.data_dir),
                 "--log-level", "warning"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "bench._echo_app:app", "--port", str(p_echo),
                 "--log-level", "warning"], cwd=ROOT, stdout=subprocess.DEVNULL))
            _wait(f"http://127.0.0.1:{p_app}/healthz", procs[0])
            _wait(f"http://127.0.0.1:{p_echo}/docs", procs[1])
            with httpx.Client(timeout=30.0) as client:
                echo = _measure(client, f"http://127.0.0.1:{p_echo}/echo", body,
                                args.requests, args.concurrency)
                cal = _measure(client, f"http://127.0.0.1:{p_app}/v1/calibrate", body,
                               args.requests, args.concurrency)
        finally:
            for p in procs:
                p.terminate()
                p.wait(10)
    ratio = cal["server_p50"] / echo["server_p50"]
    lat_ratio = cal["latency_p50"] / echo["latency_p50"]
    table = (
        f"POST /v1/calibrate, one frame of 300 detections (logits [10], box [9], covariance "
        f"2x2; request {len(body) / 1024:.0f} KiB), {args.requests} sequential requests, then "
        f"{args.requests} with {args.concurrency} concurrent clients; reference: a bare FastAPI "
        f"endpoint that parses the same JSON and echoes it. Both are uvicorn processes on "
        f"loopback, one worker each.\n\n"
        "| endpoint | server p50 ms | server p95 ms | latency p50 ms | latency p95 ms | "
        "throughput req/s |\n|---|---|---|---|---|---|\n"
        + "".join(f"| {name} | {m['server_p50']:.2f} | {m['server_p95']:.2f} | "
                  f"{m['latency_p50']:.2f} | {m['latency_p95']:.2f} | {m['rps']:.1f} |\n"
                  for name, m in (("/v1/calibrate", cal), ("echo (reference)", echo)))
        + f"\n**Ratio calibrate / echo: {ratio:.2f}× server time (p50), {lat_ratio:.2f}× "
          f"client latency (p50)** (target ≤ 1.3× server time).\n")
    from bench._report import report

    return report("service", table)


if __name__ == "__main__":
    sys.exit(main())
