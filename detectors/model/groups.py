"""Class groups of the group regression head (seed 001, Sec. III-C) and their arithmetic.

Six groups of similar shape and prevalence, as CBGS (Zhu et al.) and seed 001 use them:
(car), (truck, construction vehicle), (bus, trailer), (barrier), (motorcycle, bicycle),
(pedestrian, traffic cone). A class's *group score* is the sum of the sigmoid probabilities
of the classes in the group; option A of the paper's query refinement (Fig. 3) moves the
next layer's anchor to the group-score-weighted mean of the G heads' centres.

Shapes (B frames, Q queries, C classes, G groups):

    class_group [C] int64 group of every class
    group_scores(logits [..., C], class_group, G) -> [..., G]
    weighted_centre(centres [..., G, 2], scores [..., G]) -> [..., 2]
    select_group(values [..., G, K], index [...]) -> [..., K]
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor

#: The six class groups of seed 001 (nuScenes class names).
DEFAULT_GROUPS: tuple[tuple[str, ...], ...] = (
    ("car",), ("truck", "construction_vehicle"), ("bus", "trailer"), ("barrier",),
    ("motorcycle", "bicycle"), ("pedestrian", "traffic_cone"))


def class_groups(classes: Sequence[str], groups: Sequence[Sequence[str]]) -> tuple[int, ...]:
    """The group index of every class; every class must be in exactly one group."""
    owner: dict[str, int] = {}
    for g, members in enumerate(groups):
        if not members:
            raise ValueError(f"groups[{g}] is empty")
        for name in members:
            if name in owner:
                raise ValueError(f"groups: class {name!r} is in groups {owner[name]} and {g}")
            owner[name] = g
    unknown = sorted(set(owner) - set(classes))
    if unknown:
        raise ValueError(f"groups: unknown classes {unknown}")
    missing = [c for c in classes if c not in owner]
    if missing:
        raise ValueError(f"groups: classes {missing} are in no group")
    return tuple(owner[c] for c in classes)


def group_scores(logits: Tensor, class_group: Tensor, n_groups: int) -> Tensor:
    """`[..., C]` sigmoid logits -> `[..., G]` summed class probabilities per group."""
    probs = logits.sigmoid()
    out = probs.new_zeros(*probs.shape[:-1], n_groups)
    return out.index_add_(-1, class_group.to(probs.device), probs)


def weighted_centre(centres: Tensor, scores: Tensor, eps: float = 1e-6) -> Tensor:
    """Option A: `[..., G, 2]` centres weighted by `[..., G]` group scores -> `[..., 2]`."""
    w = scores.clamp_min(0) + eps  # all-zero scores fall back to the plain mean
    return (w[..., None] * centres).sum(-2) / w.sum(-1, keepdim=True)


def select_group(values: Tensor, index: Tensor) -> Tensor:
    """`values [..., G, K]` at group `index [...]` (int64) -> `[..., K]`."""
    k = values.shape[-1]
    gathered = values.gather(-2, index[..., None, None].expand(*index.shape, 1, k))
    return gathered.squeeze(-2)
