"""Write merged detections of many frames as a validation dump v1 (`calibrators.Dump`).

The merged covariance (sample covariance of each cluster) becomes the dump's `det_cov` over
the merge's `dims`, so `fit_profile(dump, cov_source="given")` depth-scales it. Every frame's
merge must carry `layer_logits`; with `layer_boxes` too, all L layers are written, otherwise
only the final layer (L = 1: the final logits and the merged box).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.data import Dump
from detectors.baselines.cluster import MergedDetections


def merged_dump(merged: Sequence[MergedDetections], frame_ids: Sequence[str],
                classes: Sequence[str], score_mode: str, gt_frame: np.ndarray,
                gt_labels: np.ndarray, gt_boxes: np.ndarray,
                ego_translation: np.ndarray | None = None) -> Dump:
    """A `Dump` of F frames: `merged[f]` are frame f's detections (`frame_ids [F]`).

    classes [C] in logit column order; score_mode as the logits'; gt_frame [G] int index into
    frame_ids, gt_labels [G], gt_boxes [G, 9]; ego_translation [F, 3] | None. The `Dump`
    validates everything else (a ValueError names the key).
    """
    if len(merged) != len(frame_ids):
        raise ValueError(f"merged has {len(merged)} frames but frame_ids has {len(frame_ids)}")
    if not merged:
        raise ValueError("merged must hold at least one frame")
    dims = {m.dims for m in merged}
    if len(dims) != 1:
        raise ValueError(f"merged frames disagree on the covariance dims: {sorted(dims)}")
    missing = [f for f, m in enumerate(merged) if m.layer_logits is None]
    if missing:
        raise ValueError(f"merged[{missing[0]}] has no layer_logits; merge with layer_logits to "
                         f"write a dump")
    with_layers = all(m.layer_boxes is not None for m in merged)
    logits = [m.layer_logits if with_layers else m.layer_logits[:, -1:] for m in merged]
    boxes = [m.layer_boxes if with_layers else m.boxes[:, None] for m in merged]
    return Dump(
        classes=tuple(classes), score_mode=score_mode, frame_ids=np.asarray(frame_ids),
        det_frame=np.repeat(np.arange(len(merged)), [len(m) for m in merged]),
        det_logits=np.concatenate(logits), det_boxes=np.concatenate(boxes),
        gt_frame=gt_frame, gt_labels=gt_labels, gt_boxes=gt_boxes,
        ego_translation=ego_translation,
        det_cov=np.concatenate([m.covariances for m in merged]), cov_dims=dims.pop())
