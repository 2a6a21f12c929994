"""KITTI calibration files and the map from KITTI camera boxes to detcal's box layout.

A calib file (object devkit `calib/000123.txt`, tracking devkit `calib/0004.txt`) has one
matrix per line, `NAME: v1 v2 ...` (the tracking devkit writes `NAME v1 v2 ...`):

    P0 .. P3        [3, 4]  projection of rectified camera i (not needed for boxes)
    R0_rect         [3, 3]  rectifying rotation of camera 0 (tracking: `R_rect`)
    Tr_velo_to_cam  [3, 4]  velodyne -> camera 0 (tracking: `Tr_velo_cam`)
    Tr_imu_to_velo  [3, 4]  IMU -> velodyne (tracking: `Tr_imu_velo`; not needed)

Label locations are in rectified camera-0 coordinates (x right, y down, z forward), so a
point maps to the velodyne (lidar) frame (x forward, y left, z up) as
`inv(Tr_velo_to_cam) · inv(R0_rect) · p` (4 x 4 homogeneous forms).
"""

from __future__ import annotations

import math

import numpy as np

from calibrators.core.errors import FieldError

#: Matrix names of a calib file and their sizes; aliases of the tracking devkit.
CALIB_SIZES = {"P0": 12, "P1": 12, "P2": 12, "P3": 12, "R0_rect": 9, "Tr_velo_to_cam": 12,
               "Tr_imu_to_velo": 12}
CALIB_ALIASES = {"R_rect": "R0_rect", "Tr_velo_cam": "Tr_velo_to_cam",
                 "Tr_imu_velo": "Tr_imu_to_velo"}
#: Without a calib file: the camera frame with its axes renamed (x = z_cam forward,
#: y = -x_cam left, z = -y_cam up); the origin stays at camera 0.
CAMERA_AXES = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0],
                        [0.0, 0.0, 0.0, 1.0]])


def parse_calib(text: str, name: str) -> np.ndarray:
    """`[4, 4]` map from rectified camera-0 coordinates to the velodyne frame, from the text of
    a calib file called `name` (FieldError naming the file, line and matrix otherwise)."""
    found: dict[str, np.ndarray] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        key, _, rest = line.replace(":", " ", 1).partition(" ")
        key = CALIB_ALIASES.get(key, key)
        if key not in CALIB_SIZES:
            continue  # other matrices (e.g. a second camera's) are not needed
        values = rest.split()
        try:
            arr = np.array([float(v) for v in values])
        except ValueError:
            raise FieldError(key, f"{name} line {number}: {key} must be numbers, got "
                                  f"{rest.strip()[:60]!r}", row=number) from None
        if len(arr) != CALIB_SIZES[key] or not np.all(np.isfinite(arr)):
            raise FieldError(key, f"{name} line {number}: {key} must be {CALIB_SIZES[key]} "
                                  f"finite numbers, got {len(arr)}", row=number)
        found[key] = arr
    for key in ("R0_rect", "Tr_velo_to_cam"):
        if key not in found:
            raise FieldError(key, f"{name}: missing {key} (needed to map camera boxes to the "
                                  "lidar frame)")
    rect = np.eye(4)
    rect[:3, :3] = found["R0_rect"].reshape(3, 3)
    velo_to_cam = np.eye(4)
    velo_to_cam[:3] = found["Tr_velo_to_cam"].reshape(3, 4)
    try:
        to_lidar = np.linalg.inv(velo_to_cam) @ np.linalg.inv(rect)
    except np.linalg.LinAlgError:
        raise FieldError("Tr_velo_to_cam", f"{name}: R0_rect or Tr_velo_to_cam is singular; "
                                           "it cannot be inverted") from None
    return to_lidar


def camera_boxes(fields: np.ndarray, to_frame: np.ndarray) -> np.ndarray:
    """`[N, 9]` detcal boxes of KITTI label fields `[N, 7]` = h w l x y z rotation_y.

    KITTI (devkit readme): `dimensions` are height, width, length (m); `location` is the
    **bottom** centre of the box in rectified camera-0 coordinates; `rotation_y` turns the
    box about the camera's y axis, 0 = heading along camera +x, so the heading is
    `(cos ry, 0, -sin ry)` (the devkit's computeBox3D). The centre `location - (0, h/2, 0)`
    and the heading are mapped by `to_frame` `[4, 4]`; yaw is the mapped heading's angle about
    +z. Velocities are 0 (KITTI has none).
    """
    h, w, length, x, y, z, ry = (fields[:, k] for k in range(7))
    centre = np.stack([x, y - h / 2.0, z, np.ones_like(x)], axis=1) @ to_frame.T
    heading = np.stack([np.cos(ry), np.zeros_like(ry), -np.sin(ry)], axis=1) @ to_frame[:3, :3].T
    yaw = np.arctan2(heading[:, 1], heading[:, 0])
    yaw = np.where(yaw <= -math.pi, yaw + 2 * math.pi, yaw)
    zeros = np.zeros_like(x)
    return np.stack([centre[:, 0], centre[:, 1], centre[:, 2], w, length, h, yaw, zeros, zeros],
                    axis=1)
