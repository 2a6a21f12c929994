"""Camera images of a scene: six RGB + depth images and their 2-D ground truth.

Every pixel of the camera rig (`rig.CameraRig`) is one ray of the camera sensor's grid, cast
once (`raycast.box_hits` then `raycast.nearest_hits`, the camera's own cast). A pixel that
sees a surface within 70 m gets the camera's colour model (instance colour x incidence
shading x scene lighting + pixel noise, ground grey levels from the road materials:
`camera.surface_colours`) and the camera's depth model (the monocular depth of the camera
pseudo-points, `camera.monocular_depth`: range along the pixel's ray times ``exp(e)``, a
per-object scale error plus per-pixel noise, so not the true depth). A pixel that sees
nothing within range is sky above the horizon and distant asphalt below it, with depth 0.

Determinism: ``render_images(scene)`` draws from ``default_rng([scene.seed, IMAGE_STREAM])``,
a stream of its own, so the images do not change the camera point clouds of the same seed
(and their noise and lighting are drawn independently of them).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from detectors.sim.camera import MAX_RANGE, monocular_depth, surface_colours
from detectors.sim.classes import GROUND_MATERIAL
from detectors.sim.image_truth import ImageTruth, truth_from_cast
from detectors.sim.raycast import box_hits, nearest_hits
from detectors.sim.rig import RIG, CameraRig
from detectors.sim.scene import Scene, make_scene

IMAGE_STREAM = 16  # beyond the sensors' streams, [seed, 1..4]
SKY = (0.70, 0.78, 0.88)
PIXEL_NOISE = 0.04  # colour noise of a background pixel, as on surfaces


@dataclass(frozen=True, eq=False)
class CameraImages:
    """The six images of one frame (C = 6 cameras of H x W pixels, `CAMERA_NAMES` order).

    rgb: [C, H, W, 3] float32 colour in [0, 1]; depth: [C, H, W] float32 estimated range
    along the pixel's ray in metres, 0 where nothing is within range; owner: [C, H, W] int64
    ground-truth box seen at each pixel, -1 for ground, static clutter and sky (ground truth,
    for tests and analysis, never a model input).
    """

    rig: CameraRig
    rgb: np.ndarray
    depth: np.ndarray
    owner: np.ndarray


@dataclass(frozen=True, eq=False)
class ImageFrame:
    """A scene, its six camera images and their 2-D ground truth."""

    scene: Scene
    images: CameraImages
    truth: ImageTruth


def render_images(
    scene: Scene, rng: np.random.Generator | None = None, rig: CameraRig = RIG
) -> tuple[CameraImages, ImageTruth]:
    """The camera images of `scene` and their 2-D boxes; deterministic per (seed, rig).

    rng: the noise and lighting stream; None = the scene's own image stream (module doc).
    """
    if rng is None:
        rng = np.random.default_rng([scene.seed, IMAGE_STREAM])
    grid = rig.grid
    boxes = scene.solid_boxes()
    candidates = box_hits(grid, boxes, MAX_RANGE)
    hits = nearest_hits(grid, candidates, MAX_RANGE)
    depth = monocular_depth(hits.dist, hits.owner, len(boxes), rng)
    colour = surface_colours(scene, hits.owner, hits.cos_incidence, hits.points, rng)

    ray_rgb = np.empty((grid.n_rays, 3))
    ray_depth = np.zeros(grid.n_rays)
    ray_owner = np.full(grid.n_rays, -1, dtype=np.int64)
    ray_rgb[hits.ray] = colour
    ray_depth[hits.ray] = depth
    gt = (hits.owner >= 0) & (hits.owner < scene.num_objects)
    ray_owner[hits.ray[gt]] = hits.owner[gt]
    missed = np.ones(grid.n_rays, dtype=bool)
    missed[hits.ray] = False
    miss = np.flatnonzero(missed)
    up = grid.elevation[miss // grid.n_azimuth] >= 0.0
    far_ground = GROUND_MATERIAL.palette[0][1]
    background = np.where(up[:, None], np.asarray(SKY), np.asarray(far_ground))
    ray_rgb[miss] = np.clip(background + rng.normal(0.0, PIXEL_NOISE, background.shape), 0, 1)

    index = rig.ray_index
    images = CameraImages(rig, ray_rgb[index].astype(np.float32),
                          ray_depth[index].astype(np.float32), ray_owner[index])
    truth = truth_from_cast(scene, rig, hits, candidates)
    for arr in (images.rgb, images.depth, images.owner, *vars(truth).values()):
        arr.flags.writeable = False
    return images, truth


def make_image_frame(seed: int, extra_objects: Mapping[str, float] | None = None,
                     rig: CameraRig = RIG) -> ImageFrame:
    """``ImageFrame(make_scene(seed, extra_objects), *render_images(scene, rig=rig))``."""
    scene = make_scene(seed, extra_objects)
    return ImageFrame(scene, *render_images(scene, rig=rig))
