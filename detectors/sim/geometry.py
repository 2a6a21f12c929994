"""Box geometry in the ego frame: corners, overlap tests, points in boxes, surface samples.

Boxes are ``x, y, z, w, l, h, yaw[, vx, vy]`` with ``z`` the box centre and ``l`` along the
heading ``yaw`` (nuScenes convention).
"""

from __future__ import annotations

import numpy as np


def bev_corners(boxes: np.ndarray) -> np.ndarray:
    """BEV corners of `boxes` [N, >=7], counter-clockwise from front-left. -> [N, 4, 2]."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    hl, hw = boxes[:, 4] / 2, boxes[:, 3] / 2
    local = np.array([[1, 1], [-1, 1], [-1, -1], [1, -1]], dtype=np.float64)
    dx = local[None, :, 0] * hl[:, None]
    dy = local[None, :, 1] * hw[:, None]
    x = boxes[:, None, 0] + c[:, None] * dx - s[:, None] * dy
    y = boxes[:, None, 1] + s[:, None] * dx + c[:, None] * dy
    return np.stack([x, y], axis=-1)


def bev_outline(box: np.ndarray) -> np.ndarray:
    """Closed BEV outline of one box `[>=7]` for drawing: 4 corners, then the first. -> [5, 2]."""
    corners = bev_corners(np.asarray(box, dtype=np.float64)[None, :7])[0]
    return np.vstack([corners, corners[:1]])


def overlaps(box: np.ndarray, others: np.ndarray, margin: float = 0.1) -> np.ndarray:
    """Whether `box` [>=7] intersects each of `others` [N, >=7] (BEV SAT and z interval).

    Two boxes count as overlapping when they are closer than `margin` metres. -> [N] bool.
    """
    if len(others) == 0:
        return np.zeros(0, dtype=bool)
    z_sep = np.abs(others[:, 2] - box[2]) > (others[:, 5] + box[5]) / 2 + margin
    axes_a = np.array([[np.cos(box[6]), np.sin(box[6])], [-np.sin(box[6]), np.cos(box[6])]])
    co, so = np.cos(others[:, 6]), np.sin(others[:, 6])
    axes_b = np.stack([np.stack([co, so], -1), np.stack([-so, co], -1)], axis=1)  # [N, 2, 2]
    axes = np.concatenate([np.broadcast_to(axes_a, (len(others), 2, 2)), axes_b], axis=1)
    delta = others[:, None, :2] - box[None, None, :2]  # [N, 1, 2]
    dist = np.abs(np.sum(delta * axes, axis=-1))  # [N, 4]
    # Half-extent of each box projected on each axis.
    ra = box[4] / 2 * np.abs(axes @ axes_a[0]) + box[3] / 2 * np.abs(axes @ axes_a[1])
    rb = others[:, None, 4] / 2 * np.abs(np.sum(axes * axes_b[:, :1], -1)) + others[
        :, None, 3
    ] / 2 * np.abs(np.sum(axes * axes_b[:, 1:2], -1))
    separated = np.any(dist > ra + rb + margin, axis=1)
    return ~(separated | z_sep)


def points_in_boxes(points: np.ndarray, boxes: np.ndarray, pad: float = 0.0) -> np.ndarray:
    """Membership of `points` [P, >=3] in `boxes` [N, >=7] grown by `pad`. -> [P, N] bool."""
    rel = points[:, None, :3] - boxes[None, :, :3]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    lx = c * rel[..., 0] + s * rel[..., 1]
    ly = -s * rel[..., 0] + c * rel[..., 1]
    return (
        (np.abs(lx) <= boxes[:, 4] / 2 + pad)
        & (np.abs(ly) <= boxes[:, 3] / 2 + pad)
        & (np.abs(rel[..., 2]) <= boxes[:, 5] / 2 + pad)
    )


def bev_distance_to_box(origin: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """BEV distance from `origin` [2] to the nearest point of each box [N, >=7]. -> [N]."""
    rel = origin[None, :2] - boxes[:, :2]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    lx = np.abs(c * rel[:, 0] + s * rel[:, 1]) - boxes[:, 4] / 2
    ly = np.abs(-s * rel[:, 0] + c * rel[:, 1]) - boxes[:, 3] / 2
    return np.hypot(np.maximum(lx, 0.0), np.maximum(ly, 0.0))


def sample_visible_sides(
    rng: np.random.Generator, origin: np.ndarray, boxes: np.ndarray, counts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Random points on the vertical faces of `boxes` [N, >=7] that face `origin` [3].

    Faces are chosen with probability proportional to their apparent width seen from
    `origin`; heights are uniform over the middle 80 % of the box.
    counts: [N] points per box. -> (points [sum(counts), 3], owner [sum(counts)] box index).
    """
    owner = np.repeat(np.arange(len(boxes)), counts)
    if owner.size == 0:
        return np.zeros((0, 3)), owner
    b = boxes[owner]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    # Face k: outward normal in box frame, half-extent along the normal, face half-length.
    normals = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]], dtype=np.float64)
    depth = np.stack([b[:, 4], b[:, 3], b[:, 4], b[:, 3]], 1) / 2  # [M, 4]
    half_len = np.stack([b[:, 3], b[:, 4], b[:, 3], b[:, 4]], 1) / 2
    rel = origin[None, :2] - b[:, :2]
    ox = c * rel[:, 0] + s * rel[:, 1]
    oy = -s * rel[:, 0] + c * rel[:, 1]
    # Apparent width of face k ~ max(0, (n . (o - face centre))) * face length / distance.
    facing = normals[None, :, 0] * ox[:, None] + normals[None, :, 1] * oy[:, None] - depth
    dist = np.hypot(ox, oy)[:, None] + 1e-6
    weight = np.maximum(facing, 0.0) * half_len / dist
    weight = weight + 1e-9 * (weight.sum(1, keepdims=True) == 0)
    cum = np.cumsum(weight, axis=1)
    face = np.minimum(np.sum(cum < rng.random(len(b))[:, None] * cum[:, -1:], axis=1), 3)
    n = normals[face]
    along = rng.uniform(-1.0, 1.0, len(b)) * half_len[np.arange(len(b)), face]
    d = depth[np.arange(len(b)), face]
    lx = n[:, 0] * d - n[:, 1] * along
    ly = n[:, 1] * d + n[:, 0] * along
    x = b[:, 0] + c * lx - s * ly
    y = b[:, 1] + s * lx + c * ly
    z = b[:, 2] + rng.uniform(-0.4, 0.4, len(b)) * b[:, 5]
    return np.stack([x, y, z], axis=1), owner


def segment_blocked(
    origin: np.ndarray, targets: np.ndarray, owner: np.ndarray, boxes: np.ndarray
) -> np.ndarray:
    """Whether the BEV segment origin -> target crosses a box other than its owner.

    origin: [2]; targets: [N, 2]; owner: [N] index into `boxes` (-1 = none);
    boxes: [B, >=7] (only x, y, w, l, yaw used). -> [N] bool.
    """
    if len(targets) == 0 or len(boxes) == 0:
        return np.zeros(len(targets), dtype=bool)
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    rel = origin[None, :2] - boxes[:, :2]  # [B, 2]
    ox = c * rel[:, 0] + s * rel[:, 1]
    oy = -s * rel[:, 0] + c * rel[:, 1]
    d = targets[:, None, :] - origin[None, None, :2]  # [N, 1, 2]
    dx = c[None] * d[..., 0] + s[None] * d[..., 1]  # [N, B]
    dy = -s[None] * d[..., 0] + c[None] * d[..., 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_near, t_far = _slab(ox[None], dx, boxes[None, :, 4] / 2)
        t_near2, t_far2 = _slab(oy[None], dy, boxes[None, :, 3] / 2)
    lo = np.maximum(t_near, t_near2)
    hi = np.minimum(t_far, t_far2)
    hit = (lo <= hi) & (hi > 0.0) & (lo < 0.97)
    hit[np.arange(len(targets))[owner >= 0], owner[owner >= 0]] = False
    return hit.any(axis=1)


def _slab(o: np.ndarray, d: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit ray parameters of the slab |o + t d| <= half (broadcast)."""
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    t1 = (-half - o) / d
    t2 = (half - o) / d
    return np.minimum(t1, t2), np.maximum(t1, t2)
