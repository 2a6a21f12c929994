"""Bird's-eye-view picture of one simulated frame: points, ground truth, detections, ellipses.

Detections above `min_score` are drawn as boxes labelled with class and score, with the
95 % ellipse of their (x, y) covariance (spread across decoder layers by default). With a
`CalibrationProfile`, the profile's calibrated scores and covariances are drawn instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from detectors.bevplot import add_ellipse, finish_bev_axes
from detectors.infer import detect
from detectors.model.detector import Detector
from detectors.sim.geometry import bev_outline
from detectors.uncertainty import attention_spread, layer_covariance


def render_frame(model: Detector, seed: int, out: str | Path, min_score: float = 0.3,
                 cov_source: str = "layers", profile: object | None = None,
                 confidence: float = 0.95, extent: float | None = None) -> Path:
    """Draw scene `seed` as seen by `model`'s sensor into the PNG `out`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calibrators import ellipse
    from detectors.sim import CLASSES, make_frame

    frame = make_frame(int(seed), model.config.sensor)
    points = np.array(frame.sensor_frame.points, dtype=np.float32)
    (det,) = list(detect(model, [torch.from_numpy(points)], max_detections=model.config.n_queries))
    boxes = det.boxes.numpy().astype(np.float64)
    if cov_source == "attention":
        cov = attention_spread(det.attention.double(), model.token_centres.double()).covariance
        cov = (cov + torch.eye(2, dtype=torch.float64) * model.token_grid.cell ** 2 / 12).numpy()
    else:
        cov = layer_covariance(det.layer_boxes.double()).numpy()
    scores, labels = det.scores.numpy().astype(np.float64), det.labels.numpy()
    title = f"{model.config.sensor}, scene {seed}: raw scores, {cov_source} covariance"
    if profile is not None:
        # Each profile takes its input covariance from the source it was fit on.
        source = {"given": {"covariances": cov},
                  "layers": {"layer_boxes": det.layer_boxes.numpy().astype(np.float64)},
                  "none": {}}[profile.cov_source]
        logits = ({"layer_logits": det.layer_logits.numpy()} if profile.modulation
                  else {"logits": det.layer_logits[:, -1].numpy()})
        cal = profile.calibrate(boxes=boxes, **logits, **source)
        scores, labels, cov = cal.scores, cal.labels, cal.covariances
        title = f"{model.config.sensor}, scene {seed}: calibrated (profile)"
    keep = scores >= min_score
    ell = ellipse(cov[keep][:, :2, :2], confidence=confidence) if keep.any() else None

    half = extent or model.grid.half_extent
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    colour = points[:, 2] if points.shape[1] > 2 else None
    ax.scatter(points[:, 0], points[:, 1], s=1.0 if len(points) > 5000 else 4.0, c=colour,
               cmap="viridis", alpha=0.6,
               linewidths=0)
    for box in np.asarray(frame.scene.boxes, dtype=np.float64).reshape(-1, 9):
        xy = bev_outline(box)
        ax.plot(xy[:, 0], xy[:, 1], color="0.35", lw=1.0, ls="--")
    names = [CLASSES[i] for i in labels[keep]]
    for j, (box, score, name) in enumerate(zip(boxes[keep], scores[keep], names, strict=True)):
        xy = bev_outline(box)
        ax.plot(xy[:, 0], xy[:, 1], color="tab:red", lw=1.2)
        ax.text(box[0], box[1] + 1.0, f"{name} {score:.2f}", fontsize=5, color="tab:red",
                ha="center")
        if ell is not None:
            add_ellipse(ax, box[0], box[1], ell, j, "tab:orange")
    finish_bev_axes(ax, half)
    ax.set_title(f"{title}; grey dashed: ground truth, red: score >= {min_score}, "
                 f"orange: {int(confidence * 100)} % ellipse", fontsize=8)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
