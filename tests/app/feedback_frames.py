"""Request bodies of labelled feedback built from a `Dump` (shared by the app and e2e tests)."""

from __future__ import annotations

import io
from typing import Any

import numpy as np

from calibrators import Dump


def feedback_frames(dump: Dump, cov: bool = True) -> list[dict[str, Any]]:
    """Every frame of `dump` as a feedback frame: final logits and box (and det_cov, the
    given label and the box hypotheses) of each detection, every ground-truth box with its
    class name."""
    frames = []
    for f, frame_id in enumerate(dump.frame_ids.tolist()):
        dets = []
        for i in np.flatnonzero(dump.det_frame == f):
            det: dict[str, Any] = {"id": int(i), "logits": dump.det_logits[i, -1].tolist(),
                                   "box": dump.det_boxes[i, -1].tolist()}
            if cov and dump.det_cov is not None:
                det["covariance"] = dump.det_cov[i].tolist()
            if dump.det_label is not None:
                det["label"] = dump.classes[int(dump.det_label[i])]
            if dump.det_hyp_boxes is not None:
                det["hypothesis_boxes"] = dump.det_hyp_boxes[i].tolist()
                det["hypothesis_scores"] = dump.det_hyp_scores[i].tolist()
            dets.append(det)
        gts = [{"label": dump.classes[int(dump.gt_labels[g])], "box": dump.gt_boxes[g].tolist()}
               for g in np.flatnonzero(dump.gt_frame == f)]
        frames.append({"frame_id": str(frame_id), "detections": dets, "ground_truth": gts})
    return frames


def npz_bytes(dump: Dump) -> bytes:
    """`dump` as validation dump v1 bytes."""
    from calibrators.io import save_dump

    buf = io.BytesIO()
    save_dump(buf, dump)
    return buf.getvalue()
