"""COCO instances export of the camera images' 2-D ground truth (`image_truth`).

``coco_instances(split, n)`` renders the first `n` scenes of `split` (`splits.SPLITS`) and
returns a COCO instances dict: one image per (scene, camera), one annotation per 2-D box.
Besides the COCO fields, images carry ``scene_seed``, ``camera``, ``camera_name`` and
``depth_file_name``; annotations carry ``box3d_index`` (row of ``make_scene(seed).boxes``),
``truncated``, ``occlusion`` and ``visible_pixels``. Category ids are ``CLASSES`` index + 1.
``write_coco`` writes it as JSON and, optionally, the images (RGB PNG, depth ``.npy``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from detectors.sim.classes import CLASSES
from detectors.sim.image_truth import MIN_VISIBLE_PIXELS
from detectors.sim.images import CameraImages, render_images
from detectors.sim.rig import CAMERA_NAMES, RIG, CameraRig
from detectors.sim.scene import make_scene
from detectors.sim.splits import split_seeds


def coco_categories() -> list[dict[str, Any]]:
    """COCO categories of the ten classes: ids 1..10 in CLASSES order."""
    return [{"id": i + 1, "name": name, "supercategory": "object"}
            for i, name in enumerate(CLASSES)]


def coco_instances(split: str, n: int, rig: CameraRig = RIG,
                   image_dir: str | Path | None = None) -> dict[str, Any]:
    """COCO instances of the six images of each of the first `n` scenes of `split`.

    image_dir: where to write each image's RGB (PNG, its ``file_name``) and depth (float32
    ``.npy``, its ``depth_file_name``); None writes nothing.
    """
    seeds = split_seeds(split, n)
    if image_dir is not None:
        Path(image_dir).mkdir(parents=True, exist_ok=True)
    images: list[dict[str, Any]] = []
    annotations: list[dict[str, Any]] = []
    for seed in seeds:
        camera_images, truth = render_images(make_scene(seed), rig=rig)
        ids = {}
        for camera, name in enumerate(CAMERA_NAMES):
            stem = f"{seed}_{name}"
            ids[camera] = len(images) + 1
            images.append({
                "id": ids[camera], "file_name": f"{stem}.png", "width": rig.width,
                "height": rig.height, "scene_seed": seed, "camera": camera,
                "camera_name": name, "depth_file_name": f"{stem}_depth.npy",
            })
            if image_dir is not None:
                _write_image(camera_images, camera, Path(image_dir) / stem)
        for i in range(len(truth)):
            x, y, w, h = (float(v) for v in truth.bbox[i])
            annotations.append({
                "id": len(annotations) + 1, "image_id": ids[int(truth.camera[i])],
                "category_id": int(truth.label[i]) + 1, "bbox": [x, y, w, h], "area": w * h,
                "iscrowd": 0, "box3d_index": int(truth.box3d_index[i]),
                "truncated": bool(truth.truncated[i]),
                "occlusion": round(float(truth.occlusion[i]), 4),
                "visible_pixels": int(truth.visible_pixels[i]),
            })
    info = {
        "description": "detcal simulated surround-camera images (docs/detectors.md)",
        "split": split, "scenes": len(seeds), "scale": rig.scale,
        "min_visible_pixels": MIN_VISIBLE_PIXELS,
    }
    return {"info": info, "images": images, "annotations": annotations,
            "categories": coco_categories()}


def write_coco(path: str | Path, split: str, n: int, rig: CameraRig = RIG,
               image_dir: str | Path | None = None) -> dict[str, Any]:
    """Write ``coco_instances(split, n, rig, image_dir)`` to `path` as JSON; return it."""
    coco = coco_instances(split, n, rig, image_dir)
    Path(path).write_text(json.dumps(coco), encoding="utf-8")
    return coco


def _write_image(images: CameraImages, camera: int, stem: Path) -> None:
    """`stem`.png (8-bit RGB) and `stem`_depth.npy ([H, W] float32 m) of one camera."""
    from matplotlib.image import imsave  # the detectors extra; only needed to write PNGs

    imsave(stem.with_suffix(".png"), np.round(images.rgb[camera] * 255).astype(np.uint8))
    np.save(stem.parent / f"{stem.name}_depth.npy", images.depth[camera])
