"""A steady open-loop load on POST /v1/calibrate: latency percentiles, errors and RSS growth.

    .venv/bin/python -m bench.bench_steady [--workers 2] [--rate 50] [--seconds 300]

A real `detcal serve --workers N` process tree receives one JSON frame of 300 detections
every 1/rate seconds (open loop: a request is sent on schedule whether or not the previous
ones have been answered, from a pool of client threads), for `--seconds`. Prints the client
latency p50 / p99 / max, the errors, the requests that left late (the client could not keep
the schedule), and the RSS of the server's process tree (uvicorn's supervisor, its workers
and their calibrate worker processes) after a 10 s warm-up and at the end; the reference is
the same load on `--workers 1`, measured first in the same run. Writes the `steady` section
of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np

from bench.bench_health import tree_rss_mb
from bench.bench_service import free_port, serve_detcal, service_payload, wait_ready


def _run(workers: int, rate: float, seconds: float, body: bytes, profile_json: str) -> dict:
    """One server with `workers` workers under the steady load; its figures."""
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        proc = serve_detcal(Path(tmp) / "data", profile_json, port, "--workers", str(workers),
                            env={"DETCAL_ADMIN_TOKEN": "bench-steady-token"})
        url = f"http://127.0.0.1:{port}/v1/calibrate"
        headers = {"content-type": "application/json"}
        try:
            wait_ready(f"http://127.0.0.1:{port}/healthz", proc)
            latencies: list[float] = []
            late, errors = [0], [0]
            lock = threading.Lock()
            local = threading.local()

            def one(due: float) -> None:
                client = getattr(local, "client", None)
                if client is None:
                    client = local.client = httpx.Client(timeout=30.0)
                now = time.perf_counter()
                if now < due:
                    time.sleep(due - now)
                elif now - due > 0.005:
                    with lock:
                        late[0] += 1
                t0 = time.perf_counter()
                try:
                    ok = client.post(url, content=body, headers=headers).status_code == 200
                except httpx.HTTPError:
                    ok = False
                dt = (time.perf_counter() - t0) * 1000.0
                with lock:
                    latencies.append(dt)
                    errors[0] += not ok

            with ThreadPoolExecutor(16) as pool:
                start = time.perf_counter() + 0.5
                warm = int(10 * rate)
                for i in range(warm):                       # 10 s of warm-up, not counted
                    pool.submit(one, start + i / rate)
                time.sleep(max(0.0, start + warm / rate - time.perf_counter()) + 1.0)
                with lock:
                    latencies.clear()
                    late[0] = errors[0] = 0
                rss_start = tree_rss_mb(proc.pid)
                start = time.perf_counter() + 0.5
                total = int(seconds * rate)
                futures = [pool.submit(one, start + i / rate) for i in range(total)]
                rss_peak = rss_start
                while not all(f.done() for f in futures):
                    rss_peak = max(rss_peak, tree_rss_mb(proc.pid))
                    time.sleep(1.0)
            rss_end = tree_rss_mb(proc.pid)
        finally:
            proc.terminate()
            proc.wait(20)
    lat = np.asarray(latencies)
    return {"workers": workers, "n": len(lat), "p50": float(np.percentile(lat, 50)),
            "p99": float(np.percentile(lat, 99)), "max": float(lat.max()), "errors": errors[0],
            "late": late[0], "rss_start": rss_start, "rss_end": rss_end, "rss_peak": rss_peak}


def main(argv: list[str] | None = None) -> int:
    """Measure --workers 1 (reference) and --workers N; print and record."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rate", type=float, default=50.0, help="requests per second")
    ap.add_argument("--seconds", type=float, default=300.0)
    ap.add_argument("--reference-seconds", type=float, default=60.0,
                    help="duration of the --workers 1 reference run")
    args = ap.parse_args(argv)
    payload, profile_json = service_payload()
    body = json.dumps(payload).encode()
    ref = _run(1, args.rate, args.reference_seconds, body, profile_json)
    run = _run(args.workers, args.rate, args.seconds, body, profile_json)
    rows = "".join(
        f"| {r['workers']} | {r['n']} | {r['p50']:.2f} | {r['p99']:.2f} | {r['max']:.1f} | "
        f"{r['errors']} | {r['late']} | {r['rss_start']:.0f} → {r['rss_end']:.0f} "
        f"(peak {r['rss_peak']:.0f}) | {100 * (r['rss_end'] / r['rss_start'] - 1):+.1f} % |\n"
        for r in (ref, run))
    table = (
        f"POST /v1/calibrate (JSON, one frame of 300 detections) at a steady {args.rate:g} "
        f"requests/s, open loop, after 10 s of warm-up; `detcal serve --workers "
        f"{args.workers}` for {args.seconds:.0f} s; reference: `--workers 1` for "
        f"{args.reference_seconds:.0f} s in the same run. Client on the same 2 cores.\n\n"
        "| workers | requests | latency p50 ms | p99 ms | max ms | errors | sent late | "
        "process-tree RSS MiB | RSS growth |\n|---|---|---|---|---|---|---|---|---|\n"
        + rows
        + f"\n**--workers {args.workers}: p99 {run['p99']:.1f} ms** (target < 20 ms), "
          f"{run['errors']} errors, RSS growth {100 * (run['rss_end'] / run['rss_start'] - 1):+.1f}"
          f" % (target < 10 %); p99 ratio to one worker: {run['p99'] / ref['p99']:.2f}×.\n")
    from bench._report import report

    return report("steady", table)


if __name__ == "__main__":
    sys.exit(main())
