"""Road layout: a straight or gently curved two-way road through the ego position.

Road coordinates are ``(s, t)``: ``s`` the arc length along the road centreline (metres,
``s = 0`` level with the ego), ``t`` the signed lateral offset from the centreline (left
positive). Traffic drives on the right: forward lanes (same direction as the ego) have
``t < 0``, oncoming lanes ``t > 0``. Outwards from the lanes come an optional parking strip,
the sidewalk, and a setback before the building walls.

The ego frame is the road frame translated so the ego sits at the origin and rotated by the
ego's small heading offset to the road.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PARKING_WIDTH = 2.3


@dataclass(frozen=True)
class Road:
    """Road geometry of one scene (all lengths in metres, angles in radians).

    curvature: 1 / radius of the centreline (0 = straight; positive turns left).
    heading_offset: ego yaw relative to the road direction at s = 0.
    lane_width, n_forward, n_oncoming: lanes on each side of the centreline.
    parking: (right, left) whether a parking strip runs along that side.
    sidewalk: sidewalk width; setback: gap between sidewalk and the building walls.
    ego_t: lateral offset of the ego (centre of one forward lane).
    crossing_s: arc length of a zebra crossing, or None.
    """

    curvature: float
    heading_offset: float
    lane_width: float
    n_forward: int
    n_oncoming: int
    parking: tuple[bool, bool]
    sidewalk: float
    setback: float
    ego_t: float
    crossing_s: float | None

    @property
    def right_edge(self) -> float:
        """t of the right kerb (outer edge of the parking strip or of the last lane)."""
        return -self.n_forward * self.lane_width - PARKING_WIDTH * self.parking[0]

    @property
    def left_edge(self) -> float:
        """t of the left kerb."""
        return self.n_oncoming * self.lane_width + PARKING_WIDTH * self.parking[1]

    def lane_centres(self) -> np.ndarray:
        """t of every lane centre, forward lanes first. -> [n_forward + n_oncoming]."""
        fwd = -(np.arange(self.n_forward) + 0.5) * self.lane_width
        onc = (np.arange(self.n_oncoming) + 0.5) * self.lane_width
        return np.concatenate([fwd, onc])

    def to_ego(self, s: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road coordinates ``s, t`` [N] -> ego-frame ``xy`` [N, 2] and road heading [N]."""
        s = np.asarray(s, dtype=np.float64)
        t = np.asarray(t, dtype=np.float64)
        k = self.curvature
        theta = k * s
        if abs(k) < 1e-9:
            cx, cy = s, np.zeros_like(s)
        else:
            cx, cy = np.sin(theta) / k, (1.0 - np.cos(theta)) / k
        px = cx - np.sin(theta) * t
        py = cy + np.cos(theta) * t - self.ego_t
        c, sn = np.cos(self.heading_offset), np.sin(self.heading_offset)
        xy = np.stack([c * px + sn * py, -sn * px + c * py], axis=-1)
        return xy, theta - self.heading_offset

    def to_road(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ego-frame points ``xy`` [N, 2] -> road coordinates ``s, t`` [N] each."""
        c, sn = np.cos(self.heading_offset), np.sin(self.heading_offset)
        px = c * xy[:, 0] - sn * xy[:, 1]
        py = sn * xy[:, 0] + c * xy[:, 1] + self.ego_t
        k = self.curvature
        if abs(k) < 1e-9:
            return px, py
        rel_y = py - 1.0 / k
        dist = np.hypot(px, rel_y)
        t = np.where(k > 0, 1.0 / k - dist, 1.0 / k + dist)
        s = np.arctan2(np.sign(k) * px, -np.sign(k) * rel_y) / k
        return s, t


def sample_road(rng: np.random.Generator) -> Road:
    """Draw a road: 1-3 lanes each way, optional parking, curvature up to 1/250 m."""
    curved = rng.random() < 0.5
    curvature = float(rng.uniform(-1 / 250, 1 / 250)) if curved else 0.0
    n_forward = int(rng.choice([1, 2, 2, 3]))
    n_oncoming = int(rng.choice([1, 1, 2, 2, 3])) if n_forward > 1 else int(rng.choice([1, 2]))
    lane_width = float(rng.uniform(3.1, 3.7))
    ego_lane = int(rng.integers(n_forward))
    return Road(
        curvature=curvature,
        heading_offset=float(rng.normal(0.0, np.deg2rad(2.0))),
        lane_width=lane_width,
        n_forward=n_forward,
        n_oncoming=n_oncoming,
        parking=(bool(rng.random() < 0.6), bool(rng.random() < 0.5)),
        sidewalk=float(rng.uniform(2.5, 5.0)),
        setback=float(rng.uniform(0.0, 6.0)),
        ego_t=-(ego_lane + 0.5) * lane_width,
        crossing_s=float(rng.uniform(-40.0, 50.0)) if rng.random() < 0.4 else None,
    )
