"""2-D ground truth of the camera images: one box per (object, camera) where it is visible.

A ground-truth object's box in one image is the pixel-edge extent of the pixels it owns
there (the pixels whose ray hits it first): min / max column and row, the max extended by
one pixel. Boxes are COCO ``x y w h`` in that image's pixels. Objects with fewer than
``MIN_VISIBLE_PIXELS`` visible pixels in an image get no box there; an object that two
images see gets a box in each.

- truncated: the object's full projected extent (`CameraRig.box_extent`, exact in azimuth)
  crosses the image border, a camera seam included.
- occlusion: ``1 - visible / alone``, where ``alone`` counts the pixels of that image the
  object would own if it were alone in the scene (every ray that hits it, from the same ray
  cast, `raycast.box_hits`): 0 for an unoccluded object, near 1 for a hidden one. Pixels
  beyond the camera's 70 m range are neither visible nor alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from detectors.sim.raycast import BoxHits, RayHits
from detectors.sim.rig import CameraRig
from detectors.sim.scene import Scene

MIN_VISIBLE_PIXELS = 4  # a pedestrian at 40 m shows about 10 pixels, a cone at 30 m about 6


@dataclass(frozen=True, eq=False)
class ImageTruth:
    """Ground-truth 2-D boxes of one frame's images, sorted by (object, camera).

    camera: [N] int64 image index (`CAMERA_NAMES`); bbox: [N, 4] float32 ``x y w h`` in
    pixels of that image; label: [N] int64 index into CLASSES; box3d_index: [N] int64 row of
    ``scene.boxes``; truncated: [N] bool; occlusion: [N] float32 in [0, 1]; visible_pixels:
    [N] int64 pixels the object owns in that image.
    """

    camera: np.ndarray
    bbox: np.ndarray
    label: np.ndarray
    box3d_index: np.ndarray
    truncated: np.ndarray
    occlusion: np.ndarray
    visible_pixels: np.ndarray

    def __len__(self) -> int:
        return len(self.camera)


def truth_from_cast(
    scene: Scene, rig: CameraRig, hits: RayHits, candidates: BoxHits
) -> ImageTruth:
    """2-D boxes of `scene`'s ground truth from one ray cast on ``rig.grid``.

    hits: the nearest hit per ray; candidates: every box hit, each box alone (the hits'
    source, owners indexing ``scene.solid_boxes()``, ground truth first).
    """
    g, n_cam = scene.num_objects, rig.n_cameras
    n_keys = g * n_cam
    seen = (hits.owner >= 0) & (hits.owner < g)
    camera, row, column = rig.pixels(hits.ray[seen])
    key = hits.owner[seen] * n_cam + camera
    visible = np.bincount(key, minlength=n_keys)
    x0, x1 = _extremes(key, column, n_keys)
    y0, y1 = _extremes(key, row, n_keys)
    mine = candidates.owner < g
    alone_camera = rig.pixels(candidates.ray[mine])[0]
    alone = np.bincount(candidates.owner[mine] * n_cam + alone_camera, minlength=n_keys)

    keep = np.flatnonzero(visible >= MIN_VISIBLE_PIXELS)
    obj, cam = np.divmod(keep, n_cam)
    # Pixel-edge extent: the last column / row owned ends one pixel further.
    bbox = np.stack([x0[keep], y0[keep], x1[keep] + 1 - x0[keep], y1[keep] + 1 - y0[keep]], 1)
    full = rig.box_extent(scene.boxes[obj].astype(np.float64), cam)
    truncated = ((full[:, 0] < 0.0) | (full[:, 1] < 0.0) | (full[:, 2] > rig.width)
                 | (full[:, 3] > rig.height))
    occlusion = 1.0 - visible[keep] / alone[keep]
    return ImageTruth(
        camera=cam.astype(np.int64),
        bbox=bbox.astype(np.float32),
        label=scene.labels[obj].astype(np.int64),
        box3d_index=obj.astype(np.int64),
        truncated=truncated,
        occlusion=occlusion.astype(np.float32),
        visible_pixels=visible[keep].astype(np.int64),
    )


def _extremes(key: np.ndarray, value: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest `value` [N] per `key` [N] in ``[0, n_keys)``. -> ([K], [K])."""
    lo = np.full(n_keys, np.iinfo(np.int64).max)
    hi = np.full(n_keys, -1, dtype=np.int64)
    np.minimum.at(lo, key, value)
    np.maximum.at(hi, key, value)
    return lo, hi
