"""Calibrate a nuScenes results document: boxes -> detections (score + class name), and back.

Each box keeps every key it came with; `detection_score` becomes the calibrated score and
the box gains `detection_score_raw`, `covariance` (calibrated, over the profile's dims),
`ellipse` and `ellipses` (one per requested level, as in POST /v1/calibrate). With
`detection_logits`, the label is their arg-max (as the dump formats define). The document
gains a top-level `calibration` key naming the profile version. Keys the devkit does not know
are ignored by it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from app.cache import LoadedProfile
from app.calibration import calibrate_frames
from app.errors import RequestError
from app.schemas.calibrate import DetectionIn, FrameIn
from app.schemas.nuscenes import NuScenesBox, NuScenesResults
from calibrators.vocab import quaternion_yaw


def box_to_detection(box: NuScenesBox, loc: Sequence[str | int]) -> DetectionIn:
    """A detection from one `DetectionBox`: its logits if it has `detection_logits`, else its
    score and class name. The centre is taken relative to the ego (`ego_translation`) so the
    distance is right; covariances and ellipses do not depend on where the centre is.

    `loc` is the box's field path, named by the 422 of a rotation that has no yaw.
    """
    try:
        yaw = quaternion_yaw(*box.rotation)
    except ValueError as exc:
        raise RequestError([*loc, "rotation"], str(exc)) from None
    rel = box.ego_translation
    centre = rel if rel is not None and any(rel) else box.translation   # zeros: unset
    logits = box.detection_logits
    return DetectionIn.model_construct(
        id=None, logits=logits, layer_logits=None, scores=None,
        score=None if logits is not None else box.detection_score,
        label=None if logits is not None else box.detection_name,
        box=[*centre, *box.size, yaw, *box.velocity], layer_boxes=None,
        covariance=box.covariance, hypothesis_boxes=None, hypothesis_scores=None)


def calibrate_results(loaded: LoadedProfile, doc: NuScenesResults, confidence: float,
                      levels: Sequence[float], max_detections: int | None = None
                      ) -> tuple[dict[str, Any], int]:
    """The calibrated results document and the number of boxes calibrated (`levels`: the
    query's, checked by `calibrate_frames`)."""
    tokens = list(doc.results)

    def locate(fi: int, di: int) -> list[str | int]:
        return ["body", "results", tokens[fi], di]

    frames = [FrameIn.model_construct(
        frame_id=t, ego_translation=None,
        detections=[box_to_detection(b, locate(fi, di)) for di, b in enumerate(doc.results[t])])
        for fi, t in enumerate(tokens)]
    rows = calibrate_frames(loaded, frames, confidence, locate=locate, levels=levels,
                            options_in="query", max_detections=max_detections)
    n = 0
    results: dict[str, list[dict[str, Any]]] = {}
    for token, frame_rows in zip(tokens, rows, strict=True):
        out = []
        for box, row in zip(doc.results[token], frame_rows, strict=True):
            item = box.model_dump(exclude_none=True)
            item["detection_name"] = row["label"]
            item["detection_score"] = row["score"]
            item["detection_score_raw"] = row["score_raw"]
            item["covariance"] = row["covariance"]
            item["ellipse"] = row["ellipse"]
            item["ellipses"] = row["ellipses"]
            out.append(item)
        n += len(out)
        results[token] = out
    body = doc.model_dump(exclude={"results"})
    body["results"] = results
    body["calibration"] = {"profile": loaded.ref(), "ellipse_confidence": confidence}
    return body, n
