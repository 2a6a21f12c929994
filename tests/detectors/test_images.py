"""Camera images and their 2-D ground truth: determinism, tight boxes, projection, occlusion,
truncation at the camera seams, the COCO export."""

from __future__ import annotations

import contextlib
import io
import json
from dataclasses import replace

import numpy as np
import pytest

from detectors.sim import (
    CAMERA_NAMES,
    CLASSES,
    MIN_VISIBLE_PIXELS,
    CameraRig,
    Scene,
    coco_instances,
    make_image_frame,
    make_scene,
    render,
    render_images,
    split_seeds,
    write_coco,
)
from detectors.sim.geometry import bev_corners


def _scene(boxes: list[list[float]], names: list[str]) -> Scene:
    """Seed 0's road with only the given boxes ``x y z w l h yaw vx vy`` (no clutter)."""
    arr = np.asarray(boxes, dtype=np.float32).reshape(-1, 9)
    n = len(arr)
    return replace(
        make_scene(0), boxes=arr, labels=np.array([CLASSES.index(c) for c in names]),
        static_boxes=np.zeros((0, 7), np.float32), static_kinds=np.zeros(0, np.int64),
        reflectivity=np.full(n, 0.4, np.float32), rcs=np.zeros(n, np.float32),
        color=np.full((n, 3), 0.5, np.float32), n_scatter=np.ones(n, np.int64))


def _car(x: float, y: float, yaw: float = 0.0) -> list[float]:
    return [x, y, 0.85, 1.9, 4.6, 1.7, yaw, 0.0, 0.0]


def _bus(x: float, y: float) -> list[float]:
    return [x, y, 1.75, 2.9, 11.0, 3.5, 0.0, 0.0, 0.0]


def _corners(box: list[float]) -> np.ndarray:
    """The eight 3-D corners of one box. -> [8, 3]."""
    b = np.asarray(box, dtype=np.float64)
    bev = bev_corners(b[None, :7])[0]
    z = np.array([b[2] - b[5] / 2, b[2] + b[5] / 2])
    return np.array([[x, y, zz] for x, y in bev for zz in z])


def _row(truth, obj: int, camera: int | None = None) -> int:
    """Index of the 2-D box of object `obj` (in `camera`); fails when there is none or two."""
    match = truth.box3d_index == obj
    if camera is not None:
        match &= truth.camera == camera
    (row,) = np.flatnonzero(match)
    return int(row)


@pytest.fixture(scope="module")
def frames():
    return [make_image_frame(seed) for seed in split_seeds("val", 6)]


def test_images_are_deterministic_typed_and_leave_the_camera_points_alone() -> None:
    a, b, c = make_image_frame(100_003), make_image_frame(100_003), make_image_frame(100_004)
    assert a.images.rgb.shape == (6, 71, 120, 3) and a.images.rgb.dtype == np.float32
    assert a.images.depth.shape == (6, 71, 120) and a.images.depth.dtype == np.float32
    assert a.images.owner.shape == (6, 71, 120) and a.images.owner.dtype == np.int64
    assert 0.0 <= a.images.rgb.min() and a.images.rgb.max() <= 1.0
    assert a.images.depth.min() >= 0.0 and (a.images.depth > 0).mean() > 0.5
    for field in ("rgb", "depth", "owner"):
        assert np.array_equal(getattr(a.images, field), getattr(b.images, field))
    for field in vars(a.truth):
        assert np.array_equal(getattr(a.truth, field), getattr(b.truth, field))
    assert not np.array_equal(a.images.rgb, c.images.rgb)
    # the images draw from a stream of their own: the camera's point cloud is unchanged
    scene = make_scene(100_003)
    before = render(scene, "camera").points
    render_images(scene)
    assert np.array_equal(render(scene, "camera").points, before)


def test_every_box_is_inside_its_image_and_the_tight_extent_of_its_pixels(frames) -> None:
    n_boxes = 0
    for frame in frames:
        truth, owner = frame.truth, frame.images.owner
        height, width = owner.shape[1:]
        for i in range(len(truth)):
            x, y, w, h = truth.bbox[i].astype(int)
            assert np.array_equal(truth.bbox[i], [x, y, w, h])   # whole pixels
            assert 0 <= x and 0 <= y and w >= 1 and h >= 1
            assert x + w <= width and y + h <= height
            mine = owner[truth.camera[i]] == truth.box3d_index[i]
            assert mine.sum() == truth.visible_pixels[i] >= MIN_VISIBLE_PIXELS
            inside = mine[y:y + h, x:x + w]
            assert inside.sum() == mine.sum()                    # nothing of it outside
            # tight: every border row and column of the box holds one of its pixels
            assert inside[0].any() and inside[-1].any()
            assert inside[:, 0].any() and inside[:, -1].any()
            assert truth.label[i] == frame.scene.labels[truth.box3d_index[i]]
            assert 0.0 <= truth.occlusion[i] <= 1.0
        n_boxes += len(truth)
    assert n_boxes > 60


def test_an_unoccluded_object_projects_where_its_3d_box_says() -> None:
    rig = CameraRig()
    boxes = [_car(15.0, 0.0), _car(8.0, -12.0, 0.4), [-7.0, 12.0, 0.55, 0.6, 0.7, 1.1, 0.0, 0, 0]]
    scene = _scene(boxes, ["car", "car", "pedestrian"])
    _, truth = render_images(scene)
    for obj, camera in ((0, 0), (1, 1), (2, 4)):
        i = _row(truth, obj)
        assert truth.camera[i] == camera and CAMERA_NAMES[camera] in ("CAM_FRONT",
                                                                       "CAM_FRONT_RIGHT",
                                                                       "CAM_BACK_LEFT")
        _, px, py = rig.project(_corners(boxes[obj]), np.full(8, camera))
        x, y, w, h = truth.bbox[i]
        projected = np.array([px.min(), py.min(), px.max(), py.max()])
        # pixels are owned where their centre ray hits: at most half a pixel off each edge
        assert np.abs(np.array([x, y, x + w, y + h]) - projected).max() <= 0.55
        assert truth.occlusion[i] == 0.0 and not truth.truncated[i]
        # the extent the truncation flag uses is that projection too
        full = rig.box_extent(np.asarray(boxes)[[obj]], np.array([camera]))[0]
        assert np.abs(full - projected).max() < 0.05


def test_an_object_on_a_camera_seam_has_a_truncated_box_in_both_images() -> None:
    rig = CameraRig()
    seam = np.deg2rad(30.0 + 0.25)  # the edge between CAM_FRONT_LEFT (5) and CAM_FRONT (0)
    scene = _scene([_car(14.0 * np.cos(seam), 14.0 * np.sin(seam))], ["car"])
    images, truth = render_images(scene)
    front, left = _row(truth, 0, 0), _row(truth, 0, 5)
    assert truth.truncated[front] and truth.truncated[left]
    assert truth.bbox[front][0] == 0.0                                # from the left edge
    assert truth.bbox[left][0] + truth.bbox[left][2] == rig.width     # to the right edge
    assert truth.visible_pixels[[front, left]].sum() == (images.owner == 0).sum()
    assert truth.occlusion[front] == 0.0 and truth.occlusion[left] == 0.0


def test_an_object_behind_another_is_marked_occluded() -> None:
    near, far = _car(10.0, 0.0), _car(20.0, 1.6)   # only the far car's left edge shows
    _, truth = render_images(_scene([near, far], ["car", "car"]))
    _, alone = render_images(_scene([far], ["car"]))
    front, back = _row(truth, 0), _row(truth, 1)
    assert truth.occlusion[front] == 0.0 and alone.occlusion[0] == 0.0
    assert truth.occlusion[back] > 0.75
    # occlusion compares with the pixels the far car owns when it is alone in the scene
    implied = truth.visible_pixels[back] / (1.0 - truth.occlusion[back])
    assert implied == pytest.approx(alone.visible_pixels[0], abs=0.05)
    # a bus in front of the ego leaves a small car behind it no pixel: it gets no box,
    # and the roof of a bus behind a car shows
    _, hidden = render_images(_scene([_bus(10.0, 0.0), _car(22.0, 0.0)], ["bus", "car"]))
    assert list(hidden.box3d_index) == [0]
    _, roof = render_images(_scene([_car(10.0, 0.0), _bus(26.0, 0.0)], ["car", "bus"]))
    assert 0.3 < roof.occlusion[_row(roof, 1)] < 0.7


def test_a_finer_rig_doubles_the_pixels() -> None:
    coarse, fine = CameraRig(), CameraRig(2)
    assert (fine.width, fine.height) == (240, 141)
    for rig in (coarse, fine):
        camera, row, column = rig.pixels(rig.ray_index.ravel())
        grid = np.meshgrid(np.arange(6), np.arange(rig.height), np.arange(rig.width),
                           indexing="ij")
        assert all(np.array_equal(a, g.ravel()) for a, g in zip((camera, row, column), grid,
                                                                 strict=True))
        # a ray lands on its own pixel's centre
        ray = rig.ray_index.ravel()[::97]
        c, x, y = rig.project(rig.grid.origin + 10.0 * rig.grid.directions(ray))
        cam, r, col = rig.pixels(ray)
        assert np.array_equal(c, cam)
        assert np.allclose(x, col + 0.5) and np.allclose(y, r + 0.5)
    scene = _scene([_car(15.0, 0.0)], ["car"])
    (w1, h1), (w2, h2) = (render_images(scene, rig=rig)[1].bbox[0, 2:] for rig in (coarse, fine))
    assert abs(w2 - 2 * w1) <= 1 and abs(h2 - 2 * h1) <= 1
    with pytest.raises(ValueError, match="scale"):
        CameraRig(0)


def test_coco_export_is_valid(tmp_path) -> None:
    coco = coco_instances("val", 3)
    assert [c["id"] for c in coco["categories"]] == list(range(1, 11))
    assert [c["name"] for c in coco["categories"]] == list(CLASSES)
    images = {im["id"]: im for im in coco["images"]}
    assert len(images) == len(coco["images"]) == 18
    assert {(im["scene_seed"], im["camera"]) for im in coco["images"]} == {
        (s, c) for s in split_seeds("val", 3) for c in range(6)}
    ann_ids = [a["id"] for a in coco["annotations"]]
    assert len(set(ann_ids)) == len(ann_ids) > 30
    for a in coco["annotations"]:
        im = images[a["image_id"]]
        x, y, w, h = a["bbox"]
        assert 1 <= a["category_id"] <= 10 and a["iscrowd"] == 0
        assert a["area"] == w * h > 0
        assert 0 <= x and x + w <= im["width"] and 0 <= y and y + h <= im["height"]
        assert isinstance(a["truncated"], bool) and 0.0 <= a["occlusion"] <= 1.0
        scene = make_scene(im["scene_seed"])
        assert scene.labels[a["box3d_index"]] + 1 == a["category_id"]
    # the file round-trips, and the images it names are written when asked
    out = write_coco(tmp_path / "val.json", "val", 1, image_dir=tmp_path / "images")
    assert json.loads((tmp_path / "val.json").read_text()) == out
    first = out["images"][0]
    png = pytest.importorskip("matplotlib.image").imread(tmp_path / "images" / first["file_name"])
    assert png.shape[:2] == (71, 120)
    depth = np.load(tmp_path / "images" / first["depth_file_name"])
    assert depth.shape == (71, 120) and depth.dtype == np.float32


def test_pycocotools_reads_the_export_and_scores_the_truth_perfectly(tmp_path) -> None:
    pytest.importorskip("pycocotools")
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    coco = write_coco(tmp_path / "val.json", "val", 2)
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO(str(tmp_path / "val.json"))
        dt = gt.loadRes([{**a, "score": 1.0} for a in coco["annotations"]])
        evaluation = COCOeval(gt, dt, "bbox")
        evaluation.evaluate()
        evaluation.accumulate()
        evaluation.summarize()
    assert evaluation.stats[0] == pytest.approx(1.0)   # AP@[.5:.95] of the truth itself
