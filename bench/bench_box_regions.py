"""Conformal box regions: `calibrators.boxes2d.ConformalBoxes` (additive, scaled, adaptive)
against puncc's `SplitBoxWise` (additive, multiplicative), fit on the same calibration pairs
and measured on the same disjoint test pairs, in the same run.

Data: matched (detected box, true box) pairs, the images split by a seeded hash of their id
into calibration and test.

- `--coco-results R.json --coco-gt G.json`: a detector's COCO results (with optional
  `layer_boxes`, which give the scaled score its σ through `edge_covariance` / `edge_sigma`)
  and its instances file; the true positives are `match_labels` at IoU 0.5 (COCO's ignored
  detections left out).
- by default, a seeded synthetic set: 640 x 480 images, 4 classes with their own frequency,
  size range, aspect and noise level; each edge's error is Student-t (5 dof) with standard
  deviation σ = u·(0.5 + k_class·w) for x edges (h for y edges), so it grows with the box,
  and u ~ lognormal(0, 0.35) is a per-detection difficulty that the box size does not tell.
  Six decoder-layer boxes scatter around the detection with that σ, so the σ the scaled
  score reads (`edge_sigma` of the layers) is the true one up to its sampling noise (~30 %).
  The errors are symmetric and unbiased (see the sign note below). The score is drawn
  uniformly: it says nothing about the box's error here.
  (`bench/_box_pairs.py`.)

Methods, each fit on the calibration pairs only:

- `ConformalBoxes(score="additive" | "scaled")`, default groups (class × COCO size bin), at
  q = 0.9 and 0.95;
- `ConformalBoxes adaptive`, as a 2-D profile fit serves it by default: the calibration pairs
  split in two by image (seeded hash), `EdgeErrorScale` fit on one half (box extent, score,
  the layers' spread when given, image border), the scaled score's radii on the other; so it
  uses exactly the pairs the others use;
- puncc `SplitBoxWise(BasePredictor(identity, is_trained=True), method="additive" |
  "multiplicative")`, `fit(X_calib=detected, y_calib=true)` and `predict(X_test,
  alpha=1 - q)`, the boxes as x1, y1, x2, y2 and the default Bonferroni correction (each
  coordinate at 1 - alpha/4), one global group, as its documentation shows;
- the same `SplitBoxWise` at `alpha = (1 - q)/2` ("two-sided"). Its score is the signed
  `predicted - true` per coordinate and its radius the upper quantile of that, so each edge is
  bounded on one side only: with Bonferroni over four edges it certifies the true box inside
  the outer box (its metric `object_detection_mean_coverage`), not the true edges between
  the inner and the outer box. The x2 / y2 side of its outer box holds by the symmetry of the
  errors, not by the quantile (its score for those edges has the sign of an inner bound).
  Halving alpha puts every one of the eight one-sided edge bounds at (1 - q)/8: the joint
  two-sided guarantee at q that `ConformalBoxes` gives.

Measured on the test pairs, the same way for every method:

- joint coverage: every true edge between the inner and the outer box's edge (x1 in
  [outer x1, inner x1], x2 in [inner x2, outer x2], the same for y): what `ConformalBoxes`
  certifies at q;
- outer coverage: the true box inside the outer box (puncc's `object_detection_mean_coverage`):
  what `SplitBoxWise` certifies at q;
- outer area: the mean area of the outer box, px² (puncc's
  `object_detection_mean_area(box_outer)`); its ratio to the mean detected-box area; and ours
  over SplitBoxWise's at the same nominal q. It includes the detected box itself, which no
  method can shrink: on small boxes it hides most of the difference between methods;
- region area: the mean area between the inner and the outer box (outer minus inner, an empty
  inner box counting 0), px²: the area where the true box's edges may lie.

Run (puncc is installed only in the bench environment, pinned in
bench/requirements-reference.txt, never in .venv):

    make bench
    .bench-venv/bin/python -m bench.bench_box_regions --label synthetic
    .bench-venv/bin/python -m bench.bench_box_regions --coco-results R.json --coco-gt G.json \\
        --label "my detector val"

With `--label`, the figures are also written to docs/benchmarks.md as section
`box regions <label>`.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

import numpy as np

from bench._box_pairs import Pairs, calibration_split, coco_pairs, synthetic_pairs
from calibrators.boxes2d import COCO_SIZE_EDGES, ConformalBoxes, EdgeErrorScale, box_edges

LEVELS = (0.9, 0.95)
SIZE_NAMES = ("small", "medium", "large")
MISSING_PUNCC = ("puncc is not installed here: install the bench environment: make bench "
                 "(puncc is pinned in bench/requirements-reference.txt and is installed only "
                 "into .bench-venv, never into .venv)")

@dataclass(frozen=True)
class Result:
    """One method at one level on the test pairs: inner and outer boxes as edges `[M, 4]`."""

    method: str
    level: float
    alpha: float | None
    inner: np.ndarray
    outer: np.ndarray


def run_ours(cal: Pairs, test: Pairs, score: str) -> list[Result]:
    model = ConformalBoxes(score=score).fit(cal.det, cal.true, cal.labels, cal.sigma)
    inner, outer = model.regions(test.det, test.labels, test.sigma, LEVELS)
    return [Result(f"ConformalBoxes {score}", q, None, box_edges(inner[:, i]),
                   box_edges(outer[:, i])) for i, q in enumerate(LEVELS)]


def run_adaptive(cal: Pairs, test: Pairs, seed: int) -> list[Result]:
    """The adaptive regions: `EdgeErrorScale` on half of the calibration pairs' images, the
    radii of the scaled score on the other half."""
    half = calibration_split(cal.image_id, seed + 1)
    fit, radii = cal.take(half), cal.take(~half)
    scale = EdgeErrorScale().fit(fit.det, fit.true, fit.score, fit.spread, fit.image_size)

    def sigma(p: Pairs) -> np.ndarray:
        return scale.predict(p.det, p.score, p.spread, p.image_size)

    model = ConformalBoxes(score="scaled").fit(radii.det, radii.true, radii.labels,
                                               sigma(radii))
    inner, outer = model.regions(test.det, test.labels, sigma(test), LEVELS)
    return [Result("ConformalBoxes adaptive", q, None, box_edges(inner[:, i]),
                   box_edges(outer[:, i])) for i, q in enumerate(LEVELS)]


class _Identity:
    """The 'model' that SplitBoxWise wraps: the detector already ran, so its prediction for a
    detection is the detected box itself (x1, y1, x2, y2)."""

    def predict(self, X: Any) -> np.ndarray:  # noqa: N803 (puncc's argument name)
        return np.asarray(X, dtype=np.float64)


def fit_puncc(cal: Pairs, method: str) -> Any:
    """puncc's `SplitBoxWise(method)` fit on the calibration pairs, as its documentation
    shows: a trained predictor (`BasePredictor(..., is_trained=True)`, `train=False`) and
    `fit(X_calib, y_calib)`, the boxes as x1, y1, x2, y2."""
    try:
        from deel.puncc.api.prediction import BasePredictor
        from deel.puncc.object_detection import SplitBoxWise
    except ImportError:
        raise SystemExit(MISSING_PUNCC) from None
    model = SplitBoxWise(BasePredictor(_Identity(), is_trained=True), method=method,
                         train=False)
    model.fit(X_calib=box_edges(cal.det), y_calib=box_edges(cal.true))
    return model


def puncc_result(model: Any, name: str, test: Pairs, q: float, alpha: float) -> Result:
    """`predict(X_test, alpha)` (default Bonferroni over the 4 coordinates): the inner and
    outer boxes, x1, y1, x2, y2."""
    _, inner, outer = model.predict(box_edges(test.det), alpha=alpha)
    return Result(name, q, alpha, np.asarray(inner, dtype=np.float64),
                  np.asarray(outer, dtype=np.float64))


def matched_alpha(model: Any, test: Pairs, n_cal: int, covered: Any, target: float
                  ) -> tuple[float, Result]:
    """The largest alpha (bisection on log alpha, 40 steps) at which `SplitBoxWise`'s test
    coverage `covered(result, true_edges)` is still >= `target`, and its result: the least
    area it needs to reach the coverage ours reached on the same test pairs."""
    true_edges = box_edges(test.true)
    lo, hi = np.log(4.0 / (n_cal + 1) * 1.0001), np.log(0.99)   # puncc's alpha/4 >= 1/(n+1)
    best = puncc_result(model, "", test, target, float(np.exp(lo)))
    if covered(best, true_edges).mean() < target:
        return float(np.exp(lo)), best
    for _ in range(40):
        mid = (lo + hi) / 2
        r = puncc_result(model, "", test, target, float(np.exp(mid)))
        if covered(r, true_edges).mean() >= target:
            lo, best = mid, r
        else:
            hi = mid
    return float(np.exp(lo)), best


def joint_covered(r: Result, true_edges: np.ndarray) -> np.ndarray:
    """Every true edge between the inner and the outer box's (x1 in [outer, inner], x2 in
    [inner, outer], the same for y): the band the regions certify."""
    lo = np.minimum(r.outer, r.inner)
    hi = np.maximum(r.outer, r.inner)
    return ((true_edges >= lo) & (true_edges <= hi)).all(axis=1)


def outer_covered(r: Result, true_edges: np.ndarray) -> np.ndarray:
    """The true box inside the outer box (puncc's `object_detection_mean_coverage`)."""
    return ((true_edges[:, :2] >= r.outer[:, :2]) & (true_edges[:, 2:] <= r.outer[:, 2:])
            ).all(axis=1)


def outer_area(r: Result) -> np.ndarray:
    """The outer box's area, px² (puncc's `object_detection_mean_area(box_outer)`)."""
    return (r.outer[:, 2] - r.outer[:, 0]) * (r.outer[:, 3] - r.outer[:, 1])


def region_area(r: Result) -> np.ndarray:
    """The area between the inner and the outer box, px² (an empty inner box counts 0)."""
    inner = np.clip(r.inner[:, 2] - r.inner[:, 0], 0, None) * np.clip(
        r.inner[:, 3] - r.inner[:, 1], 0, None)
    return outer_area(r) - inner


def size_bins(det: np.ndarray) -> np.ndarray:
    """COCO small / medium / large (0, 1, 2) of the detected box's sqrt(w·h), as
    ConformalBoxes bins it."""
    return np.searchsorted(np.asarray(COCO_SIZE_EDGES[1:-1]), np.sqrt(det[:, 2] * det[:, 3]),
                           side="right")


def _fmt_area(a: float) -> str:
    return f"{a:,.0f}" if np.isfinite(a) else "inf"


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.3f}" if np.isfinite(a) and np.isfinite(b) and b > 0 else "n/a"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--coco-results", help="a detector's COCO results file (R.json)")
    parser.add_argument("--coco-gt", help="its COCO instances file (G.json)")
    parser.add_argument("--iou", type=float, default=0.5, help="true-positive IoU threshold")
    parser.add_argument("--images", type=int, default=6000, help="synthetic images")
    parser.add_argument("--layers", type=int, default=6,
                        help="synthetic decoder layers behind σ (more: a less noisy σ)")
    parser.add_argument("--seed", type=int, default=0, help="data and split seed")
    parser.add_argument("--calibration-fraction", type=float, default=0.5)
    parser.add_argument("--label", help="write the figures to docs/benchmarks.md under "
                                        "'box regions <label>'")
    args = parser.parse_args(argv)
    if (args.coco_results is None) != (args.coco_gt is None):
        parser.error("--coco-results and --coco-gt go together")

    if args.coco_results:
        pairs = coco_pairs(args.coco_results, args.coco_gt, args.iou)
        source = (f"COCO results `{args.coco_results}` against `{args.coco_gt}`, true "
                  f"positives at IoU {args.iou}")
    else:
        pairs = synthetic_pairs(n_images=args.images, layers=args.layers, seed=args.seed)
        source = (f"synthetic: {args.images:,} images of 640 x 480, 4 classes, Student-t (5 "
                  "dof) edge errors of σ = u·(0.5 + k_class·w or h), u ~ lognormal(0, 0.35) "
                  f"per detection, σ read from {args.layers} decoder-layer boxes (`edge_sigma`)")
    is_cal = calibration_split(pairs.image_id, args.seed, args.calibration_fraction)
    cal, test = pairs.take(is_cal), pairs.take(~is_cal)
    if len(cal.det) == 0 or len(test.det) == 0:
        raise SystemExit("no true positives on one side of the split")
    data = (f"{source}; images split by a seeded hash (seed {args.seed}): {len(cal.det):,} "
            f"calibration and {len(test.det):,} test true positives")
    print(f"data: {data}")

    results: list[Result] = run_ours(cal, test, "additive")
    if pairs.sigma is not None:
        results += run_ours(cal, test, "scaled")
    else:
        print("no decoder-layer boxes: ConformalBoxes scaled is left out")
    results += run_adaptive(cal, test, args.seed)
    from importlib.metadata import version

    puncc = {method: fit_puncc(cal, method) for method in ("additive", "multiplicative")}
    for two_sided in (False, True):
        for method, model in puncc.items():
            name = f"SplitBoxWise {method}" + (", alpha/2" if two_sided else "")
            results += [puncc_result(model, name, test, q, (1 - q) / 2 if two_sided else 1 - q)
                        for q in LEVELS]
    reference = f"puncc {version('puncc')}"

    true_edges = box_edges(test.true)
    det_area = float(np.mean(test.det[:, 2] * test.det[:, 3]))
    n = len(test.det)
    stats = {(r.method, r.level): (joint_covered(r, true_edges), outer_covered(r, true_edges),
                                   float(np.mean(outer_area(r))), float(np.mean(region_area(r))))
             for r in results}
    methods = list(dict.fromkeys(r.method for r in results))
    alphas = {(r.method, r.level): r.alpha for r in results}

    main_rows = ["| method | q | alpha passed | joint coverage | outer coverage | mean outer "
                 "area (px²) | × detected area | mean region area (px²) |",
                 "|---|---|---|---|---|---|---|---|"]
    for q in LEVELS:
        for m in methods:
            joint, outer, area, band = stats[(m, q)]
            alpha = alphas[(m, q)]
            main_rows.append(f"| {m} | {q:g} | {'' if alpha is None else f'{alpha:g}'} | "
                             f"{joint.mean():.3f} | {outer.mean():.3f} | {_fmt_area(area)} | "
                             f"{area / det_area:.2f} | {_fmt_area(band)} |")

    refs = [m for m in methods if m.startswith("SplitBoxWise")]
    ours = [m for m in methods if m.startswith("ConformalBoxes")]
    ratio_rows = ["| q | ours | " + " | ".join(f"/ {m}" for m in refs) + " |",
                  "|---|---|" + "---|" * len(refs)]
    for q in LEVELS:
        for m in ours:
            ratio_rows.append(f"| {q:g} | {m} | " + " | ".join(
                f"{_ratio(stats[(m, q)][2], stats[(r, q)][2])} / "
                f"{_ratio(stats[(m, q)][3], stats[(r, q)][3])}" for r in refs) + " |")

    # SplitBoxWise at the alpha that reaches, on the same test pairs, the coverage ours reached
    matched_rows = ["| q | ours | joint coverage | " + " | ".join(
        f"SplitBoxWise {m}: alpha, joint cov., ours / its outer, region area" for m in puncc) +
        " | outer coverage | " + " | ".join(
        f"SplitBoxWise {m}: alpha, outer cov., ours / its outer, region area" for m in puncc)
        + " |",
        "|---|---|---|" + "---|" * len(puncc) + "---|" + "---|" * len(puncc)]
    for q in LEVELS:
        for m in ours:
            joint, outer, area, band = stats[(m, q)]
            cells = [f"{joint.mean():.3f}"]
            for covered, target in ((joint_covered, joint.mean()), (outer_covered,
                                                                     outer.mean())):
                if covered is outer_covered:
                    cells.append(f"{outer.mean():.3f}")
                for model in puncc.values():
                    alpha, r = matched_alpha(model, test, len(cal.det), covered, target)
                    cells.append(f"{alpha:.4f}, {covered(r, true_edges).mean():.3f}, "
                                 f"{_ratio(area, float(np.mean(outer_area(r))))}, "
                                 f"{_ratio(band, float(np.mean(region_area(r))))}")
            matched_rows.append(f"| {q:g} | {m} | " + " | ".join(cells) + " |")

    def group_table(title: str, keys: np.ndarray, names: list[tuple[Any, str]]) -> list[str]:
        shown = [(k, name) for k, name in names if (keys == k).any()]
        rows = [f"| {title} | q | " + " | ".join(
                    f"{name} (n={int((keys == k).sum()):,})" for k, name in shown) + " |",
                "|---|---|" + "---|" * len(shown)]
        for q in LEVELS:
            for m in methods:
                joint, outer = stats[(m, q)][:2]
                rows.append(f"| {m} | {q:g} | " + " | ".join(
                    f"{joint[keys == k].mean():.3f} / {outer[keys == k].mean():.3f}"
                    for k, _ in shown) + " |")
        return rows

    classes = [(c, f"class {c}") for c in np.unique(test.labels).tolist()]
    class_rows = group_table("method", test.labels, classes)
    size_rows = group_table("method", size_bins(test.det), list(enumerate(SIZE_NAMES)))

    se = {q: np.sqrt(q * (1 - q) / n) for q in LEVELS}
    markdown = "\n".join([
        f"## Box regions vs puncc SplitBoxWise: {args.label or 'run'}",
        "",
        f"{data}. `bench/bench_box_regions.py`; reference: {reference}'s `SplitBoxWise` "
        "(`BasePredictor` around the detected boxes, `fit(X_calib, y_calib)`, "
        "`predict(X_test, alpha)`, default Bonferroni over the 4 coordinates, one global "
        "group), fit on the same calibration pairs.",
        "",
        "Joint coverage: every true edge between the inner and the outer box "
        "(`ConformalBoxes`' guarantee at q). Outer coverage: the true box inside the outer box "
        "(`SplitBoxWise`'s guarantee at q, puncc's `object_detection_mean_coverage`). Outer "
        "area: the mean outer-box area over the test true positives, px² (puncc's "
        "`object_detection_mean_area(box_outer)`), the same for every method; × detected "
        f"area: over the mean detected-box area ({det_area:,.0f} px²). Region area: the mean "
        "area between the inner and the outer box (an empty inner box counts 0): where the "
        "true box's edges may lie. `ConformalBoxes adaptive` fits its edge-error scale on "
        "half of the calibration pairs' images and its radii on the other half. 'alpha/2': "
        "`SplitBoxWise` called at `alpha = (1 - q)/2`, which bounds all eight one-sided edge "
        "misses by (1 - q)/8 and so certifies the same joint two-sided event as "
        f"`ConformalBoxes` at q. Test-sampling standard error of a coverage near q: "
        + ", ".join(f"{se[q]:.4f} at {q:g}" for q in LEVELS) + ".",
        "",
        *main_rows,
        "",
        "Our mean outer / region area over SplitBoxWise's, same nominal q:",
        "",
        *ratio_rows,
        "",
        "At equal achieved coverage: SplitBoxWise at the largest alpha whose coverage on the "
        "same test pairs is at least ours (bisection on alpha; chosen on the test set, so "
        "this favours the reference), and our mean outer and region area over its:",
        "",
        *matched_rows,
        "",
        "Per class, joint / outer coverage:",
        "",
        *class_rows,
        "",
        "Per COCO size bin of the detected box, joint / outer coverage:",
        "",
        *size_rows,
        "",
        "How the methods differ: `ConformalBoxes` takes one quantile of the maximum of the "
        "four edge scores per class × size group, so it certifies the joint two-sided event "
        "at q in every group; `SplitBoxWise` takes one quantile per signed coordinate "
        "(`predicted - true`) at 1 - alpha/4 over all boxes at once (Bonferroni, one global "
        "group), which certifies the outer box's x1 / y1 side; its x2 / y2 side holds only "
        "as far as the errors are symmetric. Its multiplicative score divides by the detected "
        "width / height, which is itself wider when x2 errs outwards, so that side's errors "
        "are skewed and the outer box can miss more than alpha there. The mean outer area is "
        "dominated by the large boxes: a global radius that leaves large boxes under-covered "
        "and small ones over-covered (per size table) reaches a given overall coverage with "
        "less area than per-group coverage at q.",
    ])
    print(markdown)
    if args.label:
        from bench._report import write_section

        write_section(f"box regions {args.label}", markdown)


if __name__ == "__main__":
    main()
