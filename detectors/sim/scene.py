"""Deterministic driving scenes: road layout, ground-truth objects and static clutter."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from detectors.sim.classes import CLASSES
from detectors.sim.layout import Road, sample_road
from detectors.sim.placement import Placer
from detectors.sim.street import place_street
from detectors.sim.traffic import place_crossing, place_extra, place_free, place_road_works


@dataclass(frozen=True, eq=False)
class Scene:
    """One simulated scene in the ego frame (ego at the origin, ground at z = 0, x forward).

    seed: the scene's seed (``make_scene(seed)`` rebuilds it exactly).
    boxes: [G, 9] float32 ground truth ``x y z w l h yaw vx vy`` (z = box centre, velocity
        absolute in m/s), all centres within |x|, |y| <= 60 m, no two overlapping.
    labels: [G] int64 indices into CLASSES.
    ego_velocity: [2] float32 ego velocity (vx, vy) in m/s (the ego drives along +x).
    road: the road layout.
    static_boxes: [S, 7] float32 clutter that is not ground truth (walls, poles, trees, ...).
    static_kinds: [S] int64 indices into STATIC_KINDS.
    reflectivity: [G + S] float32 lidar reflectivity in [0, 1] (ground truth first, then static).
    rcs: [G + S] float32 radar cross section in dBsm.
    color: [G + S, 3] float32 camera colour in [0, 1].
    n_scatter: [G + S] int64 radar scattering centres.
    """

    seed: int
    boxes: np.ndarray
    labels: np.ndarray
    ego_velocity: np.ndarray
    road: Road
    static_boxes: np.ndarray
    static_kinds: np.ndarray
    reflectivity: np.ndarray
    rcs: np.ndarray
    color: np.ndarray
    n_scatter: np.ndarray

    @property
    def num_objects(self) -> int:
        """G, the number of ground-truth boxes."""
        return len(self.boxes)

    def solid_boxes(self) -> np.ndarray:
        """Every box a sensor can hit, ground truth first. -> [G + S, 9] float64."""
        static = np.zeros((len(self.static_boxes), 9))
        static[:, :7] = self.static_boxes
        return np.concatenate([self.boxes.astype(np.float64), static], axis=0)


def make_scene(seed: int, extra_objects: Mapping[str, float] | None = None) -> Scene:
    """Build the scene of `seed` (``np.random.default_rng(seed)``); same seed, same scene.

    `extra_objects` (training only): mean number of additional objects per class, placed
    after the scene is complete from a separate stream (``default_rng([seed, 1])``), so the
    seed's own objects are exactly those of ``make_scene(seed)``.
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if extra_objects is not None:
        unknown = sorted(set(extra_objects) - set(CLASSES))
        if unknown:
            raise ValueError(f"extra_objects: unknown classes {unknown}")
        if any(not np.isfinite(v) or v < 0 for v in extra_objects.values()):
            raise ValueError("extra_objects: means must be finite and >= 0")
    rng = np.random.default_rng(int(seed))
    road = sample_road(rng)
    placer = Placer(rng, road)
    place_street(placer)
    if rng.random() < 0.4:
        place_road_works(placer)
    place_crossing(placer)
    place_free(placer, int(rng.integers(14, 32)))
    ego_speed = 0.0 if rng.random() < 0.2 else rng.uniform(3.0, 14.0)
    if extra_objects:
        placer.rng = np.random.default_rng([int(seed), 1])
        place_extra(placer, extra_objects)

    boxes = np.asarray(placer.boxes, dtype=np.float32).reshape(-1, 9)
    static = np.asarray(placer.static_boxes, dtype=np.float32).reshape(-1, 7)
    look = placer.look + placer.static_look
    scene = Scene(
        seed=int(seed),
        boxes=boxes,
        labels=np.asarray(placer.labels, dtype=np.int64),
        ego_velocity=np.array([ego_speed, 0.0], dtype=np.float32),
        road=road,
        static_boxes=static,
        static_kinds=np.asarray(placer.static_kinds, dtype=np.int64),
        reflectivity=np.array([v[0] for v in look], dtype=np.float32),
        rcs=np.array([v[1] for v in look], dtype=np.float32),
        color=np.array([v[2] for v in look], dtype=np.float32).reshape(-1, 3),
        n_scatter=np.array([v[3] for v in look], dtype=np.int64),
    )
    for arr in (scene.boxes, scene.labels, scene.ego_velocity, scene.static_boxes,
                scene.static_kinds, scene.reflectivity, scene.rcs, scene.color, scene.n_scatter):
        arr.flags.writeable = False
    return scene
