"""The bundled detectors behind POST /v1/detect and the dashboard's bird's-eye view.

`detectors` (torch) is imported lazily: without it, or without shipped weights, the service
still runs and /v1/detect answers 503 saying why.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.http.errors import RequestError
from app.schemas.calibrate import DetectionIn


class DetectorUnavailable(RuntimeError):
    """The detectors package or a detector's weights are not installed."""


@dataclass(frozen=True)
class DetectorOutput:
    """Raw outputs of one frame: the top (query, class) pairs kept by raw score
    (`detectors.infer`, "topk" decoding: a query may give detections of several classes).

    layer_logits [N, L, C], layer_boxes [N, L, 9] (the detection's query), labels [N] (the
    class each detection asserts), points [P, F] (the input cloud), gt_boxes [G, 9] and
    gt_labels [G] (empty for uploaded points), classes [C]; a detector with group regression
    heads adds hyp_boxes [N, H, 9] and hyp_scores [N, H] (None otherwise).
    """

    layer_logits: np.ndarray
    layer_boxes: np.ndarray
    points: np.ndarray
    gt_boxes: np.ndarray
    gt_labels: np.ndarray
    classes: tuple[str, ...]
    labels: np.ndarray
    hyp_boxes: np.ndarray | None = None
    hyp_scores: np.ndarray | None = None


class DetectorService:
    """Loads each sensor's detector once and runs it on simulated or uploaded points."""

    def __init__(self) -> None:
        self._models: dict[str, Any] = {}
        self._lock = threading.Lock()

    def available(self) -> str | None:
        """None when detectors can run, else the reason they cannot."""
        try:
            import detectors  # noqa: F401
            from detectors import build_detector  # noqa: F401
            from detectors.sim import make_frame  # noqa: F401
        except ImportError as exc:
            return f"the detectors package is not available ({exc})"
        return None

    def _model(self, sensor: str) -> Any:
        with self._lock:
            if sensor in self._models:
                return self._models[sensor]
            try:
                import torch

                from detectors import build_detector
                from detectors.vocab import SENSORS
            except ImportError as exc:
                raise DetectorUnavailable(f"the detectors package is not available ({exc})"
                                          ) from None
            if sensor not in SENSORS:
                raise RequestError(["body", "sensor"], f"sensor must be one of {list(SENSORS)}, "
                                                       f"got {sensor!r}")
            torch.set_num_threads(max(1, min(2, torch.get_num_threads())))
            try:
                model = build_detector(sensor)
            except FileNotFoundError as exc:
                raise DetectorUnavailable(str(exc)) from None
            self._models[sensor] = model
            return model

    def run(self, sensor: str, seed: int | None = None, points: list[list[float]] | None = None,
            min_score: float = 0.3) -> DetectorOutput:
        """Detect on the simulated frame `seed` of `sensor` (or on `points`): the top 100
        queries by final-layer score (as the dumps keep), then those with score >= min_score."""
        model = self._model(sensor)
        import torch

        from detectors.infer import detect
        from detectors.sim import FEATURES, make_frame

        if points is None:
            frame = make_frame(0 if seed is None else seed, sensor)
            cloud = np.array(frame.sensor_frame.points, dtype=np.float32)   # writable copy
            gt_boxes = np.asarray(frame.scene.boxes, dtype=np.float64).reshape(-1, 9)
            gt_labels = np.asarray(frame.scene.labels, dtype=np.int64)
        else:
            cloud = np.array(points, dtype=np.float32)
            n_feat = len(FEATURES[sensor])
            if cloud.shape[1] != n_feat:
                raise RequestError(["body", "points"],
                                   f"points must have {n_feat} columns {list(FEATURES[sensor])} "
                                   f"for sensor {sensor!r}, got {cloud.shape[1]}")
            gt_boxes, gt_labels = np.zeros((0, 9)), np.zeros(0, dtype=np.int64)
        (det,) = list(detect(model, [torch.from_numpy(cloud)], max_detections=100))
        logits = det.layer_logits.double().numpy()     # [K, L, C], sorted by score
        boxes = det.layer_boxes.double().numpy()       # [K, L, 9]
        keep = det.scores.numpy() >= min_score
        return DetectorOutput(layer_logits=logits[keep], layer_boxes=boxes[keep], points=cloud,
                              gt_boxes=gt_boxes, gt_labels=gt_labels,
                              classes=tuple(model.config.classes),
                              labels=det.labels.numpy()[keep],
                              hyp_boxes=None if det.hyp_boxes is None
                              else det.hyp_boxes.double().numpy()[keep],
                              hyp_scores=None if det.hyp_scores is None
                              else det.hyp_scores.double().numpy()[keep])


def detections_of(out: DetectorOutput, loaded: LoadedProfile) -> list[DetectionIn]:
    """Request-shaped detections (per-layer logits and boxes, the label, and the box
    hypotheses of a group-head detector) from raw detector outputs."""
    prof = loaded.profile
    if tuple(prof.classes) != out.classes:
        raise RequestError(["body", "profile"],
                           f"profile {loaded.record.ref} is for classes {list(prof.classes)} but "
                           f"the detector predicts {list(out.classes)}")
    covs = None
    if prof.cov_source == "given" and len(out.layer_logits):
        from calibrators.covariance import layer_spread

        covs = layer_spread(out.layer_boxes, dims=tuple(prof.cov_dims)).tolist()
    logits, boxes = out.layer_logits.tolist(), out.layer_boxes.tolist()
    labels = out.labels.tolist()
    hyp_boxes = None if out.hyp_boxes is None else out.hyp_boxes.tolist()
    hyp_scores = None if out.hyp_scores is None else out.hyp_scores.tolist()
    return [DetectionIn.model_construct(
        id=i, logits=None, layer_logits=logits[i], scores=None, score=None, label=labels[i],
        box=boxes[i][-1], layer_boxes=boxes[i], covariance=None if covs is None else covs[i],
        hypothesis_boxes=None if hyp_boxes is None else hyp_boxes[i],
        hypothesis_scores=None if hyp_scores is None else hyp_scores[i])
        for i in range(len(logits))]
