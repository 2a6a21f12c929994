"""/healthz latency and server RSS while the largest allowed calibrate requests are served.

    .venv/bin/python -m bench.bench_health [--seconds 20] [--detections 20000] [--clients 2]

A real `detcal serve` process (one worker) receives back-to-back POST /v1/calibrate requests
of `--detections` detections (the default `DETCAL_MAX_DETECTIONS`, as large as the request
limits allow) from `--clients` clients, while another polls GET /healthz every 20 ms. The
reference is the same /healthz poll with the server idle, measured first in the same run.
Prints the health latency percentiles (idle and under load, and their ratio), the calibrate
latency and the server's peak RSS increase over idle; writes the `health` section of
docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import numpy as np

from bench.bench_service import free_port, serve_detcal, service_payload, wait_ready


def _rss_mb(pid: int) -> float:
    """Resident set size of `pid` in MiB (Linux /proc)."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def tree_rss_mb(pid: int) -> float:
    """RSS of `pid` and all its descendants (the calibrate worker processes) in MiB."""
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        try:
            total += _rss_mb(p)
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as fh:
                    todo.extend(int(c) for c in fh.read().split())
        except (FileNotFoundError, ProcessLookupError):
            continue
    return total


def _poll_health(url: str, stop: threading.Event, out: list[float]) -> None:
    with httpx.Client(timeout=30.0) as client:
        while not stop.is_set():
            t0 = time.perf_counter()
            client.get(url).raise_for_status()
            out.append((time.perf_counter() - t0) * 1000.0)
            stop.wait(0.02)


@dataclass
class _Figures:
    """What one run measured: /healthz and calibrate latencies (ms) and RSS (MiB)."""

    idle: list[float] = field(default_factory=list)
    loaded: list[float] = field(default_factory=list)
    calib: list[float] = field(default_factory=list)
    rss_idle: float = 0.0
    rss_warm: float = 0.0
    rss_peak: float = 0.0


def _poll_while(base: str, out: list[float]) -> tuple[threading.Event, threading.Thread]:
    """A started /healthz poller appending to `out` until its event is set."""
    stop = threading.Event()
    poller = threading.Thread(target=_poll_health, args=(f"{base}/healthz", stop, out))
    poller.start()
    return stop, poller


def _under_load(base: str, body: bytes, pid: int, args: argparse.Namespace,
                fig: _Figures) -> None:
    """Poll /healthz while `args.clients` clients send calibrate requests for `args.seconds`,
    sampling the server's RSS peak."""
    stop = threading.Event()
    poller = threading.Thread(target=_poll_health, args=(f"{base}/healthz", stop, fig.loaded))

    def load() -> None:
        with httpx.Client(timeout=120.0) as client:
            while not stop.is_set():
                t0 = time.perf_counter()
                r = client.post(f"{base}/v1/calibrate", content=body,
                                headers={"content-type": "application/json"})
                r.raise_for_status()
                fig.calib.append((time.perf_counter() - t0) * 1000.0)

    workers = [threading.Thread(target=load) for _ in range(args.clients)]
    poller.start()
    for w in workers:
        w.start()
    deadline = time.monotonic() + args.seconds
    while time.monotonic() < deadline:
        fig.rss_peak = max(fig.rss_peak, tree_rss_mb(pid))
        time.sleep(0.05)
    stop.set()
    for t in (poller, *workers):
        t.join()


def _measure(args: argparse.Namespace, body: bytes, profile_json: str) -> _Figures:
    """Serve detcal, poll it idle, warm it with one large request, then load it."""
    fig = _Figures()
    with tempfile.TemporaryDirectory() as tmp:
        port = free_port()
        proc = serve_detcal(Path(tmp) / "data", profile_json, port, env={
            "DETCAL_ADMIN_TOKEN": "bench-health-token",
            "DETCAL_MAX_REQUEST_BYTES": str(max(len(body) + 1024, 8 * 2**20))})
        base = f"http://127.0.0.1:{port}"
        try:
            wait_ready(f"{base}/healthz", proc)
            stop, poller = _poll_while(base, fig.idle)
            time.sleep(min(5.0, args.seconds / 4))
            stop.set()
            poller.join()
            fig.rss_idle = tree_rss_mb(proc.pid)
            # one large request first: the calibrate worker process starts on the first one
            httpx.post(f"{base}/v1/calibrate", content=body, timeout=120.0,
                       headers={"content-type": "application/json"}).raise_for_status()
            time.sleep(1.0)
            fig.rss_warm = tree_rss_mb(proc.pid)
            fig.rss_peak = fig.rss_warm
            _under_load(base, body, proc.pid, args, fig)
        finally:
            proc.terminate()
            proc.wait(10)
    return fig


def _table(args: argparse.Namespace, body: bytes, fig: _Figures) -> str:
    """The `health` section of docs/benchmarks.md."""
    idle, loaded, calib = fig.idle, fig.loaded, fig.calib
    rss_idle, rss_warm, rss_peak = fig.rss_idle, fig.rss_warm, fig.rss_peak
    p = {name: (float(np.percentile(v, 50)), float(np.percentile(v, 99)))
         for name, v in (("idle", idle), ("load", loaded))}
    return (
        f"GET /healthz polled every 20 ms while {args.clients} client(s) send back-to-back POST "
        f"/v1/calibrate requests of {args.detections} detections each (the default "
        f"`DETCAL_MAX_DETECTIONS`; request {len(body) / 2**20:.1f} MiB) for {args.seconds:.0f} "
        f"s; reference: the same poll with the server idle, in the same run. One uvicorn "
        f"worker on loopback, default `DETCAL_CALIBRATE_PROCESSES` "
        f"(1) and `DETCAL_OFFLOAD_BYTES` (1 MiB).\n\n"
        "| | /healthz p50 ms | /healthz p99 ms | polls |\n|---|---|---|---|\n"
        f"| idle (reference) | {p['idle'][0]:.2f} | {p['idle'][1]:.2f} | {len(idle)} |\n"
        f"| under load | {p['load'][0]:.2f} | {p['load'][1]:.2f} | {len(loaded)} |\n\n"
        f"**Ratio under load / idle: {p['load'][1] / p['idle'][1]:.1f}× p99** (target: p99 "
        f"≤ 100 ms under load). Calibrate requests served: {len(calib)}, latency p50 "
        f"{np.percentile(calib, 50):.0f} ms, p99 {np.percentile(calib, 99):.0f} ms. RSS of "
        f"the server and its calibrate worker processes together: {rss_idle:.0f} MiB idle, "
        f"{rss_warm:.0f} MiB after the first large request (workers started), peak "
        f"{rss_peak:.0f} MiB under load (+{rss_peak - rss_warm:.0f} MiB over warm idle, "
        f"{(rss_peak - rss_warm) / args.clients:.0f} MiB per request in flight; target ≤ "
        f"+256 MiB a request).\n")


def main(argv: list[str] | None = None) -> int:
    """Run the server idle, then under load; print and record the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0)
    ap.add_argument("--detections", type=int, default=20_000)
    ap.add_argument("--clients", type=int, default=2, help="concurrent calibrate clients")
    args = ap.parse_args(argv)

    payload, profile_json = service_payload(args.detections)
    body = json.dumps(payload, separators=(",", ":")).encode()
    fig = _measure(args, body, profile_json)
    from bench._report import report

    return report("health", _table(args, body, fig))


if __name__ == "__main__":
    sys.exit(main())
