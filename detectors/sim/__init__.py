"""Simulated driving world and its four sensors (lidar, radar1, radar5, camera).

``make_scene(seed)`` builds a deterministic scene (road, ground-truth boxes, static clutter),
``render(scene, sensor)`` what one sensor sees of it, ``make_frame(seed, sensor)`` both.
``render_images(scene)`` / ``make_image_frame(seed)`` give the camera rig's six RGB + depth
images with 2-D ground-truth boxes, ``coco_instances`` / ``write_coco`` export those as COCO.
See docs/sim.md for the physics and per-sensor statistics, docs/detectors.md for the images.
"""

from detectors.sim.classes import CLASSES, STATIC_KINDS
from detectors.sim.coco import coco_categories, coco_instances, write_coco
from detectors.sim.frame import (
    FEATURES,
    SENSORS,
    Frame,
    SensorFrame,
    compensate_radial_velocity,
    make_frame,
    render,
)
from detectors.sim.image_truth import MIN_VISIBLE_PIXELS, ImageTruth
from detectors.sim.images import CameraImages, ImageFrame, make_image_frame, render_images
from detectors.sim.rig import CAMERA_NAMES, CameraRig
from detectors.sim.scene import Scene, make_scene
from detectors.sim.splits import SPLITS, split_seeds

__all__ = [
    "CAMERA_NAMES",
    "CLASSES",
    "FEATURES",
    "MIN_VISIBLE_PIXELS",
    "SENSORS",
    "SPLITS",
    "STATIC_KINDS",
    "CameraImages",
    "CameraRig",
    "Frame",
    "ImageFrame",
    "ImageTruth",
    "Scene",
    "SensorFrame",
    "coco_categories",
    "coco_instances",
    "compensate_radial_velocity",
    "make_frame",
    "make_image_frame",
    "make_scene",
    "render",
    "render_images",
    "split_seeds",
    "write_coco",
]
