"""Spinning 32-beam lidar (HDL-32E-like, as on the nuScenes car).

32 beams from -30.67 to +10.67 degrees elevation, 1024 azimuth steps (0.35 degrees), mounted
1.84 m above the ground, 70 m maximum range. Each ray returns its nearest surface, so point
density on an object falls with 1 / range^2 and occluded or self-occluded surfaces get no
points. Degradations: range noise (2 cm + 0.2 mm per metre), a small beam-angle jitter,
dropouts that grow with range and with dark or grazing surfaces, intensity from the
surface's reflectivity and incidence angle with multiplicative noise, and a few spurious
returns (dust, spray).
"""

from __future__ import annotations

import numpy as np

from detectors.sim.classes import GROUND_MATERIAL, MARKING_MATERIAL, SIDEWALK_MATERIAL
from detectors.sim.layout import Road
from detectors.sim.raycast import RayGrid, cast
from detectors.sim.scene import Scene

ORIGIN = np.array([0.0, 0.0, 1.84])
GRID = RayGrid(ORIGIN, 1024, np.deg2rad(np.linspace(-30.67, 10.67, 32)))
MAX_RANGE = 70.0
FEATURES = ("x", "y", "z", "intensity")


def render_lidar(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One lidar sweep. -> (points [P, 4] float32 x y z intensity, owner [P] int64).

    owner is the index of the ground-truth box a point came from, -1 for anything else.
    """
    boxes = scene.solid_boxes()
    hits = cast(GRID, boxes, MAX_RANGE)
    refl = np.where(hits.owner >= 0, scene.reflectivity[np.maximum(hits.owner, 0)], 0.0)
    ground = hits.owner < 0
    refl[ground] = ground_reflectivity(scene.road, hits.points[ground, :2], rng)
    # Dropouts: weak echoes (far, dark, grazing) are lost more often.
    r_rel = hits.dist / MAX_RANGE
    p_drop = 0.02 + 0.3 * r_rel**2 * (1.0 - refl) * (1.6 - hits.cos_incidence)
    keep = rng.random(len(hits.dist)) >= p_drop
    dist = hits.dist[keep] + rng.normal(0.0, 1.0, keep.sum()) * (0.02 + 2e-4 * hits.dist[keep])
    dirs = GRID.directions(hits.ray[keep])
    dirs = dirs + rng.normal(0.0, np.deg2rad(0.03), dirs.shape)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    xyz = ORIGIN[None] + dist[:, None] * dirs
    intensity = refl[keep] * (0.35 + 0.65 * hits.cos_incidence[keep])
    intensity = np.clip(intensity * np.exp(rng.normal(0.0, 0.15, len(intensity))), 0.0, 1.0)
    owner = hits.owner[keep]
    owner = np.where(owner < scene.num_objects, owner, -1)
    spurious = _spurious(rng)
    points = np.concatenate([np.column_stack([xyz, intensity]), spurious], axis=0)
    owner = np.concatenate([owner, np.full(len(spurious), -1, dtype=np.int64)])
    return points.astype(np.float32), owner


def ground_reflectivity(road: Road, xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Reflectivity of ground points [N, 2]: asphalt, lane markings or sidewalk. -> [N]."""
    s, t = road.to_road(xy)
    refl = np.full(len(xy), GROUND_MATERIAL.reflectivity[0])
    lines = np.arange(-road.n_forward, road.n_oncoming + 1) * road.lane_width
    near_line = np.abs(t[:, None] - lines[None]).min(axis=1) < 0.08
    dashed = (np.abs(t) > 0.1) & (np.mod(s, 9.0) > 3.0)
    refl[near_line & ~dashed] = MARKING_MATERIAL.reflectivity[0]
    if road.crossing_s is not None:
        zebra = (np.abs(s - road.crossing_s) < 2.0) & (np.mod(t, 1.0) < 0.5)
        on_road = (t > road.right_edge) & (t < road.left_edge)
        refl[zebra & on_road] = MARKING_MATERIAL.reflectivity[0]
    refl[(t < road.right_edge) | (t > road.left_edge)] = SIDEWALK_MATERIAL.reflectivity[0]
    return refl * np.exp(rng.normal(0.0, 0.2, len(xy)))


def _spurious(rng: np.random.Generator) -> np.ndarray:
    """A few returns from dust and spray near the sensor. -> [N, 4]."""
    n = rng.poisson(25)
    r = rng.uniform(2.0, 30.0, n)
    az = rng.uniform(-np.pi, np.pi, n)
    z = rng.uniform(0.1, 2.5, n)
    return np.column_stack([r * np.cos(az), r * np.sin(az), z, rng.uniform(0.0, 0.1, n)])
