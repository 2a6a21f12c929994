"""Benchmark: a streamed fit of a 20M-detection Parquet dataset in bounded memory, and the
same fit on a 2-worker Dask LocalCluster.

A synthetic dataset with known T and per-class k (`calibrators.data._synthetic.synthetic_dump`,
chunk by chunk, written with `ParquetWriter` as float32, one decoder layer, given 2x2
covariances) is fit by `fit_profile_stream` in a child process run under `/usr/bin/time -v`
(its peak RSS is the figure), then on `distributed.LocalCluster(n_workers=2)` (worker
processes; its profile must equal the streamed one to 1e-6 in T and every k). Options:
the thesis methods (`calibration=0`), the defaults otherwise; with `--conformal`, one
temperature and everything else as the defaults (a calibration part, depth or shrinkage
chosen on it, conformal regions with cell and tail floors), section `stream-fit conformal`;
with `--defaults`, the default options through the command line itself (`detcal fit DIR`,
`detcal fit DIR --dask local:2`: score candidates and κ, covariance and regions chosen on the
calibration part), section `stream-fit defaults`.

    .venv/bin/python -m bench.bench_stream_fit                       # 20M, ~15 min
    .venv/bin/python -m bench.bench_stream_fit --conformal           # 20M, ~15 min
    .venv/bin/python -m bench.bench_stream_fit --defaults            # 20M, ~20 min
    .venv/bin/python -m bench.bench_stream_fit --detections 1000000 --no-write

The dataset is written under runs/ (gitignored) and deleted afterwards unless --keep.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

from calibrators.data import CLASSES10, DEFAULT_DEPTH_K, concat_frames, synthetic_dump
from calibrators.io import ParquetWriter

T_TRUE = 2.0
#: A quarter of the synthetic defaults: even at 60 m a true positive stays well inside the
#: 2 m matching threshold, so matching does not truncate the residuals k is fit on.
K_TRUE = {c: DEFAULT_DEPTH_K[c] / 4 for c in CLASSES10}
FRAMES_PER_CHUNK, GT_PER_FRAME = 100, 20
OPTIONS = {"calibration": 0.0}
CONFORMAL = {"score_method": "temperature"}
ROOT = Path(__file__).resolve().parent.parent


def generate(path: Path, n_detections: int, rows_per_part: int) -> tuple[int, float]:
    """Write the dataset; returns (detections written, seconds)."""
    start, total, seed = time.perf_counter(), 0, 0
    writer = ParquetWriter(path, rows_per_part=rows_per_part, float_dtype="float32",
                           source_sha256=f"synthetic T={T_TRUE} k/4 n={n_detections}")
    pending: list = []
    while total < n_detections:
        chunk = synthetic_dump(n_frames=FRAMES_PER_CHUNK, n_gt_per_frame=GT_PER_FRAME,
                               n_layers=1, temperature=T_TRUE, depth_k=K_TRUE, seed=seed)
        if pending and sum(d.n_detections for d in pending) + chunk.n_detections > \
                rows_per_part:   # one part per add: parts of about rows_per_part
            writer.add(concat_frames(pending))
            pending = []
        pending.append(chunk)
        total += chunk.n_detections
        seed += 1
    writer.add(concat_frames(pending))
    writer.close()
    return total, time.perf_counter() - start


def child_fit(path: str, out: str, dask: str | None, options: dict) -> None:
    """Fit (here or on Dask) and write the profile JSON and the fit's wall time."""
    from calibrators.fit import fit_profile_stream

    start = time.perf_counter()
    if dask is None:
        profile = fit_profile_stream(path, **options)
    else:
        from calibrators.fit import dask_client

        with dask_client(dask) as client:
            start = time.perf_counter()
            profile = fit_profile_stream(path, client=client, **options)
    seconds = time.perf_counter() - start
    Path(out).write_text(json.dumps({"seconds": seconds, "profile": profile.to_dict()}))


def run_child(path: Path, out: Path, dask: str | None, options: dict | None
              ) -> tuple[dict, float, float | None, str]:
    """Run `child_fit` (options None: `detcal fit` with its defaults) in a child process
    under /usr/bin/time -v: (result, wall s, peak RSS in GB or None, how RSS was measured)."""
    if options is None:
        cli = Path(sys.executable).parent / "detcal"
        cmd = [str(cli), "fit", str(path), "--out", str(out.with_suffix(".profile.json")),
               "--quiet"] + (["--dask", dask] if dask else [])
    else:
        cmd = [sys.executable, "-m", "bench.bench_stream_fit", "--child", str(path), str(out),
               "--child-options", json.dumps(options)]
        if dask:
            cmd += ["--child-dask", dask]
    start = time.perf_counter()
    if Path("/usr/bin/time").exists():
        done = subprocess.run(["/usr/bin/time", "-v", *cmd], cwd=ROOT, capture_output=True,
                              text=True, check=False)
        how = "/usr/bin/time -v (maximum resident set size of the fitting process)"
        found = re.search(r"Maximum resident set size \(kbytes\): (\d+)", done.stderr)
        rss = None if found is None else int(found.group(1)) / 1024**2
    else:
        import resource

        done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, check=False)
        how = "resource.getrusage(RUSAGE_CHILDREN).ru_maxrss (/usr/bin/time is absent)"
        rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024**2
    if done.returncode != 0:
        raise SystemExit(f"fit failed:\n{done.stderr[-3000:]}")
    wall = time.perf_counter() - start
    if options is None:   # the command's own wall time, cluster start included
        profile = json.loads(out.with_suffix(".profile.json").read_text())
        return {"seconds": wall, "profile": profile}, wall, rss, how
    return json.loads(out.read_text()), wall, rss, how


def max_rel(a: dict, b: dict) -> float:
    """Largest relative difference of T, pooled k and every class k between two profiles."""
    pairs = [(a["temperature"], b["temperature"]), (a["pooled_k"], b["pooled_k"])]
    pairs += [(a["depth_k"][c], b["depth_k"][c]) for c in a["depth_k"]]
    return max(abs(x - y) / abs(y) for x, y in pairs)


def table(n: int, gen_s: float, disk_gb: float, parts: int, streamed: dict, s_wall: float,
          rss: float | None, how: str, dask: dict | None, d_wall: float | None,
          options: dict) -> str:
    p = streamed["profile"]
    scaling = (p.get("covariance_scaling") or {}).get("method", "depth")
    score = (p.get("score_calibration") or {}).get("method", "temperature")
    cross = (p.get("regions") or {}).get("calibration") == "cross"
    radii = ("cross-fitted on every fit frame (a second pass)" if cross else
             f"fit on {p['provenance']['n_calibration_frames']:,} calibration frames")
    stages = (f"{score}, {scaling} chosen on the calibration part of "
              f"{p['provenance']['n_calibration_frames']:,} frames, conformal regions "
              f"{radii}; with shrinkage the k below are those of s·Σ + k·d·I, not the "
              f"generating k"
              if (p.get("regions") or {}).get("method") == "conformal"
              else "temperature, depth, gaussian")
    k_err = {c: p["depth_k"][c] / K_TRUE[c] - 1 for c in K_TRUE}
    worst = max(k_err, key=lambda c: abs(k_err[c]))
    lines = [
        f"Streamed fit of a synthetic Parquet dataset of {n:,} detections "
        f"({parts} parts of whole frames, float32, {disk_gb:.2f} GB on disk, "
        + ("written by an earlier run" if gen_s != gen_s else f"written in {gen_s:.0f} s")
        + f"), true T = {T_TRUE} and per-class k = the synthetic defaults / 4; "
        f"options {options} ({stages}), sigmoid scores, given 2x2 "
        f"covariances. Peak RSS by {how}.", "",
        "| fit | wall (s) | detections / s | peak RSS (GB) | T (error) | worst class k error | "
        "max rel. diff to streamed (T, k) |",
        "|---|---|---|---|---|---|---|",
        f"| streamed, 1 process | {streamed['seconds']:.0f} (process {s_wall:.0f}) | "
        f"{n / streamed['seconds']:,.0f} | "
        + ("n/a" if rss is None else f"{rss:.2f}")
        + f" | {p['temperature']:.5f} ({100 * (p['temperature'] / T_TRUE - 1):+.3f} %) | "
        f"{worst} {100 * k_err[worst]:+.3f} % | - |"]
    if dask is not None:
        q = dask["profile"]
        lines.append(f"| Dask LocalCluster, 2 worker processes | {dask['seconds']:.0f} "
                     f"(with cluster start {d_wall:.0f}) | {n / dask['seconds']:,.0f} | n/a | "
                     f"{q['temperature']:.5f} | - | {max_rel(q, p):.1e} |")
    lines += ["", "Per-class k recovered (fit / true - 1): " + ", ".join(
        f"{c} {100 * e:+.2f} %" for c, e in k_err.items()) + "."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detections", type=int, default=20_000_000)
    parser.add_argument("--rows-per-part", type=int, default=500_000)
    parser.add_argument("--dir", default=str(ROOT / "runs" / "bench_stream"))
    parser.add_argument("--dask", default="local:2", help="Dask spec ('' to skip)")
    parser.add_argument("--keep", action="store_true", help="keep the dataset")
    parser.add_argument("--reuse", action="store_true", help="fit an existing dataset")
    parser.add_argument("--no-write", action="store_true", help="do not touch docs/")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    parser.add_argument("--child-dask", help=argparse.SUPPRESS)
    parser.add_argument("--child-options", help=argparse.SUPPRESS)
    parser.add_argument("--conformal", action="store_true",
                        help="one temperature, the other stages as the defaults")
    parser.add_argument("--defaults", action="store_true",
                        help="`detcal fit DIR` with the default options")
    args = parser.parse_args(argv)
    if args.child:
        child_fit(*args.child, args.child_dask, json.loads(args.child_options))
        return
    options = None if args.defaults else CONFORMAL if args.conformal else OPTIONS

    path = Path(args.dir) / "dataset"
    try:
        if args.reuse and path.exists():
            from calibrators.io import open_parquet

            n, gen_s = open_parquet(path).n_detections, float("nan")
        else:
            shutil.rmtree(path, ignore_errors=True)
            n, gen_s = generate(path, args.detections, args.rows_per_part)
        disk = sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 1e9
        parts = len(list((path / "detections").glob("*.parquet")))
        print(f"dataset: {n:,} detections, {parts} parts, {disk:.2f} GB, {gen_s:.0f} s",
              flush=True)
        streamed, s_wall, rss, how = run_child(path, path.parent / "streamed.json", None,
                                               options)
        print(f"streamed: {streamed['seconds']:.0f} s, peak RSS {rss} GB, "
              f"T {streamed['profile']['temperature']:.6f}", flush=True)
        dask = d_wall = None
        if args.dask:
            dask, d_wall, _, _ = run_child(path, path.parent / "dask.json", args.dask, options)
            print(f"dask: {dask['seconds']:.0f} s, max rel diff "
                  f"{max_rel(dask['profile'], streamed['profile']):.2e}", flush=True)
    finally:
        if not args.keep:
            shutil.rmtree(path, ignore_errors=True)
    markdown = table(n, gen_s, disk, parts, streamed, s_wall, rss, how, dask, d_wall,
                     options if options is not None else {})
    if options is not CONFORMAL and options is not OPTIONS:
        markdown += "\n\n" + scores_line(streamed["profile"], dask)
    if options is not OPTIONS:
        markdown += "\n\n" + regions_line(streamed["profile"], dask)
    print(markdown)
    if not args.no_write:
        from bench._report import write_section

        section = {id(OPTIONS): "stream-fit", id(CONFORMAL): "stream-fit conformal"}
        write_section(section.get(id(options), "stream-fit defaults"), markdown)


def scores_line(p: dict, dask: dict | None) -> str:
    """The score method the defaults chose, each candidate's held-out NLL, κ, and whether
    the Dask fit's score calibration equals the streamed one."""
    sel = p["report"]["selection"]["score"]
    cands = ", ".join(f"{k} {v['nll']:.5f}" for k, v in sel["candidates"].items())
    same = "n/a" if dask is None else str(dask["profile"]["score_calibration"]
                                          == p["score_calibration"])
    return (f"Score stage: {sel['chosen']} chosen (held-out NLL on the calibration part: "
            f"{cands}), shrinkage κ = {sel['shrink']:g}; Dask's score calibration equals the "
            f"streamed one: {same}.")


def regions_line(p: dict, dask: dict | None) -> str:
    """The conformal regions' calibration true positives and the served 90 % radius of the
    first group, and whether the Dask fit's regions equal the streamed ones."""
    conf = (p.get("regions") or {}).get("conformal")
    if conf is None:
        return "Regions: gaussian."
    n = sum(sum(row) for row in conf["counts"])
    same = "n/a" if dask is None else str(dask["profile"]["regions"]["conformal"]["counts"]
                                          == conf["counts"])
    return (f"Conformal regions fit on {n:,} calibration true positives in "
            f"{len(conf['groups'])} groups; Dask's cell counts equal the streamed ones: {same}.")


if __name__ == "__main__":
    main()
