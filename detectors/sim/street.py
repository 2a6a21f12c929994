"""Static street clutter (not ground truth): building walls, poles, trees, furniture."""

from __future__ import annotations

import numpy as np

from detectors.sim.classes import STATIC_SIZES, sample_size
from detectors.sim.layout import Road
from detectors.sim.placement import Placer

S_MAX = 85.0


def place_street(placer: Placer) -> None:
    """Add walls, poles, trees and street furniture along both sides of the road."""
    road, rng = placer.road, placer.rng
    for side in (-1, 1):
        kerb = road.right_edge if side < 0 else road.left_edge
        _walls(placer, side, kerb + side * (road.sidewalk + road.setback))
        _poles_and_trees(placer, road, side, kerb)
        _furniture(placer, road, side, kerb)
    if road.crossing_s is not None:
        for side in (-1, 1):
            kerb = road.right_edge if side < 0 else road.left_edge
            for ds in (-2.6, 2.6):
                if rng.random() < 0.6:
                    size = sample_size(rng, *STATIC_SIZES["bollard"])
                    placer.place("bollard", road.crossing_s + ds, kerb + side * 0.4, 0.0,
                                 size=size)


def _walls(placer: Placer, side: int, t_front: float) -> None:
    """Building fronts: segments 8-30 m long with gaps, 3-15 m high, 5 m deep."""
    rng = placer.rng
    if rng.random() < 0.15:
        return
    s = -S_MAX + rng.uniform(0.0, 10.0)
    while s < S_MAX:
        length = rng.uniform(8.0, 30.0)
        depth = 5.0
        t = t_front + side * (rng.uniform(0.0, 1.5) + depth / 2)
        size = np.array([depth, length, rng.uniform(3.0, 15.0)])
        placer.place("wall", s + length / 2, t, 0.0, size=size, margin=0.0)
        s += length + (rng.uniform(2.0, 12.0) if rng.random() < 0.35 else 0.3)


def _poles_and_trees(placer: Placer, road: Road, side: int, kerb: float) -> None:
    """Lamp posts every 20-35 m at the kerb; trees every 8-15 m on wide sidewalks."""
    rng = placer.rng
    s = -S_MAX + rng.uniform(0.0, 20.0)
    while s < S_MAX:
        size = sample_size(rng, *STATIC_SIZES["pole"])
        placer.place("pole", s, kerb + side * 0.5, 0.0, size=size)
        s += rng.uniform(20.0, 35.0)
    if road.sidewalk < 3.0 or rng.random() < 0.5:
        return
    s = -S_MAX + rng.uniform(0.0, 10.0)
    while s < S_MAX:
        trunk = sample_size(rng, *STATIC_SIZES["tree_trunk"])
        t = kerb + side * 1.3
        if placer.place("tree_trunk", s, t, rng.uniform(-np.pi, np.pi), size=trunk):
            crown = np.full(3, rng.uniform(2.2, 3.5))
            placer.place("tree_crown", s, t, rng.uniform(-np.pi, np.pi), size=crown, margin=0.0)
        s += rng.uniform(8.0, 15.0)


def _furniture(placer: Placer, road: Road, side: int, kerb: float) -> None:
    """Bins, bollards, hydrants and benches scattered on the sidewalk."""
    rng = placer.rng
    kinds = ("bin", "bollard", "hydrant", "bench")
    for _ in range(rng.poisson(4.0)):
        kind = kinds[rng.choice(4, p=[0.35, 0.35, 0.15, 0.15])]
        size = sample_size(rng, *STATIC_SIZES[kind])
        t = kerb + side * rng.uniform(0.4, road.sidewalk - 0.4)
        yaw = 0.0 if kind == "bench" else rng.uniform(-np.pi, np.pi)
        placer.place(kind, rng.uniform(-S_MAX, S_MAX), t, yaw, size=size)
