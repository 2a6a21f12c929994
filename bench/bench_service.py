"""Latency and throughput of POST /v1/calibrate (one 300-detection frame) as JSON and as an
Arrow stream, against a bare FastAPI echo endpoint receiving the same JSON, all real uvicorn
processes on loopback. The JSON and Arrow answers are checked bit-equal first.

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


def serve_detcal(data_dir: Path, profile_json: str, port: int, *serve_args: str,
                 env: dict[str, str] | None = None) -> subprocess.Popen:
    """A `detcal serve` process on `port` over a new store in `data_dir` holding
    `profile_json` as the active `lidar`; `serve_args` are extra `detcal serve` options."""
    from app.settings import Settings
    from app.store import Store

    settings = Settings(data_dir=data_dir)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    store.add_profile("lidar", profile_json)
    store.close()
    detcal = ROOT / ".venv" / "bin" / "detcal"
    cmd = [str(detcal)] if detcal.exists() else [sys.executable, "-m", "app.cli"]
    return subprocess.Popen([*cmd, "serve", "--port", str(port), "--data-dir", str(data_dir),
                             *serve_args, "--log-level", "warning"], cwd=ROOT,
                            env={**os.environ, **(env or {})}, stdout=subprocess.DEVNULL)


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


def _arrow(payload: dict) -> bytes:
    """The frames of `payload` as an Arrow IPC stream (float64 columns, as JSON parses)."""
    import pyarrow as pa

    from calibrators.io.arrow_batch import write_stream

    dets = [d for f in payload["frames"] for d in f["detections"]]
    frame_ids = [f["frame_id"] for f in payload["frames"] for _ in f["detections"]]

    def col(key: str) -> pa.Array:
        a = np.array([np.ravel(d[key]) for d in dets], dtype=np.float64)
        return pa.FixedSizeListArray.from_arrays(pa.array(a.ravel()), a.shape[1])

    return write_stream(pa.record_batch({
        "frame_id": pa.array(frame_ids), "id": pa.array([d["id"] for d in dets]),
        "logits": col("logits"), "box": col("box"), "covariance": col("covariance")}))


def _bit_equal(client: httpx.Client, url: str, body: bytes, arrow: bytes) -> bool:
    """Whether the JSON and the Arrow answers carry the same floats, bit for bit."""
    import pyarrow as pa

    from calibrators.io.arrow_batch import ARROW_STREAM

    dets = client.post(url, content=body, headers={"content-type": "application/json"}
                       ).json()["frames"][0]["detections"]
    r = client.post(url, content=arrow, headers={"content-type": ARROW_STREAM})
    r.raise_for_status()
    table = pa.ipc.open_stream(r.content).read_all()
    json_cols = {"score": [d["score"] for d in dets], "score_raw": [d["score_raw"] for d in dets],
                 "covariance": [np.ravel(d["covariance"]).tolist() for d in dets],
                 "ellipse": [[d["ellipse"][k] for k in ("semi_major", "semi_minor", "angle")]
                             for d in dets]}
    arrow_cols = {"score": table["score"].to_pylist(),
                  "score_raw": table["score_raw"].to_pylist(),
                  "covariance": table["covariance"].to_pylist(),
                  "ellipse": [list(e.values()) for e in table["ellipse"].to_pylist()]}
    return all(np.array_equal(np.asarray(json_cols[k]), np.asarray(arrow_cols[k]))
               for k in json_cols)


def _measure(client: httpx.Client, url: str, body: bytes, n: int, concurrency: int,
             media: str = "application/json") -> dict:
    headers = {"content-type": media}
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
    ap.add_argument("--batch-frames", type=int, default=10,
                    help="frames per request of the second JSON / Arrow comparison")
    args = ap.parse_args(argv)

    from calibrators.io.arrow_batch import ARROW_STREAM

    payload, profile_json = _payload()
    body = json.dumps(payload).encode()
    arrow = _arrow(payload)
    batched = {"frames": [{**payload["frames"][0], "frame_id": f"bench-{i}"}
                          for i in range(args.batch_frames)]}
    body_k, arrow_k = json.dumps(batched).encode(), _arrow(batched)
    procs = []
    with tempfile.TemporaryDirectory() as tmp:
        p_app, p_echo = _port(), _port()
        try:
            procs.append(serve_detcal(Path(tmp) / "data", profile_json, p_app,
                                      env={"DETCAL_ADMIN_TOKEN": "bench"}))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "bench._echo_app:app", "--port", str(p_echo),
                 "--log-level", "warning"], cwd=ROOT, stdout=subprocess.DEVNULL))
            _wait(f"http://127.0.0.1:{p_app}/healthz", procs[0])
            _wait(f"http://127.0.0.1:{p_echo}/docs", procs[1])
            with httpx.Client(timeout=30.0) as client:
                echo = _measure(client, f"http://127.0.0.1:{p_echo}/echo", body,
                                args.requests, args.concurrency)
                url = f"http://127.0.0.1:{p_app}/v1/calibrate"
                same = _bit_equal(client, url, body, arrow)
                cal = _measure(client, url, body, args.requests, args.concurrency)
                fast = _measure(client, url, arrow, args.requests, args.concurrency, ARROW_STREAM)
                n_k = max(20, args.requests // args.batch_frames)
                cal_k = _measure(client, url, body_k, n_k, args.concurrency)
                fast_k = _measure(client, url, arrow_k, n_k, args.concurrency, ARROW_STREAM)
        finally:
            for p in procs:
                p.terminate()
                p.wait(10)
    ratio = cal["server_p50"] / echo["server_p50"]
    lat_ratio = cal["latency_p50"] / echo["latency_p50"]
    n_det = len(payload["frames"][0]["detections"])
    table = (
        f"POST /v1/calibrate, frames of {n_det} detections (logits [10], box [9], covariance "
        f"2x2), one per request as JSON (request {len(body) / 1024:.0f} KiB) and as an Arrow "
        f"stream ({len(arrow) / 1024:.0f} KiB), {args.requests} sequential requests, then "
        f"{args.requests} with {args.concurrency} concurrent clients; then {args.batch_frames} "
        f"frames per request (JSON {len(body_k) / 1024:.0f} KiB, Arrow "
        f"{len(arrow_k) / 1024:.0f} KiB) the same way; reference: a bare FastAPI "
        f"endpoint that parses the same JSON and echoes it. All are uvicorn processes on "
        f"loopback, one worker each; the clients (httpx) run on the same 2 cores.\n\n"
        "| endpoint | frames / request | server p50 ms | server p95 ms | latency p50 ms | "
        "latency p95 ms | throughput req/s | detections/s |\n|---|---|---|---|---|---|---|---|\n"
        + "".join(f"| {name} | {k} | {m['server_p50']:.2f} | {m['server_p95']:.2f} | "
                  f"{m['latency_p50']:.2f} | {m['latency_p95']:.2f} | {m['rps']:.1f} | "
                  f"{m['rps'] * n_det * k:,.0f} |\n"
                  for name, k, m in (("/v1/calibrate JSON", 1, cal),
                                     ("/v1/calibrate Arrow", 1, fast),
                                     ("echo (reference)", 1, echo),
                                     ("/v1/calibrate JSON", args.batch_frames, cal_k),
                                     ("/v1/calibrate Arrow", args.batch_frames, fast_k)))
        + f"\n**Ratio JSON calibrate / echo: {ratio:.2f}× server time (p50)** (target ≤ 1.0×), "
          f"{lat_ratio:.2f}× client latency (p50). **Arrow / JSON, detections/s: "
          f"{fast['rps'] / cal['rps']:.1f}× with one frame per request, "
          f"{fast_k['rps'] / cal_k['rps']:.1f}× with {args.batch_frames}** (target ≥ 5×); server "
          f"time {cal['server_p50'] / fast['server_p50']:.1f}× / "
          f"{cal_k['server_p50'] / fast_k['server_p50']:.1f}× less. With one frame the fixed "
          f"cost of an HTTP request (uvicorn, FastAPI, the client) dominates the Arrow path. "
          f"Calibrated values of the two formats bit-equal: {'yes' if same else 'NO'}.\n")
    from bench._report import report

    return report("service", table)


if __name__ == "__main__":
    sys.exit(main())
