"""Held-out figures of the streamed default profile against the in-memory one: fit a
sensor's val dump with `FitOptions()` in memory, and as a Parquet dataset by the streamed fit
(the score tables holding the rows, as they do up to 2^20 fit detections, and forced onto
cells, as above), serve a test dump from scenes no fit used and print, for each profile, ECE,
the largest class ECE, coverage at 50 / 90 / 95 / 99 %, the median 90 % r², mAP and the
cells and classes below their allowance (`bench.bench_cells`), with the test-sampling
interval of the in-memory coverage, and the largest differences of served scores and 90 %
radii against the in-memory profile.

    .venv/bin/detcal dump --sensor lidar --split val --frames 1000 --out val.npz
    .venv/bin/detcal dump --sensor lidar --split test --frames 1000 --out test.npz
    .venv/bin/python -m bench.bench_stream_heldout --val val.npz --test test.npz --label lidar

With `--label`, the table is written to docs/benchmarks.md as section `stream held-out <label>`.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from bench._report import write_section
from bench.bench_cells import LEVELS, Served, served, shortfalls, summary
from calibrators import fit_profile, load_dump, metrics
from calibrators.evaluation import evaluate
from calibrators.fit import fit_profile_stream
from calibrators.io import save_parquet


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--val", required=True, help="val dump to fit on")
    ap.add_argument("--test", required=True, help="held-out dump to measure on")
    ap.add_argument("--rows-per-part", type=int, default=20_000)
    ap.add_argument("--label", help="write the table to docs/benchmarks.md under this name")
    args = ap.parse_args(argv)
    val, test = load_dump(args.val), load_dump(args.test)
    profiles, seconds = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        save_parquet(Path(tmp) / "val", val, rows_per_part=args.rows_per_part)
        fits = {"in memory": lambda: fit_profile(val),
                "streamed (rows)": lambda: fit_profile_stream(Path(tmp) / "val"),
                "streamed (cells)": lambda: fit_profile_stream(Path(tmp) / "val",
                                                               exact_rows=0)}
        for name, fit in fits.items():
            start = time.perf_counter()
            profiles[name] = fit()
            seconds[name] = time.perf_counter() - start
    views = {name: served(p, test) for name, p in profiles.items()}
    base = views["in memory"]
    rows = []
    for name, s in views.items():
        figures = summary(s, test.classes, 500)
        mean_ap = evaluate(test, scores=s.scores).mean_ap
        missed = shortfalls(s, test.classes, 200, 500)
        d_score = float(np.abs(s.scores - base.scores).max())
        d_r90 = float(np.abs(s.radii - base.radii)[:, LEVELS.index(0.9)].max())
        method = profiles[name].report["selection"]["score"]
        rows.append(f"| {name} | {seconds[name]:.1f} | {method['chosen']}, κ "
                    f"{method['shrink']:g} | " + " | ".join(f"{v:.4f}" for v in figures.values())
                    + f" | {mean_ap:.4f} | {len(missed)} | {d_score:.1e} | {d_r90:.1e} |")
        print(rows[-1], flush=True)
    head = ("| fit | fit s | score method | " + " | ".join(summary(base, test.classes, 500))
            + " | mAP | short cells / classes | max Δ score | max Δ 90 % radius |\n|"
            + "---|" * (len(LEVELS) + 10))
    text = (f"Fit on `{Path(args.val).name}` ({val.n_frames} frames) with the default options, "
            f"in memory and streamed from Parquet; served on `{Path(args.test).name}` "
            f"({test.n_frames} frames). Test-sampling half-widths of the in-memory coverage "
            f"(95 % Clopper-Pearson): {_half_widths(base)}. Differences are against the "
            f"in-memory profile, on every test detection.\n\n{head}\n" + "\n".join(rows))
    print(text)
    if args.label:
        write_section(f"stream held-out {args.label}", text)
    return 0


def _half_widths(s: Served) -> str:
    n = len(s.maha)
    out = []
    for q, col in zip(LEVELS, (s.maha[:, None] <= s.radii).T, strict=True):
        lo, hi = metrics.proportion_bounds(int(col.sum()), n)
        out.append(f"{q:.0%} ±{(float(hi) - float(lo)) / 2:.4f}")
    return ", ".join(out)


if __name__ == "__main__":
    raise SystemExit(main())
