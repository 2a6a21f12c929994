"""Matched (detected box, true box) pairs for the box-region bench: read from a detector's COCO
results and instances, or drawn from the seeded synthetic set `bench_box_regions` describes,
and split by image."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.boxes2d import (
    box_edges,
    edge_covariance,
    edge_sigma,
    match_labels,
    read_coco_instances,
    read_coco_results,
)

# The synthetic classes: frequency, size range sqrt(w·h) (px, log-uniform), aspect w/h, and
# the noise slope k of σ = u·(0.5 + k·w).
SYNTHETIC_CLASSES = (
    (1, 0.45, (12.0, 400.0), 1.5, 0.05),
    (2, 0.30, (8.0, 300.0), 0.4, 0.08),
    (3, 0.15, (16.0, 250.0), 1.0, 0.10),
    (4, 0.10, (20.0, 400.0), 1.2, 0.04),
)
WIDTH, HEIGHT = 640.0, 480.0


@dataclass(frozen=True)
class Pairs:
    """Matched true positives: detected and true COCO boxes `[M, 4]`, class `[M]`, image id
    `[M]`, the detector's score `[M]`, its image's `image_size [M, 2]`, and per edge the
    layers' σ floored at 1 px (`sigma`, the scaled score's) and unfloored (`spread`, what
    `EdgeErrorScale` reads), both `[M, 4]` and None without decoder layers."""

    det: np.ndarray
    true: np.ndarray
    labels: np.ndarray
    image_id: np.ndarray
    score: np.ndarray
    image_size: np.ndarray
    sigma: np.ndarray | None
    spread: np.ndarray | None

    def take(self, rows: np.ndarray) -> Pairs:
        return Pairs(self.det[rows], self.true[rows], self.labels[rows], self.image_id[rows],
                     self.score[rows], self.image_size[rows],
                     None if self.sigma is None else self.sigma[rows],
                     None if self.spread is None else self.spread[rows])


def synthetic_pairs(n_images: int = 6000, per_image: float = 4.0, layers: int = 6,
                    seed: int = 0) -> Pairs:
    """The seeded synthetic set of the module docstring."""
    rng = np.random.default_rng(seed)
    counts = rng.poisson(per_image, n_images)
    image_id = np.repeat(np.arange(1, n_images + 1), counts)
    m = len(image_id)
    cls = rng.choice(len(SYNTHETIC_CLASSES), m, p=[c[1] for c in SYNTHETIC_CLASSES])
    lo = np.array([c[2][0] for c in SYNTHETIC_CLASSES])[cls]
    hi = np.array([c[2][1] for c in SYNTHETIC_CLASSES])[cls]
    aspect = np.array([c[3] for c in SYNTHETIC_CLASSES])[cls] * np.exp(rng.normal(0, 0.2, m))
    k = np.array([c[4] for c in SYNTHETIC_CLASSES])[cls]
    size = np.exp(rng.uniform(np.log(lo), np.log(hi)))
    w, h = size * np.sqrt(aspect), size / np.sqrt(aspect)
    xy = rng.uniform(0, 1, (m, 2)) * np.maximum(np.c_[WIDTH - w, HEIGHT - h], 1.0)
    true = np.c_[xy, w, h]
    u = np.exp(rng.normal(0, 0.35, m))
    sig = u[:, None] * (0.5 + k[:, None] * np.c_[w, h, w, h])         # x1, y1, x2, y2
    dof = 5.0
    err = rng.standard_t(dof, (m, 4)) / np.sqrt(dof / (dof - 2)) * sig
    edges = box_edges(true) + err
    edges[:, 2:] = np.maximum(edges[:, 2:], edges[:, :2] + 1.0)       # at least 1 px wide
    det = np.c_[edges[:, :2], edges[:, 2:] - edges[:, :2]]
    # decoder layers around the detection (the last layer is the detection itself)
    layer_edges = edges[:, None, :] + rng.normal(0, 1, (m, layers, 4)) * sig[:, None, :]
    layer_edges[:, -1] = edges
    layer_edges[..., 2:] = np.maximum(layer_edges[..., 2:], layer_edges[..., :2] + 1e-3)
    layer_boxes = np.concatenate([layer_edges[..., :2],
                                  layer_edges[..., 2:] - layer_edges[..., :2]], axis=-1)
    sigma = edge_sigma(edge_covariance(layer_boxes, min_sigma=1.0))
    spread = edge_sigma(edge_covariance(layer_boxes, min_sigma=0.0))
    labels = np.array([c[0] for c in SYNTHETIC_CLASSES])[cls]
    score = rng.uniform(0.05, 0.95, m)         # no localisation information in the score
    image_size = np.tile([WIDTH, HEIGHT], (m, 1))
    return Pairs(det, true, labels, image_id, score, image_size, sigma, spread)


def coco_pairs(results: str, instances: str, iou: float = 0.5) -> Pairs:
    """The true positives of a COCO results file against its instances (IoU `iou`)."""
    gt = read_coco_instances(instances)
    found = read_coco_results(results, instances=gt)
    labels = match_labels(found, gt.ground_truth, iou_threshold=iou)
    tp = labels.true_positive & ~labels.ignored
    det = found.bbox[tp]
    keep = (det[:, 2] > 0) & (det[:, 3] > 0)    # the multiplicative score divides by w, h
    rows = np.flatnonzero(tp)[keep]
    sigma = spread = None
    if found.layer_boxes is not None and found.layer_boxes.shape[1] >= 2:
        sigma = edge_sigma(edge_covariance(found.layer_boxes[rows], min_sigma=1.0))
        spread = edge_sigma(edge_covariance(found.layer_boxes[rows], min_sigma=0.0))
    return Pairs(found.bbox[rows], gt.ground_truth.bbox[labels.gt_row[rows]],
                 found.category_id[rows], found.image_id[rows], found.score[rows],
                 gt.image_size(found.image_id[rows]), sigma, spread)


def calibration_split(image_id: np.ndarray, seed: int, fraction: float = 0.5) -> np.ndarray:
    """Boolean `[M]`: the pair's image is in the calibration split, by a seeded hash
    (splitmix64) of the image id, so every box of an image falls on the same side."""
    with np.errstate(over="ignore"):
        z = np.asarray(image_id).astype(np.uint64) + np.uint64(seed) * np.uint64(
            0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(11)).astype(np.float64) / float(1 << 53) < fraction


