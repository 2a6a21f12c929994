"""Turn validated request detections into library arrays, calibrate, and build response rows.

Detections of one request may mix evidence forms (logits, per-class scores, one score +
label) and uncertainty forms (covariance, layer boxes, none); they are grouped by form,
each group goes through `CalibrationProfile.calibrate` once, and the rows come back in
request order. Mismatches with the profile are `RequestError`s naming the field path.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from app.cache import LoadedProfile
from app.errors import RequestError
from app.schemas.calibrate import DetectionIn, FrameIn

_EPS = 1e-12
_SOURCE_TEXT = {"layers": "the spread of layer_boxes", "none": "depth alone (no input covariance)"}


@dataclass
class _Group:
    """Arrays of detections that share one evidence/uncertainty form."""

    index: list[int] = field(default_factory=list)
    evidence: list = field(default_factory=list)   # logits rows, [L, C'] layer logits, or [score]
    labels: list[int] = field(default_factory=list)
    boxes: list[list[float]] = field(default_factory=list)
    covariances: list[list[list[float]]] = field(default_factory=list)
    layer_boxes: list[list[list[float]]] = field(default_factory=list)
    ego_xy: list[list[float]] = field(default_factory=list)


def _mismatch(loc: Sequence[str | int], msg: str) -> RequestError:
    return RequestError(loc, msg, kind="value_error.profile_mismatch")


def _label_index(label: str | int, classes: Sequence[str], loc: list[str | int]) -> int:
    if isinstance(label, int):
        if label >= len(classes):
            raise _mismatch(loc, f"label index {label} is out of range for the profile's "
                                 f"{len(classes)} classes")
        return label
    try:
        return list(classes).index(label)
    except ValueError:
        raise _mismatch(loc, f"unknown class {label!r}; the profile's classes are "
                             f"{list(classes)}") from None


def _scores_to_logits(scores: list[float], mode: str) -> list[float]:
    p = np.clip(np.asarray(scores, dtype=np.float64), _EPS, 1.0 - _EPS)
    z = np.log(p) - np.log1p(-p) if mode == "sigmoid" else np.log(p)
    return z.tolist()


def _box9(box: list[float]) -> list[float]:
    return box if len(box) == 9 else [*box, 0.0, 0.0]


Locate = Callable[[int, int], list[str | int]]


def _default_locate(fi: int, di: int) -> list[str | int]:
    return ["body", "frames", fi, "detections", di]


def calibrate_frames(loaded: LoadedProfile, frames: Sequence[FrameIn],
                     confidence: float, locate: Locate = _default_locate,
                     ) -> list[list[dict[str, object]]]:
    """Calibrated detection rows (response dicts) per frame, in request order.

    `locate(frame_index, detection_index)` gives the field path used in error messages.
    """
    prof = loaded.profile
    classes = list(prof.classes)
    width = len(classes) + (1 if prof.score_mode == "softmax" else 0)
    groups: dict[tuple[str, bool, int, int], _Group] = defaultdict(_Group)
    flat: list[DetectionIn] = []
    frame_of: list[int] = []
    for fi, frame in enumerate(frames):
        ego = (frame.ego_translation or [0.0, 0.0, 0.0])[:2]
        for di, det in enumerate(frame.detections):
            here = locate(fi, di)
            key, g_row = _prepare(det, here, classes, width, tuple(prof.cov_dims),
                                  prof.cov_source, prof.score_mode, loaded.record.ref,
                                  prof.modulation)
            g = groups[key]
            g.index.append(len(flat))
            g.evidence.append(g_row[0])
            g.labels.append(g_row[1])
            g.boxes.append(g_row[2])
            if det.covariance is not None:
                g.covariances.append(det.covariance)
            if key[2]:
                g.layer_boxes.append(det.layer_boxes or [])
            g.ego_xy.append(ego)
            flat.append(det)
            frame_of.append(fi)

    rows: list[dict[str, object] | None] = [None] * len(flat)
    for (kind, has_cov, n_layers, _), g in groups.items():
        _run_group(loaded, kind, has_cov, n_layers, g, confidence, flat, rows)
    out: list[list[dict[str, object]]] = [[] for _ in frames]
    for i, row in enumerate(rows):
        out[frame_of[i]].append(row)  # type: ignore[arg-type]
    return out


def _prepare(det: DetectionIn, loc: list[str | int], classes: list[str], width: int,
             cov_dims: tuple[str, ...], cov_source: str, mode: str, ref: str,
             modulation: bool = False,
             ) -> tuple[tuple[str, bool, int, int], tuple[list, int, list[float]]]:
    """Group key and `(evidence, label, box)` of one detection, checked against the profile.

    A profile with logits modulation needs every decoder layer's logits: its evidence is the
    `[L, C']` layer logits, and detections are grouped by L as well.
    """
    n_dims = len(cov_dims)
    n_logit_layers = 0
    if modulation:
        layers = det.layer_logits
        if det.score is not None or layers is None or len(layers) < 2:
            raise _mismatch([*loc, "layer_logits"],
                            f"profile {ref} modulates logits by their variance across decoder "
                            "layers: give layer_logits with at least 2 layers")
        bad = next((i for i, row in enumerate(layers) if len(row) != width), None)
        if bad is not None:
            raise _mismatch([*loc, "layer_logits", bad],
                            f"layer_logits[{bad}] has {len(layers[bad])} columns but profile "
                            f"{ref} ({mode}, {len(classes)} classes) needs {width}")
        kind, label, evidence, n_logit_layers = "logits", -1, layers, len(layers)
    elif det.score is not None:
        kind, evidence = "score", [det.score]
        label = _label_index(det.label, classes, [*loc, "label"])  # type: ignore[arg-type]
    else:
        kind, label = "logits", -1
        if det.logits is not None:
            evidence, field_name = det.logits, "logits"
        elif det.layer_logits is not None:
            evidence, field_name = det.layer_logits[-1], "layer_logits"
        else:
            evidence, field_name = _scores_to_logits(det.scores or [], mode), "scores"
        got = len(evidence)
        if got != width:
            raise _mismatch([*loc, field_name],
                            f"{field_name} has {got} columns but profile {ref} ({mode}, "
                            f"{len(classes)} classes) needs {width}")
    n_layers = 0
    if cov_source == "given":
        if det.covariance is None:
            raise _mismatch([*loc, "covariance"],
                            f"profile {ref} was fit on given covariances (cov_source 'given'): "
                            f"give a {n_dims}x{n_dims} covariance over {list(cov_dims)}")
        if len(det.covariance) != n_dims:
            raise _mismatch([*loc, "covariance"],
                            f"covariance is {len(det.covariance)}x{len(det.covariance)} but "
                            f"profile {ref} has cov_dims {list(cov_dims)} ({n_dims}x{n_dims})")
    elif det.covariance is not None:
        raise _mismatch([*loc, "covariance"],
                        f"profile {ref} takes its covariance from {_SOURCE_TEXT[cov_source]} "
                        f"(cov_source {cov_source!r}), so its k does not apply to a given "
                        "covariance: leave covariance out")
    elif cov_source == "layers":
        if det.layer_boxes is None or len(det.layer_boxes) < 2:
            raise _mismatch([*loc, "layer_boxes"],
                            f"profile {ref} takes box covariance from the spread across decoder "
                            "layers (cov_source 'layers'): give layer_boxes with at least 2 "
                            "layers")
        n_layers = len(det.layer_boxes)
    box = _box9(det.box) if det.box is not None else det.layer_boxes[-1]  # type: ignore[index]
    return (kind, det.covariance is not None, n_layers, n_logit_layers), (evidence, label, box)


def _run_group(loaded: LoadedProfile, kind: str, has_cov: bool, n_layers: int, g: _Group,
               confidence: float, flat: list[DetectionIn], rows: list[dict[str, object] | None]
               ) -> None:
    prof = loaded.profile
    kwargs: dict[str, object] = {
        "boxes": np.asarray(g.boxes, dtype=np.float64),
        "ego_xy": np.asarray(g.ego_xy, dtype=np.float64),
        "ellipse_confidence": confidence,
    }
    if kind == "score":
        kwargs["scores"] = np.asarray(g.evidence, dtype=np.float64)[:, 0]
        kwargs["labels"] = np.asarray(g.labels, dtype=np.int64)
    else:
        evidence = np.asarray(g.evidence, dtype=np.float64)
        # [N, L, C'] layer logits of a modulating profile, else final-layer logits [N, C']
        kwargs["layer_logits" if evidence.ndim == 3 else "logits"] = evidence
    if has_cov:
        kwargs["covariances"] = np.asarray(g.covariances, dtype=np.float64)
    if n_layers:
        kwargs["layer_boxes"] = np.asarray(g.layer_boxes, dtype=np.float64)
    try:
        res = prof.calibrate(**kwargs)  # type: ignore[arg-type]
    except ValueError as exc:
        raise _mismatch(["body"], f"profile {loaded.record.ref}: {exc}") from None
    classes = prof.classes
    labels = res.labels.tolist()
    scores = res.scores.tolist()
    raw = res.scores_raw.tolist()
    cls_scores = res.class_scores.tolist() if res.class_scores is not None else None
    covs = res.covariances.tolist()
    el = res.ellipses
    if el is not None:
        major, minor, angle = el.semi_major.tolist(), el.semi_minor.tolist(), el.angle.tolist()
    dist = res.distances.tolist()
    for j, i in enumerate(g.index):
        rows[i] = {
            "id": flat[i].id,
            "label": classes[labels[j]],
            "label_index": labels[j],
            "score": scores[j],
            "score_raw": raw[j],
            "class_scores": None if cls_scores is None else cls_scores[j],
            "box": g.boxes[j],
            "covariance": covs[j],
            "ellipse": None if el is None else {
                "semi_major": major[j], "semi_minor": minor[j], "angle": angle[j],
                "confidence": confidence},
            "distance": dist[j],
        }
