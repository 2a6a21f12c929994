"""Held-out honesty per class × range cell: fit the default profile on a sensor's val dump,
serve a test dump from scenes no fit or choice used, and print what the served regions and
scores hold per cell, per class and overall, for the default fit and without cell floors (the
reference), with cell floors decided by their binomial test alone (no tail floors) and without
cell ceilings, measured in the same run.

    .venv/bin/detcal dump --sensor lidar --split val --frames 1000 --out val.npz
    .venv/bin/detcal dump --sensor lidar --split holdout --frames 3000 --out test.npz
    .venv/bin/python -m bench.bench_cells --val val.npz --test test.npz --label "lidar holdout"

Criteria (cells: class × 0-15 / 15-30 / 30+ m with >= `--min-cell` test true positives, at
90 / 95 / 99 %): coverage >= q - 0.02 - 2.33·sqrt(q(1-q)/n), the one-sided 99 % test-sampling
allowance plus 2 pp; classes (>= `--min-class` TPs, at every level): within that allowance of
q on either side; overall and class
ECE of the served scores; the median 90 % ellipse area (its square radius in Mahalanobis units).
With `--label`, the figures are also written to docs/benchmarks.md as section `cells <label>`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench._report import write_section
from calibrators import (
    CalibrationProfile,
    FitOptions,
    apply_profile,
    fit_profile,
    load_dump,
    match_dump,
    metrics,
    tp_residuals,
)
from calibrators.data import Dump
from calibrators.regions import DEFAULT_DISTANCE_EDGES, xy_mahalanobis

LEVELS = (0.5, 0.9, 0.95, 0.99)
CELLS_DOC = Path(__file__).resolve().parent.parent / "docs" / "report" / "cells.md"
CELLS_HEADER = (
    "# Per-cell coverage on held-out scenes\n\n"
    "Written by `bench/bench_cells.py --label` (one section per sensor; the command is in its "
    "docstring). Each default profile is fit on 1000 val scenes and served on scenes of the "
    "`holdout` split, which no fit or choice used. A cell is **short** when its coverage at "
    "90 / 95 / 99 % is below `q − 0.02 − 2.33·sqrt(q(1−q)/n)` "
    "(`calibrators.metrics.coverage_allowance`); `small` cells hold fewer test true positives "
    "than the bench's `--min-cell` and are not judged.\n")
CELL_LEVELS = (0.9, 0.95, 0.99)


@dataclass(frozen=True)
class Served:
    """Test true positives under one profile: Mahalanobis distance `[M]`, class, distance,
    served radii `[M, Q]`; every detection's served score, TP flag and class `[N]`."""

    maha: np.ndarray
    labels: np.ndarray
    distance: np.ndarray
    radii: np.ndarray
    scores: np.ndarray
    tp: np.ndarray
    det_labels: np.ndarray


def serve(val: Dump, test: Dump, options: FitOptions) -> Served:
    return served(fit_profile(val, options), test)


def served(profile: CalibrationProfile, test: Dump) -> Served:
    """What `profile` serves on `test`, read at its true positives (`Served`)."""
    out = apply_profile(test, profile, levels=LEVELS)
    matched = match_dump(test)
    tp = np.asarray(matched.tp, dtype=bool)
    dims = tuple(profile.cov_dims)
    maha = xy_mahalanobis(tp_residuals(test, matched, dims), out.covariances[tp], dims)
    radii = np.stack([out.region_radii[q][tp] for q in LEVELS], axis=1)
    return Served(maha, test.det_labels[tp], test.det_distance[tp], radii, out.scores, tp,
                  test.det_labels)


def cell_table(s: Served, classes: tuple[str, ...]) -> metrics.CoverageTable:
    """Coverage of the served regions per class × distance cell (`metrics.coverage_table`)."""
    return metrics.coverage_table(s.maha, s.radii, LEVELS, np.asarray(classes)[s.labels],
                                  s.distance, DEFAULT_DISTANCE_EDGES)


def shortfalls(s: Served, classes: tuple[str, ...], min_cell: int, min_class: int
               ) -> list[str]:
    """Every cell below its allowance (`metrics.coverage_allowance`) and every class further
    from its level than that allowance, on either side, as `class bin @ level: coverage (n)`
    (`… (n) over` for a class above its level)."""
    out = []
    by_class = metrics.coverage_table(s.maha, s.radii, LEVELS, np.asarray(classes)[s.labels],
                                      s.distance, (0.0, float("inf")))
    cells = {r["class"]: [] for r in by_class.rows}
    for r in cell_table(s, classes).rows:
        cells[r["class"]].append((_span(r["distance_range"]), r, CELL_LEVELS, min_cell))
    for r in by_class.rows:
        for where, row, levels, least in [*cells[r["class"]], ("all", r, LEVELS, min_class)]:
            for q in levels if row["count"] >= least else ():
                cov = row["coverage"][LEVELS.index(q)]
                low = float(metrics.coverage_allowance(q, row["count"]))
                over = where == "all" and cov > 2 * q - low   # classes: within, both sides
                if cov < low or over:
                    out.append(f"{row['class']} {where} @ {q}: {cov:.3f} ({row['count']})"
                               + (" over" if over else ""))
    return out


def cell_markdown(s: Served, classes: tuple[str, ...], min_cell: int) -> str:
    """Every class × distance cell of `s`: test TPs and the coverage at each level with its
    95 % Clopper-Pearson interval; **short** where below its allowance, `small` where the cell
    has fewer than `min_cell` TPs (too few to judge)."""
    head = ("| class | range | test TPs | " + " | ".join(f"{q:.0%}" for q in LEVELS)
            + " |\n|" + "---|" * (len(LEVELS) + 3))
    lines = [head]
    for r in cell_table(s, classes).rows:
        n, cells = r["count"], []
        for q, cov in zip(LEVELS, r["coverage"], strict=True):
            lo, hi = metrics.proportion_bounds(round(cov * n), n)
            mark = ("small" if n < min_cell else "**short**"
                    if q in CELL_LEVELS and cov < metrics.coverage_allowance(q, n) else "")
            cells.append(f"{cov:.3f} [{float(lo):.3f}, {float(hi):.3f}] {mark}".rstrip())
        lines.append(f"| {r['class']} | {_span(r['distance_range'])} | {n} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines)


def _span(edges: list) -> str:
    lo, hi = edges
    return f"{lo:g}+ m" if hi is None or not np.isfinite(hi) else f"{lo:g}-{hi:g} m"


def summary(s: Served, classes: tuple[str, ...], min_class: int) -> dict[str, float]:
    covered = (s.maha[:, None] <= s.radii).mean(axis=0)
    class_ece = [metrics.expected_calibration_error(s.scores[s.det_labels == c],
                                                    s.tp[s.det_labels == c])
                 for c in range(len(classes)) if (s.labels == c).sum() >= min_class]
    return {"ece": float(metrics.expected_calibration_error(s.scores, s.tp)),
            f"max class ECE (classes with >= {min_class} TPs)": float(max(class_ece,
                                                                          default=np.nan)),
            **{f"coverage {q}": float(v) for q, v in zip(LEVELS, covered, strict=True)},
            "median 90 % r²": float(np.median(s.radii[:, LEVELS.index(0.9)] ** 2))}


def held_out_parser(doc: str, label_help: str, seeds: bool = False) -> argparse.ArgumentParser:
    """The arguments every held-out cell bench takes: `--val`, `--test`, (`--seeds`),
    `--min-cell`, `--min-class`, `--label` (`label_help`); `doc`: the bench's docstring."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--val", required=True, help="val dump to fit on")
    ap.add_argument("--test", required=True, help="held-out dump to measure on")
    if seeds:
        ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3],
                        help="calibration-split seeds")
    ap.add_argument("--min-cell", type=int, default=200, help="test TPs a cell needs")
    ap.add_argument("--min-class", type=int, default=500, help="test TPs a class needs")
    ap.add_argument("--label", help=label_help)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = held_out_parser(__doc__, "write the figures to docs/benchmarks.md under this "
                           "name").parse_args(argv)
    val, test = load_dump(args.val), load_dump(args.test)
    rows, served = [], None
    for name, options in (("reference: without cell floors", FitOptions(cell_floors=False)),
                          ("cell floors by test only (floor_delta none)",
                           FitOptions(floor_delta=None)),
                          ("cell and tail floors, no ceilings", FitOptions(cell_ceilings=False)),
                          ("default options (cell and tail floors, ceilings)", FitOptions())):
        served = serve(val, test, options)   # the last: the default options
        missed = shortfalls(served, test.classes, args.min_cell, args.min_class)
        figures = summary(served, test.classes, args.min_class)
        print(f"## {name}: {len(missed)} cells or classes below their allowance")
        for line in missed:
            print("   ", line)
        for key, value in figures.items():
            print(f"    {key}: {value:.4f}")
        rows.append(f"| {name} | {len(missed)}: {'; '.join(missed) or '-'} | "
                    + " | ".join(f"{v:.4f}" for v in figures.values()) + " |")
    if args.label:
        head = ("| fit | shortfalls (class, range, level: coverage (test TPs)) | "
                + " | ".join(figures) + " |\n|" + "---|" * (len(figures) + 2))
        write_section(f"cells {args.label}", f"## Per-cell coverage: {args.label}\n\n"
                      f"Fit on `{Path(args.val).name}`, served on `{Path(args.test).name}` "
                      f"({test.n_frames} frames); cells with >= {args.min_cell} test TPs, "
                      f"classes with >= {args.min_class}.\n\n{head}\n" + "\n".join(rows))
    table = cell_markdown(served, test.classes, args.min_cell)
    print(table)
    if args.label:
        write_section(f"cells {args.label}", f"## {args.label}\n\nThe default profile fit on "
                      f"`{Path(args.val).name}`, served on `{Path(args.test).name}` "
                      f"({test.n_frames} frames): coverage of the served ellipses per class × "
                      f"distance cell, with its 95 % Clopper-Pearson interval.\n\n{table}",
                      doc=CELLS_DOC, header=CELLS_HEADER)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
