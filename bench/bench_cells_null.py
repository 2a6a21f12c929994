"""What the per-cell criterion of `bench.bench_cells` costs a method whose every cell is exactly
calibrated: a null simulation on a sensor's real cell counts.

For each calibration-split seed, the default profile (and the one with the other
`region_calibration`) is fit on the val dump only to read how many calibration true positives
each class × distance cell holds (`selection.regions.cells`). Each draw then replaces every
score by an exchangeable one (i.i.d. exponential, every cell alike, so no cell differs from
its pool), fits the radii with the fit's own code (`calibrators.fit.conformal_region_fit`, the
same options) on those counts, serves a held-out dump's true positives (their real classes and
distances, fresh exchangeable scores) and judges them with `bench_cells.shortfalls`. Every
shortfall here comes from the calibration draw alone: the criterion's allowance counts the
test's sampling, not the calibration's.

    .venv/bin/python -m bench.bench_cells_null --val val.npz --test holdout.npz \\
        --draws 400 --label "lidar holdout"

(the dumps as in `bench/bench_cells.py`'s docstring). Prints, per radii calibration, the mean
number of shortfalls per fit, the chance of none, what they are (cells or classes, under or
over, per level) and how often the overall coverage is more than 1 pp from a level. With
`--label`, the table is also written to docs/report/cells.md as section `null <label>`.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from bench._report import write_section
from bench.bench_cells import CELLS_DOC, CELLS_HEADER, LEVELS, Served, held_out_parser, shortfalls
from calibrators import FitOptions, fit_profile, load_dump, match_dump
from calibrators.data import Dump
from calibrators.fit import conformal_region_fit
from calibrators.regions import ConformalRegions

CALIBRATIONS = ("split", "cross")


def cell_counts(val: Dump, options: FitOptions) -> tuple[np.ndarray, np.ndarray]:
    """Class indices and distances `[M]` with the fit's calibration count in every class ×
    distance cell (each at its bin's middle: the radii depend on the counts alone)."""
    profile = fit_profile(val, options)
    edges = (0.0, *options.distance_edges, 2.0 * options.distance_edges[-1])
    index = {name: i for i, name in enumerate(val.classes)}
    labels, distances = [], []
    for row in profile.report["selection"]["regions"]["cells"]:
        labels.append(np.full(row["count"], index[row["class"]]))
        distances.append(np.full(row["count"], (edges[row["bin"]] + edges[row["bin"] + 1]) / 2))
    return np.concatenate(labels), np.concatenate(distances)


def null_draw(rng: np.random.Generator, calib: tuple[np.ndarray, np.ndarray],
              test: tuple[np.ndarray, np.ndarray], options: FitOptions, n_classes: int
              ) -> Served:
    """One draw: exchangeable scores on the calibration counts `calib` and the test true
    positives `test` (class indices, distances), radii fit as the profile fits them."""
    labels, distances = calib
    fit = conformal_region_fit(rng.exponential(size=labels.size), labels, distances, n_classes,
                               options.min_group, options.distance_edges,
                               **options.conformal_options())
    regions = ConformalRegions.from_dict(fit.conformal)
    radii = np.stack([regions.radius(q, *test) for q in LEVELS], axis=1)
    none = np.zeros(0)
    return Served(rng.exponential(size=test[0].size), test[0], test[1], radii, none,
                  none.astype(bool), none.astype(int))


def kind(line: str) -> str:
    """`cell @ q under`, `class @ q under` or `class @ q over` of a `shortfalls` line."""
    where, rest = line.split(" @ ")
    side = "over" if line.endswith(" over") else "under"
    return f"{'class' if where.endswith(' all') else 'cell'} @ {rest.split(':')[0]} {side}"


def main(argv: list[str] | None = None) -> int:
    ap = held_out_parser(__doc__, "write the table to docs/report/cells.md under this name",
                         seeds=True)
    ap.add_argument("--draws", type=int, default=400, help="draws per radii calibration")
    args = ap.parse_args(argv)
    val, test = load_dump(args.val), load_dump(args.test)
    tp = np.asarray(match_dump(test).tp, dtype=bool)
    judged = (test.det_labels[tp], test.det_distance[tp])
    rows = []
    for calibration in CALIBRATIONS:
        counts = {s: cell_counts(val, FitOptions(seed=s, region_calibration=calibration))
                  for s in args.seeds}
        options = FitOptions(region_calibration=calibration)
        rng, missed, kinds, off = np.random.default_rng(0), [], Counter(), 0
        for k in range(args.draws):
            served = null_draw(rng, counts[args.seeds[k % len(args.seeds)]], judged, options,
                               len(val.classes))
            lines = shortfalls(served, test.classes, args.min_cell, args.min_class)
            missed.append(len(lines))
            kinds.update(kind(line) for line in lines)
            covered = (served.maha[:, None] <= served.radii).mean(axis=0)
            off += bool(np.any(np.abs(covered - np.asarray(LEVELS)) > 0.01))
        missed_ = np.asarray(missed)
        what = "; ".join(f"{k} {v / args.draws:.2f}" for k, v in sorted(kinds.items()))
        line = (f"| {calibration} | {missed_.mean():.2f} | {np.mean(missed_ == 0):.2f} | "
                f"{what or '-'} | {off / args.draws:.2f} |")
        print(line, flush=True)
        rows.append(line)
    if args.label:
        head = ("| radii | shortfalls per fit | P(none) | per fit, by kind | P(overall > 1 pp "
                "off) |\n|---|---|---|---|---|")
        write_section(f"null {args.label}", f"## Null simulation: {args.label}\n\n"
                      f"`bench/bench_cells_null.py`: the calibration counts of `"
                      f"{Path(args.val).name}` (seeds {args.seeds}), the true positives of "
                      f"`{Path(args.test).name}` ({test.n_frames} frames), exchangeable scores, "
                      f"{args.draws} draws per row; cells with >= {args.min_cell} test TPs, "
                      f"classes with >= {args.min_class}.\n\n{head}\n" + "\n".join(rows),
                      doc=CELLS_DOC, header=CELLS_HEADER)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
