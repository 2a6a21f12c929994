"""Fit a 2-D profile: `fit_profile_2d(detections, instances, options) -> Profile2D`, the 2-D
counterpart of `calibrators.fit.fit_profile`.

1. Every detection's category and image must be the instances' (a `FieldError` names the
   first that is not); with `logits`, `score_mode` says how they read.
2. Each detection is labelled by the COCO rule at `iou_threshold` (`match_labels`); COCO's
   ignored detections take no part.
3. The images are split by a seeded hash of their id (`calibrators.data.held_out_frames`, as
   3-D frames are): a `holdout` fraction for the report, then a `calibration` fraction of the
   rest kept apart from the fitting part. An image's side depends on its id and the seed
   alone, never on the input's order.
4. Score stage (`_score_fit`): every candidate fit on the fitting part, the lowest NLL on the
   calibration part chosen, refit on both.
5. Box regions: `ConformalBoxes` fit on the calibration part's true positives (their matched
   ground truth), per category × COCO size. By default (`region_score="auto"`) `adaptive`:
   each edge's error divided by the `EdgeErrorScale` fit on the fitting part's true
   positives; with fewer than `MIN_SCALE_FIT` of those, `scaled` by the edge σ of the decoder
   layers' spread when the detections carry `layer_boxes` (L >= 2), else `additive`.
   Without a calibration part the profile has no regions.
6. Report (`_fit_report`): the held-out images when `holdout > 0`, and every candidate's
   held-out NLL, ECE and D-ECE.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from calibrators.boxes2d._box_scores import conformity_score
from calibrators.boxes2d._boxes import Detections2D
from calibrators.boxes2d._coco_instances import CocoInstances
from calibrators.boxes2d._conformal_boxes import ConformalBoxes
from calibrators.boxes2d._error_scale import EdgeErrorScale
from calibrators.boxes2d._fit_options import FitOptions2D
from calibrators.boxes2d._fit_report import REPORT_LEVELS, holdout_report
from calibrators.boxes2d._labels import match_labels
from calibrators.boxes2d._layer_spread import edge_covariance, edge_sigma
from calibrators.boxes2d._profile2d import Profile2D
from calibrators.boxes2d._score_fit import ScoreData, fit_score_stage_2d
from calibrators.boxes2d._score_inputs import score_inputs
from calibrators.core.errors import FieldError, OptionError
from calibrators.data import held_out_frames
from calibrators.profile import make_provenance

__all__ = ["MIN_SCALE_FIT", "check_fit_input_2d", "fit_profile_2d", "held_out_images"]

#: Fitting-part true positives the adaptive regions' edge-error scale needs (about ten per
#: coefficient).
MIN_SCALE_FIT: int = 100

Progress = Callable[[str, float], None]


def fit_profile_2d(detections: Detections2D, instances: CocoInstances,
                   options: FitOptions2D | None = None, *, results_sha256: str | None = None,
                   instances_sha256: str | None = None, progress: Progress | None = None,
                   **overrides: Any) -> Profile2D:
    """Fit a 2-D profile (module docstring) on `detections` (`read_coco_results`) and the
    `instances` they were made on (`read_coco_instances`). `options` (default: all defaults)
    with keyword `overrides` replacing single options; the files' hashes for the provenance
    (None: a hash of the arrays); `progress(stage, fraction)` as `fit_profile` calls it.
    Raises `OptionError` naming a bad option, `FieldError` naming a bad field, ValueError for
    data that cannot be fit (no true positive, no false positive)."""
    opts = options if options is not None else FitOptions2D()
    if not isinstance(opts, FitOptions2D):
        raise OptionError("options", f"options must be a FitOptions2D, got {type(opts).__name__}")
    if overrides:
        opts = FitOptions2D.from_dict({**opts.to_dict(), **overrides})
    say = progress if progress is not None else _quiet
    region_score = check_fit_input_2d(detections, instances, opts)
    say("prepare", 0.0)
    ids = tuple(int(i) for i in instances.category_id)
    z, labels = score_inputs(detections, ids, opts.score_mode)
    truth = instances.ground_truth
    say("match", 0.1)
    match = match_labels(detections, truth, opts.iou_threshold)
    data = ScoreData(z, labels, instances.image_size(detections.image_id), detections, match,
                     len(ids))
    held_img = held_out_images(instances.image_id, opts.holdout, opts.seed, "holdout")
    calib_img = np.zeros_like(held_img)
    if opts.calibration > 0:
        calib_img[~held_img] = held_out_images(instances.image_id[~held_img], opts.calibration,
                                               opts.seed + 1, "calibration")
    row = instances.image_rows(detections.image_id)
    counted = ~match.ignored
    held, calib = held_img[row], calib_img[row] & counted
    train = counted & ~held & ~calib_img[row]
    say("scores", 0.25)
    stage, selection = fit_score_stage_2d(data, train, calib if calib.any() else None,
                                          opts.score_method, opts.min_samples)
    say("regions", 0.55)
    regions = (_regions(data, truth.bbox, train, calib, region_score, opts, ids)
               if calib.any() else None)
    profile = Profile2D(
        category_ids=ids, category_names=tuple(instances.category_name),
        score_mode=opts.score_mode, image_size=_common_size(instances),
        matching={"rule": "coco_iou", "iou_threshold": opts.iou_threshold},
        score_calibration=stage.to_dict(), regions=regions,
        provenance=make_provenance(
            results_sha256=results_sha256 or _digest(detections),
            instances_sha256=instances_sha256 or _digest(truth), n_images=len(instances.image_id),
            n_detections=len(detections), n_ground_truth=len(truth),
            n_holdout_images=int(held_img.sum()), n_calibration_images=int(calib_img.sum()),
            n_true_positives=int(match.true_positive.sum()),
            n_calibration_true_positives=int((calib & match.true_positive).sum()),
            seed=opts.seed, options=opts.to_dict()))
    say("report", 0.75)
    report = {"selection": {"score": selection,
                            "regions": None if regions is None else _guarantees(profile)},
              "holdout": holdout_report(profile, data, truth, held, held_img[
                  instances.image_rows(truth.image_id)]) if held.any() else None}
    profile = replace(profile, report=report)
    say("done", 1.0)
    return profile


def check_fit_input_2d(detections: Detections2D, instances: CocoInstances,
                       options: FitOptions2D) -> str:
    """Raise `FieldError` / `OptionError` naming what makes `detections` and `instances`
    unfit for a 2-D fit with `options` (an image or category the instances lack, logits
    without `score_mode` or the reverse, logits of the wrong width, scaled regions without
    layer boxes); returns the region score the fit will use (for `auto`, the one it falls
    back to when the fitting part holds fewer than `MIN_SCALE_FIT` true positives).
    Front ends call it to refuse an upload before queueing a fit."""
    if not isinstance(instances, CocoInstances):
        raise FieldError("instances", "instances must be a CocoInstances (read_coco_instances)")
    if not isinstance(detections, Detections2D) or len(detections) == 0:
        raise FieldError("detections", "detections must be a non-empty Detections2D")
    instances.image_rows(detections.image_id)
    if (detections.logits is None) != (options.score_mode is None):
        raise OptionError("score_mode", "the detections carry logits: state score_mode "
                          "(sigmoid or softmax)" if detections.logits is not None else
                          "score_mode reads the detections' logits, and they carry none")
    score_inputs(detections, [int(i) for i in instances.category_id], options.score_mode)
    return _region_score(detections, options)


def held_out_images(image_id: np.ndarray, fraction: float, seed: int, option: str
                    ) -> np.ndarray:
    """`[I]` bool: the `round(fraction · I)` images (at least one when `fraction > 0`) whose
    seeded id hash is smallest (`held_out_frames` on the ids); `OptionError` naming `option`
    when no image would be left."""
    if fraction <= 0:
        return np.zeros(len(image_id), dtype=bool)
    try:
        return held_out_frames(np.asarray(image_id).astype(str), fraction, seed)
    except ValueError:
        raise OptionError(option, f"{option}={fraction} of {len(image_id)} images leaves no "
                                  "image on the other side") from None


def _region_score(detections: Detections2D, opts: FitOptions2D) -> str:
    layered = detections.layer_boxes is not None and detections.layer_boxes.shape[1] >= 2
    if opts.region_score == "scaled" and not layered:
        raise OptionError("region_score", "region_score='scaled' needs the detections' "
                                          "layer_boxes of L >= 2 decoder layers")
    if opts.region_score == "auto":
        return "scaled" if layered else "additive"
    return opts.region_score


def _regions(data: ScoreData, truth_bbox: np.ndarray, train: np.ndarray, calib: np.ndarray,
             score: str, opts: FitOptions2D, ids: tuple[int, ...]) -> dict[str, Any] | None:
    """The `regions` field: `ConformalBoxes` on the calibration part's true positives, their
    errors scaled by the edge-error scale fit on the fitting part's (adaptive), by the layer
    spread (scaled) or not at all (additive). `score` is `_region_score`'s; with
    `region_score='auto'` the regions are adaptive when the fitting part holds
    `MIN_SCALE_FIT` true positives."""
    rows = calib & data.match.true_positive
    if not rows.any():
        return None
    fit_rows = train & data.match.true_positive
    if opts.region_score == "auto" and fit_rows.sum() >= MIN_SCALE_FIT:
        score = "adaptive"
    elif score == "adaptive" and fit_rows.sum() < MIN_SCALE_FIT:
        raise OptionError("region_score", f"region_score='adaptive' fits its edge-error scale "
                          f"on the fitting part's true positives: {int(fit_rows.sum())} < "
                          f"{MIN_SCALE_FIT}")
    dets, gt = data.detections, data.match.gt_row
    layered = dets.layer_boxes is not None and dets.layer_boxes.shape[1] >= 2
    out: dict[str, Any] = {"score": score, "min_sigma": opts.min_sigma}
    sigma = None
    if score == "scaled":
        sigma = edge_sigma(edge_covariance(dets.layer_boxes[rows], opts.min_sigma))
    elif score == "adaptive":
        def inputs(m: np.ndarray) -> tuple[np.ndarray, ...]:
            spread = edge_sigma(edge_covariance(dets.layer_boxes[m], 0.0)) if layered else None
            return dets.bbox[m], dets.score[m], spread, data.image_size[m]
        box, p, spread, size = inputs(fit_rows)
        scale = EdgeErrorScale().fit(box, truth_bbox[gt[fit_rows]], p, spread, size)
        sigma = scale.predict(*inputs(rows))
        out["scale"] = scale.to_dict()
    boxes = ConformalBoxes(score=conformity_score(score), min_group=opts.min_group).fit(
        dets.bbox[rows], truth_bbox[gt[rows]], dets.category_id[rows], sigma,
        all_classes=list(ids))
    return {**out, "conformal": boxes.to_dict()}


def _guarantees(profile: Profile2D) -> list[dict[str, Any]]:
    """What each category × size cell's regions guarantee at the report levels, by name."""
    assert profile.box_regions is not None
    names = dict(zip(profile.category_ids, profile.category_names, strict=True))
    return [{**row, "class": names.get(row["class"], row["class"])}
            for row in profile.box_regions.guarantees(REPORT_LEVELS)]


def _common_size(instances: CocoInstances) -> tuple[int, int] | None:
    sizes = set(zip(instances.width.tolist(), instances.height.tolist(), strict=True))
    return next(iter(sizes)) if len(sizes) == 1 else None


def _digest(boxes: Any) -> str:
    """sha256 over the containers' arrays (for inputs that came without a file)."""
    h = hashlib.sha256()
    for name in ("image_id", "category_id", "bbox", "score", "logits", "layer_boxes", "area",
                 "iscrowd"):
        arr = getattr(boxes, name, None)
        h.update(b"none" if arr is None else str(arr.shape).encode()
                 + np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _quiet(stage: str, fraction: float) -> None:
    """Default progress callback: does nothing."""
