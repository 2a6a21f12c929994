"""Surround camera rig turned into pseudo-points (what a monocular depth network gives).

Six cameras cover 360 degrees; their pixels are modelled as a ray grid of 0.5 degrees
(720 azimuths x 71 rows from -20 to +15 degrees elevation) from 1.6 m above the ground.
Every ray that sees a surface within 70 m becomes a point with an accurate bearing (0.05
degree jitter) but a depth error that grows with the square of the range, as monocular depth
does: the depth is multiplied by ``exp(e)`` with ``e ~ N(0, (0.001 r)^2)``, where 80 % of the
variance is shared by all pixels of one object (a per-object scale error) and 20 % is per
pixel. At 5 m the depth error is about 2.5 cm, at 50 m about 2.5 m. A point carries the
surface's colour (instance colour x incidence shading x scene lighting + pixel noise).
Only 45 % of the pixels are kept (a fixed random subsample, as pseudo-lidar pipelines do)
to stay within the point budget. `images.py` renders every pixel of the same grid as six
RGB + depth images with the same colour and depth models.
"""

from __future__ import annotations

import numpy as np

from detectors.sim.classes import GROUND_MATERIAL, MARKING_MATERIAL, SIDEWALK_MATERIAL
from detectors.sim.lidar import ground_reflectivity
from detectors.sim.raycast import RayGrid, cast
from detectors.sim.scene import Scene

ORIGIN = np.array([0.0, 0.0, 1.6])
ELEVATION = (-20.0, 15.0)  # degrees, lowest and highest pixel row
PIXEL = 0.5  # degrees between neighbouring pixels, in azimuth and in elevation
MAX_RANGE = 70.0
KEEP = 0.45
DEPTH_REL_SIGMA = 1e-3  # relative depth sigma per metre of range
SHARED = 0.8  # share of the depth variance common to one object
FEATURES = ("x", "y", "z", "r", "g", "b")


def camera_grid(scale: int = 1) -> RayGrid:
    """The pixels' rays, `scale` times finer than the sensor's 0.5 degrees (1: 720 x 71)."""
    n_rows = round((ELEVATION[1] - ELEVATION[0]) / PIXEL) * scale + 1
    elevation = np.deg2rad(np.linspace(ELEVATION[0], ELEVATION[1], n_rows))
    return RayGrid(ORIGIN, round(360.0 / PIXEL) * scale, elevation)


GRID = camera_grid()


def render_camera(scene: Scene, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """One set of camera pseudo-points. -> (points [P, 6] float32 x y z r g b, owner [P])."""
    boxes = scene.solid_boxes()
    hits = cast(GRID, boxes, MAX_RANGE)
    keep = rng.random(len(hits.ray)) < KEEP
    ray, dist, owner = hits.ray[keep], hits.dist[keep], hits.owner[keep]
    cos_inc, true_xyz = hits.cos_incidence[keep], hits.points[keep]
    depth = monocular_depth(dist, owner, len(boxes), rng)
    dirs = GRID.directions(ray) + rng.normal(0.0, np.deg2rad(0.05), (len(ray), 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    xyz = ORIGIN[None] + depth[:, None] * dirs
    in_range = depth <= MAX_RANGE
    rgb = surface_colours(scene, owner, cos_inc, true_xyz, rng)
    owner = np.where(owner < scene.num_objects, owner, -1)
    points = np.column_stack([xyz, rgb])[in_range]
    return points.astype(np.float32), owner[in_range]


def monocular_depth(
    dist: np.ndarray, owner: np.ndarray, n_boxes: int, rng: np.random.Generator
) -> np.ndarray:
    """Estimated depth of pixels at true range `dist` [N] whose surface is `owner` [N].

    owner: index into the scene's `n_boxes` solid boxes, -1 for the ground. -> [N] metres.
    """
    # Log-normal with sigma growing linearly in range (absolute error ~ r^2).
    sigma = DEPTH_REL_SIGMA * dist
    object_error = rng.standard_normal(n_boxes + 1)[owner]  # owner -1 -> last entry
    object_error[owner < 0] = 0.0
    shared = np.where(owner >= 0, np.sqrt(SHARED), 0.0)
    pixel = np.sqrt(1.0 - shared**2)
    return dist * np.exp(sigma * (shared * object_error + pixel * rng.standard_normal(len(dist))))


def surface_colours(
    scene: Scene,
    owner: np.ndarray,
    cos_inc: np.ndarray,
    xyz: np.ndarray,
    rng: np.random.Generator,
) -> np.ndarray:
    """Observed colour of pixels that see `owner` [N] (solid box index, -1 = ground).

    cos_inc: [N] incidence cosine; xyz: [N, 3] true surface points. -> [N, 3] in [0, 1].
    """
    base = np.empty((len(owner), 3))
    obj = owner >= 0
    base[obj] = scene.color[owner[obj]]
    ground = ~obj
    # Ground colour from the same material map the lidar uses (reflectivity -> grey level).
    refl = ground_reflectivity(scene.road, xyz[ground, :2], rng)
    grey = np.interp(
        refl,
        [GROUND_MATERIAL.reflectivity[0], SIDEWALK_MATERIAL.reflectivity[0],
         MARKING_MATERIAL.reflectivity[0]],
        [GROUND_MATERIAL.palette[0][1][0], SIDEWALK_MATERIAL.palette[0][1][0],
         MARKING_MATERIAL.palette[0][1][0]],
    )
    base[ground] = grey[:, None]
    light = rng.uniform(0.6, 1.15)  # scene lighting (overcast ... sunny)
    shade = 0.55 + 0.45 * cos_inc
    rgb = base * (shade * light)[:, None] + rng.normal(0.0, 0.04, base.shape)
    return np.clip(rgb, 0.0, 1.0)
