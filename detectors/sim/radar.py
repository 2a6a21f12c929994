"""Automotive radar (five corner/front radars merged at the ego origin, 0.5 m high).

Each object is a handful of scattering centres on its faces towards the sensor (vehicles
6-12, pedestrians 2, cones 1; walls one per 4 m). A centre is detected when its echo beats
the noise floor: ``SNR = rcs_centre + 66 - 40 log10(r) + 10 log10(Exp(1))`` dB (radar
equation with Swerling-1 fluctuation) must exceed 0 dB, so far, small objects often have
no return at all. A centre hidden behind another box (in bird's-eye view) still gets through
by multipath with probability 0.15. Measurements: range sigma 0.1 m + 0.3 % of range,
azimuth sigma 1 degree, elevation sigma 3 degrees (so z is nearly useless far away), RCS
with 2 dB noise, and raw Doppler radial velocity ``vr = (v_object - v_ego) . u`` (NOT ego
motion compensated; add ``v_ego . u`` to compensate) with 0.1 m/s noise, more for
pedestrians and cyclists (limbs, wheels). Clutter: random ground returns (about 25 per scan)
and ghosts of strong reflectors (a double bounce at twice the range and a mirror image across
the nearest wall).
"""

from __future__ import annotations

import numpy as np

from detectors.sim.classes import CLASSES
from detectors.sim.geometry import sample_visible_sides, segment_blocked
from detectors.sim.scene import Scene

HEIGHT = 0.5
MAX_RANGE = 80.0
SNR_OFFSET = 66.0
MULTIPATH = 0.15
SCAN_DT = 0.05
N_SCANS = 5
FEATURES1 = ("x", "y", "z", "rcs", "vr")
FEATURES5 = ("x", "y", "z", "rcs", "vr", "t")
_VR_SIGMA = np.full(len(CLASSES), 0.1)
_VR_SIGMA[[CLASSES.index("pedestrian"), CLASSES.index("bicycle")]] = 0.4


def render_radar(
    scene: Scene, rng: np.random.Generator, n_scans: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Accumulate `n_scans` scans at ``t = 0, -0.05, ...`` s in the current ego frame.

    Past scans see moving objects where they were (``centre + v t``) from where the ego was
    (``v_ego t``); points are ego-motion compensated into the current frame, so static things
    line up and moving things smear. -> (points [P, 5 or 6] float32 x y z rcs vr [t],
    owner [P] int64 ground-truth box index or -1).
    """
    parts, owners = [], []
    for k in range(n_scans):
        t = -SCAN_DT * k if k else 0.0
        pts, own = _scan(scene, rng, t)
        if n_scans > 1:
            pts = np.column_stack([pts, np.full(len(pts), t)])
        parts.append(pts)
        owners.append(own)
    return np.concatenate(parts).astype(np.float32), np.concatenate(owners)


def _scan(scene: Scene, rng: np.random.Generator, t: float) -> tuple[np.ndarray, np.ndarray]:
    """One scan at time `t` (<= 0). -> (points [P, 5], owner [P])."""
    boxes = scene.solid_boxes()
    boxes[:, :2] += boxes[:, 7:9] * t
    ego_v = np.array([scene.ego_velocity[0], scene.ego_velocity[1], 0.0], dtype=np.float64)
    origin = np.array([ego_v[0] * t, ego_v[1] * t, HEIGHT])
    counts = np.maximum(scene.n_scatter, 0)
    centres, owner = sample_visible_sides(rng, origin, boxes, counts)
    rel = centres - origin
    r = np.linalg.norm(rel, axis=1)
    per_centre_rcs = scene.rcs[owner] - 10 * np.log10(np.maximum(counts[owner], 1))
    fluct = 10 * np.log10(rng.exponential(1.0, len(r)) + 1e-12)
    snr = per_centre_rcs + SNR_OFFSET - 40 * np.log10(np.maximum(r, 1.0)) + fluct
    blocked = segment_blocked(origin[:2], centres[:, :2], owner, _blockers(boxes))
    detected = (snr > 0.0) & (r < MAX_RANGE) & (~blocked | (rng.random(len(r)) < MULTIPATH))
    centres, owner, rel, rcs = centres[detected], owner[detected], rel[detected], (
        per_centre_rcs + fluct)[detected]
    u = rel / np.maximum(np.linalg.norm(rel, axis=1, keepdims=True), 1e-6)
    vr = np.sum((boxes[owner, 7:9] - ego_v[None, :2]) * u[:, :2], axis=1)
    is_gt = owner < scene.num_objects
    vr_sigma = np.full(len(vr), 0.1)
    vr_sigma[is_gt] = _VR_SIGMA[scene.labels[owner[is_gt]]]
    vr = vr + rng.normal(0.0, 1.0, len(vr)) * vr_sigma
    ghosts = _ghosts(scene, rng, centres, rcs, vr, origin)
    clutter = _clutter(rng, ego_v, origin)
    true = np.column_stack([centres, rcs, vr])
    measured = _measure(np.concatenate([true, ghosts, clutter]), origin, rng)
    own = np.concatenate([np.where(is_gt, owner, -1), np.full(len(ghosts) + len(clutter), -1)])
    return measured, own.astype(np.int64)


def _blockers(boxes: np.ndarray) -> np.ndarray:
    """Boxes that block a radar ray near the ground (elevated tree crowns do not)."""
    low = boxes[:, 2] - boxes[:, 5] / 2 < 1.0
    out = boxes.copy()
    out[~low, 3:5] = 0.0  # zero size -> never blocks
    return out


def _measure(true: np.ndarray, origin: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Add range/azimuth/elevation/RCS noise to returns [N, 5] (x y z rcs vr). -> [N, 5]."""
    rel = true[:, :3] - origin
    r = np.linalg.norm(rel, axis=1)
    az = np.arctan2(rel[:, 1], rel[:, 0])
    el = np.arcsin(np.clip(rel[:, 2] / np.maximum(r, 1e-6), -1.0, 1.0))
    n = len(r)
    r = r + rng.normal(0.0, 1.0, n) * (0.1 + 0.003 * r)
    az = az + rng.normal(0.0, np.deg2rad(1.0), n)
    el = el + rng.normal(0.0, np.deg2rad(3.0), n)
    xyz = origin + np.column_stack(
        [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)]
    )
    rcs = true[:, 3] + rng.normal(0.0, 2.0, n)
    return np.column_stack([xyz, rcs, true[:, 4]])


def _ghosts(
    scene: Scene,
    rng: np.random.Generator,
    centres: np.ndarray,
    rcs: np.ndarray,
    vr: np.ndarray,
    origin: np.ndarray,
) -> np.ndarray:
    """Multipath ghosts of strong returns: double bounce and wall mirror. -> [N, 5]."""
    strong = rcs > 0.0
    rel = centres - origin
    double = strong & (rng.random(len(rcs)) < 0.08)
    g1 = np.column_stack([origin + 2 * rel[double], rcs[double] - 8.0, 2 * vr[double]])
    # Mirror across the wall line on the same side of the road as the return.
    s, t = scene.road.to_road(centres[:, :2])
    kerb_r, kerb_l = scene.road.right_edge, scene.road.left_edge
    wall_t = np.where(t < 0, kerb_r - scene.road.sidewalk - scene.road.setback,
                      kerb_l + scene.road.sidewalk + scene.road.setback)
    mirror = strong & (rng.random(len(rcs)) < 0.12)
    mt = 2 * wall_t[mirror] - t[mirror]
    mxy, _ = scene.road.to_ego(s[mirror], mt)
    g2 = np.column_stack([mxy, centres[mirror, 2], rcs[mirror] - 6.0, vr[mirror]])
    ghosts = np.concatenate([g1, g2])
    return ghosts[np.linalg.norm(ghosts[:, :2] - origin[:2], axis=1) < MAX_RANGE]


def _clutter(rng: np.random.Generator, ego_v: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Random ground clutter, uniform in range (denser near the sensor). -> [N, 5]."""
    n = rng.poisson(25)
    r = rng.uniform(2.0, MAX_RANGE, n)
    az = rng.uniform(-np.pi, np.pi, n)
    u = np.column_stack([np.cos(az), np.sin(az)])
    vr = -u @ ego_v[:2] + rng.normal(0.0, 0.3, n)
    moving = rng.random(n) < 0.2
    vr[moving] += rng.normal(0.0, 3.0, moving.sum())
    xy = origin[:2] + r[:, None] * u
    return np.column_stack([xy, np.full(n, 0.2), rng.normal(-12.0, 4.0, n), vr])
