"""Split vs cross-fitted conformal radii on held-out scenes, over calibration-split seeds: fit
the default profile (`region_calibration='split'`) and the cross-fitted one (`'cross'`) on a
sensor's val dump with each `FitOptions(seed=s)`, serve a held-out dump, and print per fit the
shortfalls of `bench.bench_cells` (cells at 90 / 95 / 99 %, classes at every level, with its
allowance), the overall coverage, the largest class ECE and the median 90 % r², then how far
each class's coverage moves between seeds.

    .venv/bin/python -m bench.bench_cross_regions --val val.npz --test holdout.npz \\
        --seeds 0 1 2 3 --label "lidar holdout"

(the dumps as in `bench/bench_cells.py`'s docstring). With `--label`, the table is also
written to docs/report/cells.md as section `cross <label>`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench._report import write_section
from bench.bench_cells import (
    CELLS_DOC,
    CELLS_HEADER,
    LEVELS,
    Served,
    held_out_parser,
    serve,
    shortfalls,
    summary,
)
from calibrators import FitOptions, load_dump

CALIBRATIONS = ("split", "cross")


def class_coverage(s: Served, n_classes: int, min_class: int) -> np.ndarray:
    """`[C, Q]` coverage at `LEVELS` of each class with >= `min_class` test TPs (NaN else)."""
    out = np.full((n_classes, len(LEVELS)), np.nan)
    for c in range(n_classes):
        rows = s.labels == c
        if rows.sum() >= min_class:
            out[c] = (s.maha[rows, None] <= s.radii[rows]).mean(axis=0)
    return out


def seed_range(per_seed: list[np.ndarray]) -> np.ndarray:
    """`[Q]` the mean over classes of (max - min over seeds) of the class coverage."""
    stack = np.stack(per_seed)
    return np.nanmean(stack.max(axis=0) - stack.min(axis=0), axis=0)


def main(argv: list[str] | None = None) -> int:
    args = held_out_parser(__doc__, "write the table to docs/report/cells.md under this name",
                           seeds=True).parse_args(argv)
    val, test = load_dump(args.val), load_dump(args.test)
    rows, spread = [], {}
    for calibration in CALIBRATIONS:
        per_seed = []
        for seed in args.seeds:
            s = serve(val, test, FitOptions(seed=seed, region_calibration=calibration))
            missed = shortfalls(s, test.classes, args.min_cell, args.min_class)
            fig = list(summary(s, test.classes, args.min_class).values())
            per_seed.append(class_coverage(s, len(test.classes), args.min_class))
            line = (f"| {calibration} | {seed} | {len(missed)}: {'; '.join(missed) or '-'} | "
                    + " / ".join(f"{v:.4f}" for v in fig[2:6])
                    + f" | {fig[1]:.4f} | {fig[6]:.3f} |")
            print(line, flush=True)
            rows.append(line)
        spread[calibration] = seed_range(per_seed)
    notes = [f"- {c}: a class's coverage moves between seeds by "
             + " / ".join(f"{100 * v:.1f}" for v in spread[c]) + " pp at "
             + " / ".join(f"{q:.0%}" for q in LEVELS) + " (mean over classes)"
             for c in CALIBRATIONS]
    print("\n".join(notes))
    if args.label:
        head = ("| radii | seed | shortfalls (class, range, level: coverage (test TPs)) | "
                "coverage 50 / 90 / 95 / 99 % | max class ECE | median 90 % r² |\n"
                "|---|---|---|---|---|---|")
        write_section(f"cross {args.label}", f"## Split vs cross-fitted radii: {args.label}\n\n"
                      f"Fit on `{Path(args.val).name}` with each calibration-split seed, served "
                      f"on `{Path(args.test).name}` ({test.n_frames} frames); cells with >= "
                      f"{args.min_cell} test TPs, classes with >= {args.min_class} "
                      f"(`bench/bench_cross_regions.py`).\n\n{head}\n" + "\n".join(rows)
                      + "\n\n" + "\n".join(notes), doc=CELLS_DOC, header=CELLS_HEADER)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
