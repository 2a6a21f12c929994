"""Per-sensor statistics of the simulated world (the tables in docs/sim.md).

Run ``python -m detectors.sim.stats [n_frames]``; it renders the first `n_frames` validation
scenes with every sensor and prints points per frame, render time, the share of
ground-truth boxes without any point and the position error of ground-truth points against
their box by range band.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from detectors.sim.classes import CLASSES
from detectors.sim.frame import SENSORS, render
from detectors.sim.scene import make_scene
from detectors.sim.splits import SPLITS

BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 35.0), (35.0, 60.0))


def box_error(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Distance of each point [P, >=3] to the surface region of its own box [P, >=7]. -> [P].

    Zero inside the box; otherwise the 3D distance to the nearest point of the box.
    """
    rel = points[:, :3].astype(np.float64) - boxes[:, :3]
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
    half = np.stack([boxes[:, 4], boxes[:, 3], boxes[:, 5]], 1) / 2
    return np.linalg.norm(np.maximum(np.abs(local) - half, 0.0), axis=1)


def sensor_stats(n_frames: int = 50) -> str:
    """Markdown tables of the statistics over the first `n_frames` validation scenes."""
    scenes = [make_scene(seed) for seed in SPLITS["val"][:n_frames]]
    rows = ["| sensor | points / frame (mean, p5-p95) | GT points / frame | GT boxes with 0 points "
            "| ms / frame | " + " | ".join(f"err {a:.0f}-{b:.0f} m" for a, b in BANDS) + " |",
            "|---" * (5 + len(BANDS)) + "|"]
    per_class: dict[str, list[float]] = {}
    for sensor in SENSORS:
        render(scenes[0], sensor)  # warm-up
        start = time.perf_counter()
        frames = [render(scene, sensor) for scene in scenes]
        ms = (time.perf_counter() - start) / n_frames * 1e3
        n_pts = np.array([len(f.points) for f in frames])
        gt_pts = np.mean([f.gt_num_points.sum() for f in frames])
        zero = np.mean(np.concatenate([f.gt_num_points == 0 for f in frames]))
        errs: list[list[np.ndarray]] = [[] for _ in BANDS]
        counts = np.zeros(len(CLASSES))
        n_obj = np.zeros(len(CLASSES))
        for scene, frame in zip(scenes, frames, strict=True):
            own = frame.point_owner
            boxes = scene.boxes.astype(np.float64)[np.maximum(own, 0)]
            err = box_error(frame.points, boxes)
            rng_xy = np.hypot(boxes[:, 0], boxes[:, 1])
            for i, (a, b) in enumerate(BANDS):
                errs[i].append(err[(own >= 0) & (rng_xy >= a) & (rng_xy < b)])
            np.add.at(counts, scene.labels, frame.gt_num_points)
            np.add.at(n_obj, scene.labels, 1)
        band = [np.concatenate(e) for e in errs]
        cells = " | ".join(f"{e.mean():.2f}" if len(e) else "-" for e in band)
        rows.append(f"| {sensor} | {n_pts.mean():.0f} ({np.percentile(n_pts, 5):.0f}-"
                    f"{np.percentile(n_pts, 95):.0f}) | {gt_pts:.0f} | {zero:.0%} | {ms:.1f} | "
                    f"{cells} |")
        per_class[sensor] = list(counts / np.maximum(n_obj, 1))
    rows += ["", "Mean points per ground-truth box, by class:", "",
             "| class | " + " | ".join(SENSORS) + " |", "|---" * (1 + len(SENSORS)) + "|"]
    for k, name in enumerate(CLASSES):
        rows.append(f"| {name} | " + " | ".join(f"{per_class[s][k]:.1f}" for s in SENSORS) + " |")
    return "\n".join(rows)


if __name__ == "__main__":
    print(sensor_stats(int(sys.argv[1]) if len(sys.argv) > 1 else 50))
