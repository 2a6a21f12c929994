"""Bird's-eye-view picture of one simulated frame: points, ground truth, detections, ellipses.

Detections above `min_score` are drawn as boxes labelled with class and score, with the
95 % ellipse of their (x, y) covariance (spread across decoder layers by default). With a
`CalibrationProfile`, the profile's calibrated scores and covariances are drawn instead.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from calibrators.core.checks import check_choice
from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from detectors.infer import detect
from detectors.model.detector import Detector
from detectors.panels import pyplot
from detectors.panels.bev import BevStyle, bev_panel
from detectors.uncertainty import attention_spread, layer_covariance
from detectors.vocab import DETECTOR_COV_SOURCES

#: `detcal show`'s bird's-eye view: points coloured by height, grey dashed ground truth,
#: red detections and text, orange ellipses.
SHOW_BEV = BevStyle(point_color=None, point_size=(1.0, 4.0), point_alpha=0.6, gt_color="0.35",
                    box_width=1.2, label_dy=1.0, label_colored=True)


def render_frame(model: Detector, seed: int, out: str | Path, min_score: float = 0.3,
                 cov_source: str = "layers", profile: object | None = None,
                 confidence: float = ELLIPSE_CONFIDENCE, extent: float | None = None) -> Path:
    """Draw scene `seed` as seen by `model`'s sensor into the PNG `out`; `cov_source` is
    one of `detectors.vocab.DETECTOR_COV_SOURCES`."""
    from calibrators import ellipse
    from detectors.sim import CLASSES, make_frame

    check_choice("cov_source", cov_source, DETECTOR_COV_SOURCES)
    frame = make_frame(int(seed), model.config.sensor)
    points = np.array(frame.sensor_frame.points, dtype=np.float32)
    (det,) = list(detect(model, [torch.from_numpy(points)], max_detections=model.config.n_queries,
                         decode="query"))
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

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(9, 9), dpi=110)
    texts = [f"{CLASSES[label]} {score:.2f}" for label, score in zip(labels[keep], scores[keep],
                                                                     strict=True)]
    bev_panel(ax, points, np.asarray(frame.scene.boxes, dtype=np.float64).reshape(-1, 9),
              boxes[keep], texts, ell, color="tab:red", ellipse_color="tab:orange",
              half=extent or model.grid.half_extent, style=SHOW_BEV)
    ax.set_title(f"{title}; grey dashed: ground truth, red: score >= {min_score}, "
                 f"orange: {int(confidence * 100)} % ellipse", fontsize=8)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
