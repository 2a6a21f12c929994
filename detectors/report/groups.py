"""Unified vs group regression heads: seed 001's per-layer analyses, and the trend test of
seed 000's attention spread (issue 13).

Functions of model outputs (numpy), each with its shapes (N queries, L decoder layers,
C classes, G group heads, F frames):

- `class_switches(layer_logits [N, L, C], det_frame [N], n_frames)` -> `[F, L - 1]` int:
  per frame, how many of its queries change their top class between layer l and l + 1
  (seed 001 Fig. 6). "No object" counts as a class: a sigmoid query whose best class
  probability is below `no_object_below` is a no-object query.
- `inter_group_std(group_boxes [N, L, G, 9])` -> `[N, L, 3]`: the sample standard deviation
  (ddof = 1) of x, y, z across the G group heads' boxes of a query, per layer (Fig. 4).
- `per_layer(values [N, L] or [F, L])` -> `Binned`: median and quartiles per layer.
- `trend(binned)`: Spearman's rho of the bin medians against the bin order (seed 000's
  claims: AS falls with IoU, rho <= -0.6; rises with distance, rho >= 0.6).
- `attention_trends(dump, attn_cov [N, L, 2, 2], cell)`: for every layer, AS vs IoU and vs
  distance for one class above a score (the issue: car, score > 0.8), with both rhos and
  the share of rank-deficient C_K.
- `sample_rho(values, other)`: Spearman's rho over the detections themselves (not the bin
  medians): how much AS says about IoU or distance, one detection at a time.
- `collect_outputs(model, seeds)`: the per-query arrays above from a detector's forward
  passes over simulated scenes (final-layer-score order, `max_detections` per frame).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import spearmanr

from calibrators import Dump
from detectors.report.attention import AttentionStats, Binned, attention_stats, binned


def class_switches(layer_logits: np.ndarray, det_frame: np.ndarray, n_frames: int,
                   no_object_below: float = 0.5) -> np.ndarray:
    """`[F, L - 1]` per-frame count of queries whose top class (or no object) changes
    between consecutive layers; `layer_logits [N, L, C]` raw sigmoid logits."""
    logits = np.asarray(layer_logits, dtype=np.float64)
    if logits.ndim != 3 or logits.shape[1] < 2:
        raise ValueError(f"layer_logits must have shape [N, L >= 2, C], got {logits.shape}")
    frame = np.asarray(det_frame, dtype=np.int64)
    if frame.shape != logits.shape[:1]:
        raise ValueError(f"det_frame must have shape [{len(logits)}], got {frame.shape}")
    best = logits.max(axis=2)
    label = np.where(1.0 / (1.0 + np.exp(-best)) >= no_object_below, logits.argmax(axis=2),
                     logits.shape[2])                              # [N, L], C = no object
    switched = label[:, 1:] != label[:, :-1]                        # [N, L - 1]
    out = np.zeros((n_frames, switched.shape[1]), dtype=np.int64)
    np.add.at(out, frame, switched.astype(np.int64))
    return out


def inter_group_std(group_boxes: np.ndarray) -> np.ndarray:
    """`[N, L, 3]` std (ddof 1) of x, y, z across the G heads of `group_boxes [N, L, G, 9]`."""
    boxes = np.asarray(group_boxes, dtype=np.float64)
    if boxes.ndim != 4 or boxes.shape[3] != 9 or boxes.shape[2] < 2:
        raise ValueError(f"group_boxes must have shape [N, L, G >= 2, 9], got {boxes.shape}")
    return boxes[..., 0:3].std(axis=2, ddof=1)


def per_layer(values: np.ndarray) -> Binned:
    """Median and quartiles of `values [M, L]` per layer (labels "layer 1".."layer L")."""
    values = np.asarray(values, dtype=np.float64)
    n_layers = values.shape[1]
    return binned(values.T.reshape(-1), np.repeat(np.arange(n_layers), values.shape[0]),
                  n_layers, tuple(f"layer {i + 1}" for i in range(n_layers)))


def trend(stat: Binned, min_n: int = 5, flat: float = 1e-6) -> float:
    """Spearman's rho of the medians of bins holding >= `min_n` values against their order;
    NaN with fewer than three such bins, or when the medians are equal to a relative `flat`
    (no trend: a rho of float noise means nothing)."""
    ok = np.flatnonzero((stat.n >= min_n) & np.isfinite(stat.median))
    if len(ok) < 3:
        return float("nan")
    medians = stat.median[ok]
    if np.ptp(medians) <= flat * max(np.abs(medians).max(), 1e-300):
        return float("nan")
    return float(spearmanr(ok, medians).statistic)


def trend_interval(values: np.ndarray, bins: np.ndarray, n_bins: int, n_boot: int = 1000,
                   seed: int = 0, level: float = 0.95) -> tuple[float, float]:
    """Bootstrap interval of `trend` over the rows: `values [n]` in bins `bins [n]`
    (0..n_bins-1; other bins left out), resampled `n_boot` times with replacement. A rho
    decided by a bin of a dozen detections shows as a wide interval. (NaN, NaN) when no
    resample gives a rho."""
    values, bins = np.asarray(values, dtype=np.float64), np.asarray(bins)
    rows = (bins >= 0) & (bins < n_bins)
    values, bins = values[rows], bins[rows]
    labels = tuple(str(b) for b in range(n_bins))
    rng = np.random.default_rng(seed)
    rhos = np.array([trend(binned(values[i], bins[i], n_bins, labels))
                     for i in (rng.integers(0, len(values), len(values))
                               for _ in range(n_boot if len(values) else 0))])
    rhos = rhos[np.isfinite(rhos)]
    if len(rhos) == 0:
        return float("nan"), float("nan")
    lo, hi = np.percentile(rhos, [50 * (1 - level), 50 * (1 + level)])
    return float(lo), float(hi)


def sample_rho(values: np.ndarray, other: np.ndarray) -> float:
    """Spearman's rho of `values [n]` against `other [n]` over the rows (NaN below 3 rows
    or when either is constant)."""
    values, other = np.asarray(values, dtype=np.float64), np.asarray(other, dtype=np.float64)
    if values.shape != other.shape:
        raise ValueError(f"values and other must have one shape, got {values.shape} and "
                         f"{other.shape}")
    if len(values) < 3 or np.ptp(values) == 0 or np.ptp(other) == 0:
        return float("nan")
    return float(spearmanr(values, other).statistic)


@dataclass(frozen=True)
class LayerTrend:
    """Seed 000's statistics at one decoder layer, with the two rhos and their bootstrap
    95 % intervals over the detections (`trend_interval`), and the two per-detection rhos
    (`sample_rho`: AS against IoU > 0, AS against distance)."""

    layer: int
    stats: AttentionStats
    rho_iou: float
    rho_distance: float
    rank_deficient: float
    rho_iou_interval: tuple[float, float] = (float("nan"), float("nan"))
    rho_distance_interval: tuple[float, float] = (float("nan"), float("nan"))
    sample_rho_iou: float = float("nan")
    sample_rho_distance: float = float("nan")


def attention_trends(dump: Dump, attn_cov: np.ndarray, cell: float, class_name: str = "car",
                     min_score: float = 0.8) -> list[LayerTrend]:
    """Per layer: AS vs IoU / distance of `class_name` detections with raw score >=
    `min_score` (IoU with the final box, as seed 000), the rhos and the rank-deficient share;
    `attn_cov [N, L, 2, 2]` the raw C_K of every layer (`detectors.report.runner`)."""
    if class_name not in dump.classes:
        raise ValueError(f"class_name {class_name!r} is not one of the dump's classes")
    keep = dump.det_labels == dump.classes.index(class_name)
    sub, cov = dump.select_detections(keep), np.asarray(attn_cov)[keep]
    out = []
    for layer in range(cov.shape[1]):
        stats = attention_stats(sub, cov[:, :layer + 1], cell, min_score)
        collapsed = stats.vs_distance.collapsed
        n = stats.vs_distance.n
        share = float(np.nansum(collapsed * n) / max(n.sum(), 1))
        final, n_iou = stats.final_as, len(stats.vs_iou.labels)
        positive = stats.iou > 0
        out.append(LayerTrend(
            layer + 1, stats, trend(stats.vs_iou), trend(stats.vs_distance), share,
            trend_interval(final, stats.iou_bin, n_iou),
            trend_interval(final, stats.distance_bin, len(stats.vs_distance.labels)),
            sample_rho(final[positive], stats.iou[positive]),
            sample_rho(final, stats.distance)))
    return out


@dataclass(frozen=True)
class GroupOutputs:
    """Per kept query: `layer_logits [N, L, C]`, `group_boxes [N, L, G, 9]` (None for a
    unified head), `det_frame [N]`."""

    layer_logits: np.ndarray
    group_boxes: np.ndarray | None
    det_frame: np.ndarray
    n_frames: int


def collect_outputs(model: object, seeds: Sequence[int],
                    max_detections: int | None = None) -> GroupOutputs:
    """Run `model` (eval mode) over the simulated scenes `seeds`, keeping the top
    `max_detections` queries per frame by final-layer score (default: all)."""
    import torch

    from detectors.sim import make_frame

    cfg = model.config  # type: ignore[attr-defined]
    k = max_detections or cfg.n_queries
    logits, groups, frames = [], [], []
    for i, seed in enumerate(seeds):
        points = torch.from_numpy(np.array(make_frame(int(seed), cfg.sensor).sensor_frame.points,
                                           dtype=np.float32))
        with torch.no_grad():
            out = model([points], need_attention=False)  # type: ignore[operator]
        score = out["pred_logits"][-1, 0].sigmoid().max(dim=1).values
        order = score.topk(min(k, len(score))).indices
        logits.append(out["pred_logits"][:, 0, order].transpose(0, 1).numpy())
        if "pred_group_boxes" in out:
            groups.append(out["pred_group_boxes"][:, 0, order].transpose(0, 1).numpy())
        frames.append(np.full(len(order), i, dtype=np.int64))
    return GroupOutputs(layer_logits=np.concatenate(logits),
                        group_boxes=np.concatenate(groups) if groups else None,
                        det_frame=np.concatenate(frames), n_frames=len(seeds))
