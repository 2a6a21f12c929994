"""Simulated world and sensors: determinism, layout, physics of the degradations."""

from __future__ import annotations

import numpy as np
import pytest

from detectors.sim import (
    CLASSES,
    FEATURES,
    SENSORS,
    SPLITS,
    Scene,
    compensate_radial_velocity,
    make_frame,
    make_scene,
    render,
)
from detectors.sim.classes import CLASS_SPECS
from detectors.sim.geometry import bev_distance_to_box, overlaps
from detectors.sim.layout import Road

STRAIGHT = Road(0.0, 0.0, 3.5, 2, 2, (False, False), 3.0, 2.0, -1.75, None)


def _scene(boxes: list[list[float]], names: list[str], seed: int = 0, ego_v: float = 0.0) -> Scene:
    """A hand-made scene: given boxes ``x y z w l h yaw vx vy`` on an empty straight road."""
    arr = np.asarray(boxes, dtype=np.float32).reshape(-1, 9)
    specs = [CLASS_SPECS[n] for n in names]
    return Scene(
        seed=seed,
        boxes=arr,
        labels=np.array([CLASSES.index(n) for n in names], dtype=np.int64),
        ego_velocity=np.array([ego_v, 0.0], dtype=np.float32),
        road=STRAIGHT,
        static_boxes=np.zeros((0, 7), dtype=np.float32),
        static_kinds=np.zeros(0, dtype=np.int64),
        reflectivity=np.full(len(arr), 0.4, dtype=np.float32),
        rcs=np.array([s.material.rcs[0] for s in specs], dtype=np.float32),
        color=np.full((len(arr), 3), 0.5, dtype=np.float32),
        n_scatter=np.array([s.material.n_scatter for s in specs], dtype=np.int64),
    )


def _car(x: float, y: float, vx: float = 0.0) -> list[float]:
    return [x, y, 0.85, 1.9, 4.6, 1.7, 0.0, vx, 0.0]


@pytest.fixture(scope="module")
def scenes() -> list[Scene]:
    return [make_scene(seed) for seed in range(200)]


def test_scene_is_deterministic_per_seed() -> None:
    a, b, c = make_scene(11), make_scene(11), make_scene(12)
    assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.labels, b.labels)
    assert np.array_equal(a.static_boxes, b.static_boxes) and a.road == b.road
    assert a.boxes.shape != c.boxes.shape or not np.array_equal(a.boxes, c.boxes)


@pytest.mark.parametrize("sensor", SENSORS)
def test_render_is_deterministic_and_typed(sensor: str) -> None:
    a, b, c = make_frame(5, sensor), make_frame(5, sensor), make_frame(6, sensor)
    assert np.array_equal(a.points, b.points)
    assert not np.array_equal(a.points[:50], c.points[:50])
    pts, g = a.points, a.scene.num_objects
    assert pts.dtype == np.float32 and pts.ndim == 2 and pts.shape[1] == len(FEATURES[sensor])
    assert np.isfinite(pts).all()
    assert FEATURES[sensor][:3] == ("x", "y", "z")
    assert a.sensor_frame.gt_num_points.shape == (g,)
    assert a.sensor_frame.gt_num_points.dtype == np.int64
    assert a.sensor_frame.point_owner.shape == (len(pts),)
    assert a.sensor_frame.gt_num_points.sum() == (a.sensor_frame.point_owner >= 0).sum()
    assert a.boxes.dtype == np.float32 and a.boxes.shape == (g, 9)
    assert a.labels.dtype == np.int64 and a.scene.ego_velocity.shape == (2,)


def test_feature_names() -> None:
    assert FEATURES["lidar"] == ("x", "y", "z", "intensity")
    assert FEATURES["radar1"] == ("x", "y", "z", "rcs", "vr")
    assert FEATURES["radar5"] == ("x", "y", "z", "rcs", "vr", "t")
    assert FEATURES["camera"][:3] == ("x", "y", "z") and len(FEATURES["camera"]) == 6


def test_splits_are_disjoint() -> None:
    sets = {name: set(r) for name, r in SPLITS.items()}
    assert set(SPLITS) == {"train", "val", "test", "holdout"}
    names = sorted(sets)
    assert all(not sets[a] & sets[b] for a in names for b in names if a < b)
    assert len(SPLITS["holdout"]) >= 3000


def test_bad_arguments_are_named() -> None:
    with pytest.raises(ValueError, match="sensor"):
        render(make_scene(0), "sonar")
    with pytest.raises(ValueError, match="seed"):
        make_scene(-1)


def test_boxes_in_range_on_ground_and_disjoint(scenes: list[Scene]) -> None:
    for scene in scenes[:60]:
        boxes = scene.boxes.astype(np.float64)
        assert (np.abs(boxes[:, :2]) <= 60.0).all()
        np.testing.assert_allclose(boxes[:, 2], boxes[:, 5] / 2, atol=1e-5)
        for i in range(len(boxes)):
            assert not overlaps(boxes[i], np.delete(boxes, i, axis=0), margin=0.0).any()


def test_class_frequencies_and_sizes(scenes: list[Scene]) -> None:
    labels = np.concatenate([s.labels for s in scenes])
    counts = np.bincount(labels, minlength=len(CLASSES))
    assert counts.argmax() == CLASSES.index("car")
    assert (counts > 0).all()
    assert counts[CLASSES.index("construction_vehicle")] / counts.sum() < 0.03
    n = np.array([s.num_objects for s in scenes])
    assert 15 <= n.mean() <= 40
    boxes = np.concatenate([s.boxes for s in scenes])
    for name in ("car", "bus", "pedestrian", "traffic_cone"):
        mean_wlh = boxes[labels == CLASSES.index(name), 3:6].mean(axis=0)
        np.testing.assert_allclose(mean_wlh, CLASS_SPECS[name].size, rtol=0.1)


def test_lidar_density_falls_with_range() -> None:
    per_range = []
    for x in (8.0, 16.0, 32.0):
        counts = [render(_scene([_car(x, 4.0)], ["car"], seed=s), "lidar").gt_num_points[0]
                  for s in range(3)]
        per_range.append(np.mean(counts))
    assert per_range[0] > 2 * per_range[1] > 4 * per_range[2] > 0


def _surface_error(sensor: str, x: float) -> float:
    """Mean BEV distance of a car's points to its box, over several seeds."""
    errors = []
    for seed in range(6):
        scene = _scene([_car(x, 5.0)], ["car"], seed=seed)
        frame = render(scene, sensor)
        pts = frame.points[frame.point_owner == 0]
        box = scene.boxes.astype(np.float64)
        errors += [bev_distance_to_box(p[:2].astype(np.float64), box)[0] for p in pts]
    assert errors, f"{sensor} saw no points of the car at {x} m"
    return float(np.mean(errors))


@pytest.mark.parametrize("sensor", ["lidar", "radar1", "camera"])
def test_position_noise_grows_with_range(sensor: str) -> None:
    near, far = _surface_error(sensor, 8.0), _surface_error(sensor, 38.0)
    assert far > 1.5 * near
    if sensor == "camera":
        assert near < 0.15 and far > 0.3


def test_occlusion_removes_points() -> None:
    ped = [30.0, 0.3, 0.9, 0.7, 0.7, 1.8, 0.0, 0.0, 0.0]
    bus = [12.0, 0.0, 1.75, 2.9, 11.0, 3.5, 0.0, 0.0, 0.0]
    for sensor in ("lidar", "camera"):
        alone = render(_scene([ped], ["pedestrian"]), sensor).gt_num_points[0]
        hidden = render(_scene([ped, bus], ["pedestrian", "bus"]), sensor).gt_num_points[0]
        assert alone > 5 and hidden == 0
    car = _car(30.0, 0.3)
    alone = sum(render(_scene([car], ["car"], seed=s), "radar1").gt_num_points[0]
                for s in range(10))
    hidden = sum(render(_scene([car, bus], ["car", "bus"], seed=s), "radar1").gt_num_points[0]
                 for s in range(10))
    assert hidden < 0.5 * alone


def test_radar5_compensates_ego_motion_and_smears_movers() -> None:
    scene = _scene([_car(20.0, 6.0), _car(20.0, -6.0, vx=10.0)], ["car", "car"], ego_v=8.0)
    frame = render(scene, "radar5")
    pts, owner = frame.points, frame.point_owner
    np.testing.assert_allclose(np.unique(pts[:, 5]), [-0.2, -0.15, -0.1, -0.05, 0.0], atol=1e-6)
    shift = []
    for obj in (0, 1):
        now = pts[(owner == obj) & (pts[:, 5] == 0.0), 0].mean()
        past = pts[(owner == obj) & (pts[:, 5] <= -0.15), 0].mean()
        shift.append(now - past)
    assert abs(shift[0]) < 0.6  # the parked car lines up across scans
    assert 1.0 < shift[1] < 2.6  # the mover smears by v * dt (10 m/s * 0.15-0.2 s)


def test_radar_radial_velocity_is_relative_doppler() -> None:
    scene = _scene([_car(25.0, 3.0)], ["car"], ego_v=10.0)
    frame = render(scene, "radar1")
    pts = frame.points[frame.point_owner == 0]
    assert len(pts) > 0
    assert np.all(pts[:, 4] < -8.0)  # static car seen from a moving ego approaches
    comp = compensate_radial_velocity(pts, scene.ego_velocity)
    assert np.abs(comp).max() < 1.0


def test_extra_objects_add_to_the_seeds_own_scene() -> None:
    rare = {"bus": 2.0, "bicycle": 2.0}
    counts = {"plain": 0, "extra": 0}
    for seed in range(30):
        plain, extra = make_scene(seed), make_scene(seed, rare)
        assert np.array_equal(plain.boxes, extra.boxes[:plain.num_objects])
        assert np.array_equal(plain.labels, extra.labels[:plain.num_objects])
        for name, scene in (("plain", plain), ("extra", extra)):
            counts[name] += int(np.isin(scene.labels, [CLASSES.index(c) for c in rare]).sum())
        boxes = extra.boxes.astype(np.float64)
        for i in range(len(boxes)):
            assert not overlaps(boxes[i], np.delete(boxes, i, axis=0), margin=0.0).any()
    assert counts["extra"] > 2 * counts["plain"]
    with pytest.raises(ValueError, match="extra_objects"):
        make_scene(0, {"unicorn": 1.0})
    with pytest.raises(ValueError, match="extra_objects"):
        make_scene(0, {"bus": -1.0})
