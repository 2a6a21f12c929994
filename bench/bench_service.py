"""Latency and throughput of POST /v1/calibrate (one 300-detection frame) as JSON and as an
Arrow stream, against a bare FastAPI echo endpoint receiving the same JSON, all real uvicorn
processes on loopback. The JSON and Arrow answers are checked bit-equal first.

    .venv/bin/python -m bench.bench_service [--requests 300] [--clients 2] [--rounds 5]

Server time is read from each response's `Server-Timing` header (the same middleware in
both apps); client latency includes transfer (httpx, sequential). Throughput (detections/s)
is what `--clients` load-generator processes (stdlib `http.client`, one keep-alive
connection each: a few hundred microseconds of client CPU per request, where a threaded
httpx client in one process spent more than the Arrow server did and was the bottleneck)
get through; the formats alternate over `--rounds` rounds, so a slow stretch of this shared
machine hits both, and the ratio is the median of the rounds' ratios. Server CPU per
request (`/proc`, the server process) is the machine-independent view of the same work.
Writes the `service` section of docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
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
    cmd = [str(detcal)] if detcal.exists() else [sys.executable, "-m", "app.cli.main"]
    return subprocess.Popen([*cmd, "serve", "--port", str(port), "--data-dir", str(data_dir),
                             *serve_args, "--log-level", "warning"], cwd=ROOT,
                            env={**os.environ, **(env or {})}, stdout=subprocess.DEVNULL)


def service_payload(n: int = 300) -> tuple[dict, str]:
    """A 300-detection frame from a synthetic dump, and the profile JSON fit on that dump."""
    from calibrators.data import synthetic_dump
    from calibrators.fit import fit_profile

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


def _latency(client: httpx.Client, url: str, body: bytes, n: int,
             media: str = "application/json") -> dict:
    """Sequential requests: server time (Server-Timing) and client latency, p50 and p95."""
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
    return {"server_p50": float(np.median(server)), "server_p95": float(np.percentile(server, 95)),
            "latency_p50": float(np.median(latency)),
            "latency_p95": float(np.percentile(latency, 95))}


def _client(url: str, body: bytes, media: str, n: int) -> None:
    """One load-generator process: `n` POSTs on one keep-alive connection."""
    import http.client

    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port)
    for _ in range(n):
        conn.request("POST", parts.path, body=body, headers={"content-type": media})
        response = conn.getresponse()
        response.read()
        if response.status != 200:
            raise RuntimeError(f"{url}: {response.status}")


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time so far of process `pid` and its live descendants (the
    calibrate worker processes that large bodies go to)."""
    total = 0.0
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        total = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
        for task in Path(f"/proc/{pid}/task").iterdir():
            for child in (task / "children").read_text().split():
                total += _cpu_seconds(int(child))
    except (FileNotFoundError, ProcessLookupError):
        pass
    return total


def _throughput(url: str, body: bytes, media: str, n: int, clients: int, pid: int
                ) -> tuple[float, float]:
    """(requests/s, server CPU ms per request) of `n` requests from `clients` processes."""
    import multiprocessing

    ctx = multiprocessing.get_context("fork")
    procs = [ctx.Process(target=_client, args=(url, body, media, n // clients))
             for _ in range(clients)]
    cpu, t0 = _cpu_seconds(pid), time.perf_counter()
    for p in procs:
        p.start()
    for p in procs:
        p.join()
        if p.exitcode != 0:
            raise RuntimeError(f"a load-generator process failed ({p.exitcode})")
    total = (n // clients) * clients
    return total / (time.perf_counter() - t0), (_cpu_seconds(pid) - cpu) / total * 1000.0


def _rounds(variants: dict[str, tuple[str, bytes, str, int, int]], clients: int, rounds: int
            ) -> dict[str, list[tuple[float, float]]]:
    """Every variant `name: (url, body, media, requests, server pid)` once per round, in
    turn; per variant the rounds' (requests/s, server CPU ms per request)."""
    out: dict[str, list[tuple[float, float]]] = {name: [] for name in variants}
    for _ in range(rounds):
        for name, (url, body, media, n, pid) in variants.items():
            out[name].append(_throughput(url, body, media, n, clients, pid))
    return out


def main(argv: list[str] | None = None) -> int:
    """Run both servers, measure, print the ratio and record it."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=300,
                    help="requests per measurement (one frame per request)")
    ap.add_argument("--clients", type=int, default=2, help="load-generator processes")
    ap.add_argument("--rounds", type=int, default=5, help="alternating throughput rounds")
    ap.add_argument("--batch-frames", type=int, default=10,
                    help="frames per request of the second JSON / Arrow comparison")
    args = ap.parse_args(argv)

    from calibrators.io.arrow_batch import ARROW_STREAM

    payload, profile_json = service_payload()
    body = json.dumps(payload).encode()
    arrow = _arrow(payload)
    batched = {"frames": [{**payload["frames"][0], "frame_id": f"bench-{i}"}
                          for i in range(args.batch_frames)]}
    body_k, arrow_k = json.dumps(batched).encode(), _arrow(batched)
    n_k = max(20, args.requests // args.batch_frames)
    procs = []
    with tempfile.TemporaryDirectory() as tmp:
        p_app, p_echo = free_port(), free_port()
        try:
            procs.append(serve_detcal(Path(tmp) / "data", profile_json, p_app,
                                      env={"DETCAL_ADMIN_TOKEN": "bench"}))
            procs.append(subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "bench._echo_app:app", "--port", str(p_echo),
                 "--log-level", "warning"], cwd=ROOT, stdout=subprocess.DEVNULL))
            wait_ready(f"http://127.0.0.1:{p_app}/healthz", procs[0])
            wait_ready(f"http://127.0.0.1:{p_echo}/docs", procs[1])
            echo_url = f"http://127.0.0.1:{p_echo}/echo"
            url = f"http://127.0.0.1:{p_app}/v1/calibrate"
            with httpx.Client(timeout=30.0) as client:
                same = _bit_equal(client, url, body, arrow)
                lat = {"echo": _latency(client, echo_url, body, args.requests),
                       "json": _latency(client, url, body, args.requests),
                       "arrow": _latency(client, url, arrow, args.requests, ARROW_STREAM),
                       "json_k": _latency(client, url, body_k, n_k),
                       "arrow_k": _latency(client, url, arrow_k, n_k, ARROW_STREAM)}
            json_media, app_pid, echo_pid = "application/json", procs[0].pid, procs[1].pid
            tp = _rounds({"echo": (echo_url, body, json_media, args.requests, echo_pid),
                          "json": (url, body, json_media, args.requests, app_pid),
                          "arrow": (url, arrow, ARROW_STREAM, args.requests, app_pid),
                          "json_k": (url, body_k, json_media, n_k, app_pid),
                          "arrow_k": (url, arrow_k, ARROW_STREAM, n_k, app_pid)},
                         args.clients, args.rounds)
        finally:
            for p in procs:
                p.terminate()
                p.wait(10)
    return report_service(args, payload, body, arrow, body_k, arrow_k, same, lat, tp)


def report_service(args: argparse.Namespace, payload: dict, body: bytes, arrow: bytes,
                   body_k: bytes, arrow_k: bytes, same: bool, lat: dict,
                   tp: dict[str, list[tuple[float, float]]]) -> int:
    """The markdown section of the measurements, printed and written."""
    n_det = len(payload["frames"][0]["detections"])

    def rps(name: str) -> float:
        return statistics.median(r for r, _ in tp[name])

    def cpu(name: str) -> float:
        return statistics.median(c for _, c in tp[name])

    def ratio(a: str, b: str) -> float:
        """Median over the rounds of a's throughput over b's."""
        return statistics.median(x[0] / y[0] for x, y in zip(tp[a], tp[b], strict=True))

    rows = (("/v1/calibrate JSON", 1, "json"), ("/v1/calibrate Arrow", 1, "arrow"),
            ("echo (reference)", 1, "echo"), ("/v1/calibrate JSON", args.batch_frames, "json_k"),
            ("/v1/calibrate Arrow", args.batch_frames, "arrow_k"))
    table = (
        f"POST /v1/calibrate, frames of {n_det} detections (logits [10], box [9], covariance "
        f"2x2), one per request as JSON (request {len(body) / 1024:.0f} KiB) and as an Arrow "
        f"stream ({len(arrow) / 1024:.0f} KiB), and {args.batch_frames} frames per request "
        f"(JSON {len(body_k) / 1024:.0f} KiB, Arrow {len(arrow_k) / 1024:.0f} KiB); reference: "
        f"a bare FastAPI endpoint that parses the same JSON and echoes it. All are uvicorn "
        f"processes on loopback, one worker each, on the same 2 cores as the clients. Latency: "
        f"{args.requests} sequential requests (httpx); throughput: {args.clients} "
        f"load-generator processes (`http.client`, keep-alive), {args.rounds} rounds with the "
        f"formats alternating (medians; ratios are medians of the per-round ratios).\n\n"
        "| endpoint | frames / request | server p50 ms | server p95 ms | latency p50 ms | "
        "latency p95 ms | server CPU ms / request | throughput req/s | detections/s |\n"
        "|---|---|---|---|---|---|---|---|---|\n"
        + "".join(f"| {name} | {k} | {lat[key]['server_p50']:.2f} | "
                  f"{lat[key]['server_p95']:.2f} | {lat[key]['latency_p50']:.2f} | "
                  f"{lat[key]['latency_p95']:.2f} | {cpu(key):.2f} | {rps(key):.1f} | "
                  f"{rps(key) * n_det * k:,.0f} |\n" for name, k, key in rows)
        + f"\n**Ratio JSON calibrate / echo: "
          f"{lat['json']['server_p50'] / lat['echo']['server_p50']:.2f}× server time (p50)** "
          f"(target ≤ 1.0×), {lat['json']['latency_p50'] / lat['echo']['latency_p50']:.2f}× "
          f"client latency (p50). **Arrow / JSON, detections/s: {ratio('arrow', 'json'):.1f}× "
          f"with one frame per request (rounds: "
          + ", ".join(f"{x[0] / y[0]:.1f}" for x, y in zip(tp["arrow"], tp["json"], strict=True))
          + f"), {ratio('arrow_k', 'json_k'):.1f}× with {args.batch_frames}** (target ≥ 5×); "
          f"server CPU per detection {cpu('json') / cpu('arrow'):.1f}× / "
          f"{cpu('json_k') / cpu('arrow_k'):.1f}× less. Calibrated values of the two formats "
          f"bit-equal: {'yes' if same else 'NO'}.\n")
    from bench._report import report

    return report("service", table)


if __name__ == "__main__":
    sys.exit(main())
