"""Sensor frames: render a scene with one of the four sensors."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from detectors.sim import camera, lidar, radar
from detectors.sim.scene import Scene, make_scene
from detectors.vocab import SENSORS

FEATURES: dict[str, tuple[str, ...]] = {
    "lidar": lidar.FEATURES,
    "radar1": radar.FEATURES1,
    "radar5": radar.FEATURES5,
    "camera": camera.FEATURES,
}


@dataclass(frozen=True, eq=False)
class SensorFrame:
    """What one sensor saw of a scene (ego frame).

    sensor: one of SENSORS.
    points: [P, F] float32 point features in FEATURES[sensor] order.
    gt_num_points: [G] int64 points that came from each ground-truth box.
    point_owner: [P] int64 ground-truth box each point came from, -1 for ground, clutter,
        ghosts and static objects. Ground truth: for tests and analysis, never a model input.
    """

    sensor: str
    points: np.ndarray
    gt_num_points: np.ndarray
    point_owner: np.ndarray


@dataclass(frozen=True, eq=False)
class Frame:
    """A scene and one sensor's view of it."""

    scene: Scene
    sensor_frame: SensorFrame

    @property
    def points(self) -> np.ndarray:
        """[P, F] float32 sensor points."""
        return self.sensor_frame.points

    @property
    def boxes(self) -> np.ndarray:
        """[G, 9] float32 ground-truth boxes."""
        return self.scene.boxes

    @property
    def labels(self) -> np.ndarray:
        """[G] int64 ground-truth labels."""
        return self.scene.labels


def check_sensor(sensor: str) -> int:
    """Index of `sensor` in SENSORS, or a ValueError naming the valid sensors."""
    if sensor not in SENSORS:
        raise ValueError(f"sensor must be one of {SENSORS}, got {sensor!r}")
    return SENSORS.index(sensor)


def render(scene: Scene, sensor: str) -> SensorFrame:
    """Render `scene` with `sensor`; deterministic per (scene.seed, sensor)."""
    index = check_sensor(sensor)
    rng = np.random.default_rng([scene.seed, index + 1])
    if sensor == "lidar":
        points, owner = lidar.render_lidar(scene, rng)
    elif sensor == "camera":
        points, owner = camera.render_camera(scene, rng)
    else:
        points, owner = radar.render_radar(scene, rng, 1 if sensor == "radar1" else radar.N_SCANS)
    counts = np.bincount(owner[owner >= 0], minlength=scene.num_objects).astype(np.int64)
    for arr in (points, counts, owner):
        arr.flags.writeable = False
    return SensorFrame(sensor, points, counts, owner.astype(np.int64))


def make_frame(seed: int, sensor: str,
               extra_objects: Mapping[str, float] | None = None) -> Frame:
    """``Frame(make_scene(seed, extra_objects), render(scene, sensor))``."""
    check_sensor(sensor)
    scene = make_scene(seed, extra_objects)
    return Frame(scene, render(scene, sensor))


def compensate_radial_velocity(points: np.ndarray, ego_velocity: np.ndarray) -> np.ndarray:
    """Ego-motion compensated radial velocity of radar points [P, >=5] (vr column 4). -> [P].

    ``vr + v_ego . u`` with ``u`` the unit bearing of the point in BEV: zero for static
    things, the object's own radial speed for moving ones.
    """
    xy = points[:, :2].astype(np.float64)
    u = xy / np.maximum(np.linalg.norm(xy, axis=1, keepdims=True), 1e-6)
    return (points[:, 4] + u @ np.asarray(ego_velocity, dtype=np.float64)).astype(np.float32)
