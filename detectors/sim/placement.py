"""Collision-free placement of boxes given in road coordinates."""

from __future__ import annotations

import dataclasses

import numpy as np

from calibrators.core.vocab import wrap_angle
from detectors.sim.classes import (
    CLASS_SPECS,
    CLASSES,
    STATIC_KINDS,
    STATIC_MATERIALS,
    Material,
    sample_material,
    sample_size,
)
from detectors.sim.geometry import overlaps
from detectors.sim.layout import Road

# The ego vehicle's own box (never overlapped): rear axle at the origin.
EGO_BOX = np.array([1.4, 0.0, 0.9, 2.0, 4.9, 1.8, 0.0])
GT_RANGE = 60.0
STATIC_RANGE = 90.0


class Placer:
    """Accumulates ground-truth objects and static clutter without overlaps.

    Every object is given in road coordinates (``s``, ``t``, yaw relative to the road
    heading); `place` converts to the ego frame, rejects boxes out of range or touching an
    already placed box (or a keep-out zone, or the ego), draws the instance's material and
    records it.
    """

    def __init__(self, rng: np.random.Generator, road: Road) -> None:
        self.rng = rng
        self.road = road
        self._occupied: list[np.ndarray] = [EGO_BOX]
        self.boxes: list[np.ndarray] = []
        self.labels: list[int] = []
        self.static_boxes: list[np.ndarray] = []
        self.static_kinds: list[int] = []
        self.look: list[tuple[float, float, np.ndarray, int]] = []
        self.static_look: list[tuple[float, float, np.ndarray, int]] = []

    def place(
        self,
        name: str,
        s: float,
        t: float,
        rel_yaw: float,
        speed: float = 0.0,
        size: np.ndarray | None = None,
        palette: tuple | None = None,
        margin: float = 0.15,
    ) -> bool:
        """Try to add one object of class or static kind `name`; return whether it fit."""
        is_gt = name in CLASS_SPECS
        if is_gt:
            spec = CLASS_SPECS[name]
            material: Material = spec.material
            if size is None:
                size = sample_size(self.rng, spec.size, spec.size_spread)
        else:
            material = STATIC_MATERIALS[name]
            if size is None:
                raise ValueError(f"size is required for static kind {name!r}")
        if palette is not None:
            material = dataclasses.replace(material, palette=palette)
        xy, heading = self.road.to_ego(np.array([s]), np.array([t]))
        x, y = float(xy[0, 0]), float(xy[0, 1])
        limit = GT_RANGE if is_gt else STATIC_RANGE
        if abs(x) > limit or abs(y) > limit:
            return False
        yaw = float(wrap_angle(float(heading[0]) + rel_yaw))
        w, length, h = (float(v) for v in size)
        z = h / 2 if name != "tree_crown" else 2.6 + h / 2
        box = np.array([x, y, z, w, length, h, yaw, speed * np.cos(yaw), speed * np.sin(yaw)])
        if overlaps(box, np.asarray(self._occupied), margin).any():
            return False
        self._occupied.append(box[:7])
        refl, rcs, rgb = sample_material(self.rng, material)
        n_scatter = material.n_scatter
        if name == "wall":
            n_scatter = max(1, int(round(length / 4.0)))
        look = (refl, rcs, rgb, n_scatter)
        if is_gt:
            self.boxes.append(box)
            self.labels.append(CLASSES.index(name))
            self.look.append(look)
        else:
            self.static_boxes.append(box[:7])
            self.static_kinds.append(STATIC_KINDS.index(name))
            self.static_look.append(look)
        return True

    def keep_out(self, s0: float, s1: float, t0: float, t1: float) -> None:
        """Reserve the road-coordinate rectangle [s0, s1] x [t0, t1] for later placements."""
        s_mid, t_mid = (s0 + s1) / 2, (t0 + t1) / 2
        xy, heading = self.road.to_ego(np.array([s_mid]), np.array([t_mid]))
        self._occupied.append(
            np.array([xy[0, 0], xy[0, 1], 1.0, abs(t1 - t0), abs(s1 - s0), 2.0, heading[0]])
        )

