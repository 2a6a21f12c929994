"""Ground-truth objects on the road layout: traffic, parked vehicles, pedestrians, road works.

Every generator works in road coordinates and hands boxes to a `Placer`, which rejects
overlaps. Speeds are in m/s; object velocities are absolute (world) velocities expressed in
the ego frame, as nuScenes annotates them.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from detectors.sim.classes import CLASS_SPECS, CLASSES
from detectors.sim.layout import PARKING_WIDTH
from detectors.sim.placement import Placer

S_RANGE = 68.0
TRIES = 12
HIVIS = ((0.5, (0.90, 0.45, 0.10)), (0.5, (0.80, 0.85, 0.20)))
# (probability of driving, min speed, max speed) per vehicle-like class.
MOTION = {
    "car": (0.6, 2.0, 15.0),
    "truck": (0.6, 2.0, 12.0),
    "bus": (0.75, 2.0, 12.0),
    "trailer": (0.5, 2.0, 12.0),
    "construction_vehicle": (0.4, 0.5, 4.0),
    "motorcycle": (0.55, 2.0, 14.0),
    "bicycle": (0.5, 2.0, 7.0),
}


def place_road_works(placer: Placer) -> None:
    """A closed stretch of one lane: cones and/or barriers, maybe a digger and workers."""
    road, rng = placer.road, placer.rng
    lanes = road.lane_centres()
    lane = int(rng.choice([0, road.n_forward - 1, len(lanes) - 1]))
    tc = float(lanes[lane])
    length = rng.uniform(10.0, 35.0)
    s0 = rng.uniform(-50.0, 45.0)
    if abs(tc - road.ego_t) < 0.1 and s0 < 8.0 < s0 + length + 8.0:
        s0 = rng.uniform(10.0, 40.0)  # never close the ego's lane around the ego
    toward_centre = -np.sign(tc) if tc != 0 else 1.0
    edge = tc + toward_centre * road.lane_width / 2 * 0.9
    style = rng.choice(["cones", "barriers", "both"], p=[0.45, 0.25, 0.30])
    spacing = rng.uniform(2.0, 4.0)
    for i, s in enumerate(np.arange(s0, s0 + length, spacing)):
        taper = min(1.0, i / 3.0)  # first cones close the lane diagonally
        t = tc + (edge - tc) * taper if i < 4 else edge
        if style == "barriers" and i >= 4:
            placer.place("barrier", s, edge, np.pi / 2 + rng.normal(0, 0.05))
        else:
            placer.place("traffic_cone", s, t + rng.normal(0, 0.05), rng.uniform(-np.pi, np.pi))
    if style == "both":
        t_in = tc - toward_centre * road.lane_width * 0.2
        for s in np.arange(s0 + 4.0, s0 + length, rng.uniform(2.6, 3.2)):
            placer.place("barrier", s, t_in, np.pi / 2 + rng.normal(0, 0.05))
    inside = (tc - road.lane_width * 0.15, s0 + 3.0, s0 + length - 2.0)
    if rng.random() < 0.45:
        for _ in range(TRIES):
            if placer.place("construction_vehicle", rng.uniform(*inside[1:]), inside[0],
                            rng.choice([0.0, np.pi]) + rng.normal(0, 0.2),
                            rng.choice([0.0, rng.uniform(0.3, 2.0)])):
                break
    for _ in range(rng.integers(0, 4)):
        _try(placer, lambda: ("pedestrian", rng.uniform(*inside[1:]),
                              tc + rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi),
                              rng.choice([0.0, rng.uniform(0.3, 1.2)])), palette=HIVIS)
    t_lo, t_hi = sorted((tc - road.lane_width / 2, tc + road.lane_width / 2))
    placer.keep_out(s0 - 1.0, s0 + length + 1.0, t_lo, t_hi)


def place_crossing(placer: Placer) -> None:
    """Pedestrians on the zebra crossing (walking across) and waiting at its kerbs."""
    road, rng = placer.road, placer.rng
    if road.crossing_s is None:
        return
    for _ in range(rng.poisson(2.0)):
        direction = rng.choice([-1.0, 1.0])
        _try(placer, lambda d=direction: (
            "pedestrian", road.crossing_s + rng.uniform(-1.8, 1.8),
            rng.uniform(road.right_edge, road.left_edge), d * np.pi / 2 + rng.normal(0, 0.15),
            rng.uniform(0.8, 1.7)))
    for _ in range(rng.poisson(1.0)):
        side = rng.choice([-1, 1])
        kerb = road.right_edge if side < 0 else road.left_edge
        _try(placer, lambda k=kerb, sd=side: (
            "pedestrian", road.crossing_s + rng.uniform(-2.0, 2.0), k + sd * rng.uniform(0.3, 1.5),
            -sd * np.pi / 2 + rng.normal(0, 0.3), 0.0))


def place_free(placer: Placer, n: int, max_total: int = 40) -> None:
    """`n` objects of classes drawn by frequency, each placed where its class belongs.

    Stops early once the scene holds `max_total` ground-truth objects.
    """
    rng = placer.rng
    weights = np.array([CLASS_SPECS[c].weight for c in CLASSES])
    for k in rng.choice(len(CLASSES), size=n, p=weights / weights.sum()):
        if len(placer.boxes) >= max_total:
            break
        name = CLASSES[int(k)]
        _place_where_it_belongs(placer, name)
        if name == "pedestrian" and rng.random() < 0.3:  # a companion walking alongside
            _place_where_it_belongs(placer, name)


def place_extra(placer: Placer, means: Mapping[str, float]) -> None:
    """Training-time object sampling: Poisson(`means[c]`) extra objects of class c, each
    placed where its class belongs (the simulated counterpart of mmdet3d's ObjectSample /
    GT-database pasting, which every nuScenes detector uses to see rare classes more often).
    The sensor then renders them like any other object, occlusion included."""
    rng = placer.rng
    for name in CLASSES:
        mean = float(means.get(name, 0.0))
        for _ in range(int(rng.poisson(mean)) if mean > 0 else 0):
            _place_where_it_belongs(placer, name)


Pose = tuple[str, float, float, float, float]


def _place_where_it_belongs(placer: Placer, name: str) -> bool:
    """One object of class `name`: pedestrians on a sidewalk, vehicles in a lane or parked,
    cones and barriers (stray ones) at the kerb."""
    if name == "pedestrian":
        return _try(placer, lambda: _sidewalk_pose(placer, name))
    if name in MOTION:
        return _try(placer, lambda: _vehicle_pose(placer, name))
    return _try(placer, lambda: _kerb_pose(placer, name))


def _try(placer: Placer, draw, palette: tuple | None = None) -> bool:  # noqa: ANN001
    """Draw poses from `draw() -> (name, s, t, rel_yaw, speed)` until one fits."""
    for _ in range(TRIES):
        name, s, t, yaw, speed = draw()
        if placer.place(name, s, t, yaw, speed, palette=palette):
            return True
    return False


def _vehicle_pose(placer: Placer, name: str) -> Pose:
    """Driving in a lane (lane-aligned, 25 % standing in traffic) or parked at the kerb."""
    road, rng = placer.road, placer.rng
    p_drive, v_lo, v_hi = MOTION[name]
    s = rng.uniform(-S_RANGE, S_RANGE)
    sides = [sd for sd, has in zip((-1, 1), road.parking, strict=True) if has]
    if rng.random() < p_drive or not sides:
        lanes = road.lane_centres()
        lane = int(rng.integers(len(lanes)))
        t = lanes[lane] + rng.normal(0.0, 0.15)
        if name in ("bicycle", "motorcycle"):
            t += rng.normal(0.0, 0.5)
        yaw = (0.0 if lane < road.n_forward else np.pi) + rng.normal(0.0, 0.02)
        speed = 0.0 if rng.random() < 0.25 else rng.uniform(v_lo, v_hi)
        return name, s, t, yaw, speed
    side = int(rng.choice(sides))
    kerb = road.right_edge if side < 0 else road.left_edge
    t = kerb - side * PARKING_WIDTH / 2 + rng.normal(0.0, 0.1)
    if name in ("bicycle", "motorcycle") and rng.random() < 0.5:  # on the sidewalk, in a rack
        t = kerb + side * rng.uniform(0.5, 1.2)
        return name, s, t, side * np.pi / 2 + rng.normal(0.0, 0.15), 0.0
    along = 0.0 if side < 0 else np.pi
    if rng.random() < 0.15:
        along += np.pi
    return name, s, t, along + rng.normal(0.0, 0.04), 0.0


def _sidewalk_pose(placer: Placer, name: str) -> Pose:
    """On a sidewalk: 60 % walking along it, otherwise standing with any heading."""
    road, rng = placer.road, placer.rng
    side = rng.choice([-1, 1])
    kerb = road.right_edge if side < 0 else road.left_edge
    t = kerb + side * rng.uniform(0.4, road.sidewalk - 0.3)
    s = rng.uniform(-S_RANGE, S_RANGE)
    if rng.random() < 0.6:
        return name, s, t, rng.choice([0.0, np.pi]) + rng.normal(0, 0.15), rng.uniform(0.7, 1.8)
    return name, s, t, rng.uniform(-np.pi, np.pi), 0.0


def _kerb_pose(placer: Placer, name: str) -> Pose:
    """Standing just inside the road edge or on the sidewalk edge."""
    road, rng = placer.road, placer.rng
    side = rng.choice([-1, 1])
    kerb = road.right_edge if side < 0 else road.left_edge
    t = kerb + side * rng.uniform(-0.8, 0.8)
    yaw = np.pi / 2 if name == "barrier" else rng.uniform(-np.pi, np.pi)
    return name, rng.uniform(-S_RANGE, S_RANGE), t, yaw + rng.normal(0, 0.1), 0.0
