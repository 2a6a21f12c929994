"""The surround camera rig as six images: which pixel each camera ray is, where a point lands.

The camera sensor's ray grid (`camera.camera_grid`: 0.5 degrees between pixels in azimuth
and in elevation, rows from -20 to +15 degrees, 1.6 m above the ground) is cut into six
60 degree images in nuScenes order, ``CAMERA_NAMES``: camera ``c`` looks along azimuth
``-60 c`` degrees (front, then clockwise). The images are equirectangular (cylindrical):
the column is linear in azimuth, left = larger azimuth (what looking out shows), the row is
linear in elevation, row 0 at the top. Put side by side, cameras 0..5 form one 360 degree
panorama with camera 5's right edge meeting camera 0's left edge.

Pixel coordinates are pixel-edge ones: pixel (row i, column j) covers ``[j, j + 1] x [i, i +
1]`` and is the ray through its centre ``(j + 0.5, i + 0.5)``; an image spans ``[0, W] x [0,
H]``. ``W`` is even, so a camera's heading is the ray of column ``W / 2``, half a pixel
right of the image centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from calibrators.core.vocab import wrap_angle
from detectors.sim.camera import PIXEL, camera_grid
from detectors.sim.raycast import RayGrid, angular_extent

CAMERA_NAMES: tuple[str, ...] = (
    "CAM_FRONT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_FRONT_LEFT",
)


@dataclass(frozen=True)
class CameraRig:
    """Six images of ``H x W`` pixels from the camera ray grid `scale` times finer.

    scale 1 is the camera sensor's own grid: 6 images of 71 rows x 120 columns.
    """

    scale: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.scale, bool) or not isinstance(self.scale, int) or self.scale < 1:
            raise ValueError(f"scale must be a positive integer, got {self.scale!r}")

    @cached_property
    def grid(self) -> RayGrid:
        """The rays of all pixels (``6 W`` azimuths x ``H`` elevations)."""
        return camera_grid(self.scale)

    @property
    def n_cameras(self) -> int:
        """C = 6."""
        return len(CAMERA_NAMES)

    @property
    def width(self) -> int:
        """W, columns per image."""
        return self.grid.n_azimuth // self.n_cameras

    @property
    def height(self) -> int:
        """H, rows per image."""
        return len(self.grid.elevation)

    @property
    def pixel(self) -> float:
        """Angle between neighbouring pixels in radians (the same along rows and columns)."""
        return float(np.deg2rad(PIXEL)) / self.scale

    def heading(self, camera: np.ndarray) -> np.ndarray:
        """Azimuth of the camera's heading (radians) for camera indices [N]. -> [N]."""
        return -2 * np.pi / self.n_cameras * np.asarray(camera, dtype=np.float64)

    def pixels(self, ray: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(camera, row, column) of grid rays [N] (``e * 6W + a``), each [N] int64."""
        e, a = np.divmod(np.asarray(ray, dtype=np.int64), self.grid.n_azimuth)
        column = np.mod(self.width // 2 - a, self.grid.n_azimuth)
        camera, column = np.divmod(column, self.width)
        return camera, self.height - 1 - e, column

    @cached_property
    def ray_index(self) -> np.ndarray:
        """Grid ray of every pixel. -> [C, H, W] int64 (inverse of `pixels`)."""
        camera, row, column = np.meshgrid(np.arange(self.n_cameras), np.arange(self.height),
                                          np.arange(self.width), indexing="ij")
        a = np.mod(self.width // 2 - (camera * self.width + column), self.grid.n_azimuth)
        return (self.height - 1 - row) * self.grid.n_azimuth + a

    def project(
        self, xyz: np.ndarray, camera: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel-edge coordinates of ego-frame points [N, 3] in the image of `camera` [N].

        Without `camera`, each point goes to the image whose azimuth span holds it.
        -> (camera [N] int64, x [N], y [N]); x or y outside ``[0, W] x [0, H]`` is off the image.
        """
        rel = np.asarray(xyz, dtype=np.float64)[:, :3] - self.grid.origin[None]
        az = np.arctan2(rel[:, 1], rel[:, 0])
        el = np.arctan2(rel[:, 2], np.hypot(rel[:, 0], rel[:, 1]))
        if camera is None:
            u = np.mod(self.width / 2 + 0.5 - az / self.pixel, self.grid.n_azimuth)
            camera = np.minimum(u // self.width, self.n_cameras - 1).astype(np.int64)
        camera = np.asarray(camera, dtype=np.int64)
        return camera, self._column(az, camera), self._row(el)

    def box_extent(self, boxes: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """Full projected extent of boxes [N, >=7] in the image of `camera` [N], occlusion and
        image borders ignored. -> [N, 4] ``x0 y0 x1 y1`` pixel-edge coordinates.

        The azimuth span is exact (upright faces); the elevation span is that of the box's
        nearest point and farthest corner, as the ray cast's windows.
        """
        ext = angular_extent(self.grid.origin, np.asarray(boxes, dtype=np.float64))
        camera = np.asarray(camera, dtype=np.int64)
        x0 = self._column(ext.azimuth + ext.az_hi, camera)
        x1 = self._column(ext.azimuth + ext.az_lo, camera)
        return np.stack([x0, self._row(ext.el_hi), x1, self._row(ext.el_lo)], axis=1)

    def _column(self, az: np.ndarray, camera: np.ndarray) -> np.ndarray:
        """x of azimuths [N] in the images of `camera` [N] (offsets taken within +-180 deg)."""
        offset = wrap_angle(az - self.heading(camera))
        return self.width / 2 + 0.5 - offset / self.pixel

    def _row(self, el: np.ndarray) -> np.ndarray:
        """y of elevations [N] (the same in every image)."""
        return (self.grid.elevation[-1] - el) / self.pixel + 0.5


RIG = CameraRig()
