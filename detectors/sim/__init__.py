"""Simulated driving world and its four sensors (lidar, radar1, radar5, camera).

``make_scene(seed)`` builds a deterministic scene (road, ground-truth boxes, static clutter),
``render(scene, sensor)`` what one sensor sees of it, ``make_frame(seed, sensor)`` both.
See docs/sim.md for the physics and per-sensor statistics.
"""

from detectors.sim.classes import CLASSES, STATIC_KINDS
from detectors.sim.frame import (
    FEATURES,
    SENSORS,
    Frame,
    SensorFrame,
    compensate_radial_velocity,
    make_frame,
    render,
)
from detectors.sim.scene import Scene, make_scene
from detectors.sim.splits import SPLITS, split_seeds

__all__ = [
    "CLASSES",
    "FEATURES",
    "SENSORS",
    "SPLITS",
    "STATIC_KINDS",
    "Frame",
    "Scene",
    "SensorFrame",
    "compensate_radial_velocity",
    "make_frame",
    "make_scene",
    "render",
    "split_seeds",
]
