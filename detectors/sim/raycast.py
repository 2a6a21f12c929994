"""Vectorised ray casting against oriented boxes and a flat ground (lidar and camera).

A sensor is a grid of rays: ``A`` azimuths uniform over 360 degrees times ``E`` elevations.
Each box is only tested against the rays inside its azimuth / elevation window, so the cost
is proportional to the solid angle the boxes cover, not to ``rays x boxes``. The nearest hit
along each ray wins (a z-buffer per ray), which gives self-occlusion (only faces towards the
sensor are seen) and occlusion by nearer objects for free. ``cast`` is ``box_hits`` (every
ray-box hit, each box as if alone) then ``nearest_hits`` (that z-buffer, with the ground).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibrators.core.vocab import wrap_angle
from detectors.sim.geometry import bev_corners, bev_distance_to_box


@dataclass(frozen=True)
class RayGrid:
    """Ray directions of one sensor at `origin` [3].

    n_azimuth: A azimuths at ``2 pi k / A``; elevation: [E] ascending, radians.
    """

    origin: np.ndarray
    n_azimuth: int
    elevation: np.ndarray

    @property
    def n_rays(self) -> int:
        """A * E."""
        return self.n_azimuth * len(self.elevation)

    def directions(self, ray: np.ndarray) -> np.ndarray:
        """Unit directions of rays ``e * A + a`` [N]. -> [N, 3]."""
        e, a = np.divmod(ray, self.n_azimuth)
        az = a * (2 * np.pi / self.n_azimuth)
        el = self.elevation[e]
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)


@dataclass(frozen=True)
class RayHits:
    """Nearest hit of every ray that hits something within range.

    ray: [H] int64 ray index; dist: [H] range along the ray (m); owner: [H] int64 box index
    (-1 = ground); cos_incidence: [H] |cos| of the angle between ray and surface normal;
    points: [H, 3] exact hit positions.
    """

    ray: np.ndarray
    dist: np.ndarray
    owner: np.ndarray
    cos_incidence: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class BoxHits:
    """Every hit of a ray on a box within range, each box as if it were alone (no z-buffer).

    ray: [K] int64 ray index; dist: [K] range of the box's near face along the ray (m);
    owner: [K] int64 box index; cos_incidence: [K] as in RayHits. A box's rows are the rays
    it would own if nothing else were in the scene.
    """

    ray: np.ndarray
    dist: np.ndarray
    owner: np.ndarray
    cos_incidence: np.ndarray


@dataclass(frozen=True)
class AngularExtent:
    """Directions each box covers, seen from an origin (radians).

    azimuth: [B] bearing of the box centre; az_lo, az_hi: [B] smallest and largest azimuth
    offset of its BEV corners from `azimuth` (its whole azimuth span: the faces are
    vertical); el_lo, el_hi: [B] lowest and highest elevation of the box; d_min, d_max: [B]
    BEV distance to its nearest point and to its farthest corner.
    """

    azimuth: np.ndarray
    az_lo: np.ndarray
    az_hi: np.ndarray
    el_lo: np.ndarray
    el_hi: np.ndarray
    d_min: np.ndarray
    d_max: np.ndarray


def cast(grid: RayGrid, boxes: np.ndarray, max_range: float) -> RayHits:
    """Cast every ray of `grid` against `boxes` [B, >=7] and the ground plane z = 0."""
    return nearest_hits(grid, box_hits(grid, boxes, max_range), max_range)


def box_hits(grid: RayGrid, boxes: np.ndarray, max_range: float) -> BoxHits:
    """Every ray of `grid` that hits a box of `boxes` [B, >=7] within `max_range`."""
    origin = np.asarray(grid.origin, dtype=np.float64)
    return BoxHits(*_box_hits(grid, boxes, origin, max_range))


def nearest_hits(grid: RayGrid, hits: BoxHits, max_range: float) -> RayHits:
    """The nearest of `hits` and the ground plane z = 0 along every ray (the z-buffer)."""
    origin = np.asarray(grid.origin, dtype=np.float64)
    ray, dist, owner, cos_inc = hits.ray, hits.dist, hits.owner, hits.cos_incidence
    g_ray, g_dist = _ground_hits(grid, origin, max_range)
    g_cos = -np.sin(grid.elevation[g_ray // grid.n_azimuth])
    ray = np.concatenate([ray, g_ray])
    dist = np.concatenate([dist, g_dist])
    owner = np.concatenate([owner, np.full(len(g_ray), -1, dtype=np.int64)])
    cos_inc = np.concatenate([cos_inc, g_cos])
    order = np.lexsort((dist, ray))
    ray, dist, owner, cos_inc = ray[order], dist[order], owner[order], cos_inc[order]
    first = np.ones(len(ray), dtype=bool)
    first[1:] = ray[1:] != ray[:-1]
    ray, dist, owner, cos_inc = ray[first], dist[first], owner[first], cos_inc[first]
    points = origin[None] + dist[:, None] * grid.directions(ray)
    return RayHits(ray, dist, owner, cos_inc, points)


def angular_extent(origin: np.ndarray, boxes: np.ndarray) -> AngularExtent:
    """Azimuth and elevation window of each box [B, >=7] seen from `origin` [3]."""
    d_min = bev_distance_to_box(origin[:2], boxes)
    corners = bev_corners(boxes) - origin[None, None, :2]
    corner_d = np.hypot(corners[..., 0], corners[..., 1])
    d_max = corner_d.max(axis=1)
    az_c = np.arctan2(boxes[:, 1] - origin[1], boxes[:, 0] - origin[0])
    rel = np.arctan2(corners[..., 1], corners[..., 0]) - az_c[:, None]
    rel = wrap_angle(rel)
    zb = boxes[:, 2] - boxes[:, 5] / 2 - origin[2]
    zt = boxes[:, 2] + boxes[:, 5] / 2 - origin[2]
    # The top and bottom edges are highest / lowest at the nearest or the farthest point.
    safe_min = np.maximum(d_min, 1e-3)
    el_lo = np.minimum(np.arctan2(zb, safe_min), np.arctan2(zb, d_max))
    el_hi = np.maximum(np.arctan2(zt, safe_min), np.arctan2(zt, d_max))
    return AngularExtent(az_c, rel.min(axis=1), rel.max(axis=1), el_lo, el_hi, d_min, d_max)


def _ground_hits(
    grid: RayGrid, origin: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray]:
    """Rays pointing down hit z = 0 at ``h / sin(-el)``. -> (ray [H], dist [H])."""
    down = np.flatnonzero(grid.elevation < 0)
    dist_e = origin[2] / -np.sin(grid.elevation[down])
    keep = dist_e <= max_range
    down, dist_e = down[keep], dist_e[keep]
    a = np.arange(grid.n_azimuth)
    ray = (down[:, None] * grid.n_azimuth + a[None, :]).ravel()
    return ray, np.repeat(dist_e, grid.n_azimuth)


def _box_hits(
    grid: RayGrid, boxes: np.ndarray, origin: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Slab test of each box against the rays of its window. -> (ray, dist, owner, cos)."""
    n_az, res = grid.n_azimuth, 2 * np.pi / grid.n_azimuth
    empty = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros(0))
    if len(boxes) == 0:
        return empty
    ext = angular_extent(origin, boxes)
    d_min = ext.d_min
    i0 = np.ceil((ext.azimuth + ext.az_lo) / res).astype(np.int64)
    i1 = np.floor((ext.azimuth + ext.az_hi) / res).astype(np.int64)
    el_lo, el_hi = ext.el_lo, ext.el_hi
    j0 = np.searchsorted(grid.elevation, el_lo, side="left")
    j1 = np.searchsorted(grid.elevation, el_hi, side="right")
    n_a = np.maximum(i1 - i0 + 1, 0)
    n_e = np.maximum(j1 - j0, 0)
    valid = (d_min > 1e-3) & (d_min < max_range)
    n = np.where(valid, n_a * n_e, 0)
    total = int(n.sum())
    if total == 0:
        return empty
    box = np.repeat(np.arange(len(boxes)), n)
    k = np.arange(total) - np.repeat(np.cumsum(n) - n, n)
    ne = n_e[box]
    ia = (i0[box] + k // ne) % n_az
    ie = j0[box] + k % ne
    ray = ie * n_az + ia
    d = grid.directions(ray)
    b = boxes[box]
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    px, py, pz = origin[0] - b[:, 0], origin[1] - b[:, 1], origin[2] - b[:, 2]
    o_loc = np.stack([c * px + s * py, -s * px + c * py, pz], axis=1)
    d_loc = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)
    half = np.stack([b[:, 4], b[:, 3], b[:, 5]], axis=1) / 2
    d_safe = np.where(np.abs(d_loc) < 1e-12, 1e-12, d_loc)
    t1 = (-half - o_loc) / d_safe
    t2 = (half - o_loc) / d_safe
    t_lo = np.minimum(t1, t2)
    t_near = t_lo.max(axis=1)
    t_far = np.maximum(t1, t2).min(axis=1)
    hit = (t_near <= t_far) & (t_near > 0.0) & (t_near <= max_range)
    axis = t_lo.argmax(axis=1)
    cos_inc = np.abs(d_loc[np.arange(total), axis])
    return ray[hit], t_near[hit], box[hit], cos_inc[hit]
