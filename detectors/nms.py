"""Class-wise circle NMS on BEV box centres (CenterPoint's radii), for the "topk_nms" decoding.

A DETR decoder is trained one-to-one, yet on this machine's small models two queries still
land on one object now and then, and under the top-K (query, class) decoding both come out
as detections of the same class: the second is a false positive of high score. Circle NMS
(CenterPoint, Yin et al. 2021) keeps, class by class and in score order, a detection only if
no kept one of its class lies within the class's radius in the ground plane. A query's
detections of *different* classes never suppress each other, so the top-K decoding's second
class (a trailer for a bus) survives.

The radii are CenterPoint's nuScenes ones (its `min_radius`, squared metres, per head:
car 4, truck and construction vehicle 12, bus and trailer 10, barrier 1, motorcycle and
bicycle 0.85, pedestrian and traffic cone 0.175); its heads are seed 001's class groups.

Shapes: centres [K, 2] metres, labels [K] int64 class indices, scores [K] -> keep [K'] int64
indices into K, in descending score order.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

#: Squared suppression radius (m^2) per nuScenes class (CenterPoint's `min_radius`).
NMS_RADIUS_SQ: dict[str, float] = {
    "car": 4.0, "truck": 12.0, "construction_vehicle": 12.0, "bus": 10.0, "trailer": 10.0,
    "barrier": 1.0, "motorcycle": 0.85, "bicycle": 0.85, "pedestrian": 0.175,
    "traffic_cone": 0.175,
}


def class_radii_sq(classes: Sequence[str]) -> Tensor:
    """`[C]` squared radii of `classes` (ValueError naming a class without one)."""
    missing = [c for c in classes if c not in NMS_RADIUS_SQ]
    if missing:
        raise ValueError(f"no circle-NMS radius for classes {missing}; "
                         f"known: {sorted(NMS_RADIUS_SQ)}")
    return torch.tensor([NMS_RADIUS_SQ[c] for c in classes], dtype=torch.float32)


def circle_nms(centres: Tensor, labels: Tensor, scores: Tensor, radii_sq: Tensor) -> Tensor:
    """Greedy class-wise circle NMS; returns the kept indices, highest score first.

    `radii_sq [C]` is indexed by `labels`. Ties in score keep the earlier index."""
    if not (centres.ndim == 2 and centres.shape[1] == 2 and labels.shape == scores.shape
            == centres.shape[:1]):
        raise ValueError(f"circle_nms needs centres [K, 2], labels [K], scores [K]; got "
                         f"{tuple(centres.shape)}, {tuple(labels.shape)}, "
                         f"{tuple(scores.shape)}")
    order = torch.sort(scores, descending=True, stable=True).indices
    xy, lab = centres[order].float(), labels[order]
    d2 = torch.cdist(xy, xy).square()
    close = (d2 < radii_sq.to(xy)[lab][:, None]) & (lab[:, None] == lab[None, :])
    # Greedy in score order: a detection survives when no surviving, higher-scored one of its
    # class is close. K is at most a few hundred: a loop over the rows of a small bool matrix.
    near = close.numpy()
    alive = np.ones(len(order), dtype=bool)
    for i in range(len(order)):
        if alive[i]:
            alive[i + 1:] &= ~near[i, i + 1:]
    return order[torch.from_numpy(alive)]
