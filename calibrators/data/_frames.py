"""Frame-level selection of a dump: detections by mask, a seeded hold-out of frames by token,
and a canonical frame / detection order (so a fit is free of input order)."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import numpy as np

from calibrators.data._dump import Dump


def select_detections(dump: Dump, keep: np.ndarray) -> Dump:
    """A dump with only the detections where the boolean `[N]` mask `keep` is True."""
    return dump.select_detections(keep)



def split_frames(dump: Dump, holdout: float, seed: int) -> tuple[Dump, Dump | None]:
    """(fit part, held-out part or None): a seeded random `holdout` fraction of the frames,
    drawn by frame token (`held_out_frames`), so the same frames whatever their order.

    At least one frame is held out when `holdout > 0`; at least one must remain to fit on.
    """
    if holdout <= 0:
        return dump, None
    held = held_out_frames(dump.frame_ids, holdout, seed)
    return dump.select_frames(~held), dump.select_frames(held)



def held_out_frames(frame_ids: np.ndarray, holdout: float, seed: int) -> np.ndarray:
    """`[F]` bool: the frames of tokens `frame_ids [F]` that `split_frames` holds out (a
    streamed fit picks the same ones): the `round(holdout · F)` frames whose seeded token hash
    is smallest, so a frame's side depends on its token and the seed, never on where it sits.
    At least one when `holdout > 0`; at least one must remain to fit on."""
    n_frames = len(frame_ids)
    held = np.zeros(n_frames, dtype=bool)
    if holdout <= 0:
        return held
    n_hold = max(1, int(round(holdout * n_frames)))
    if n_hold >= n_frames:
        raise ValueError(f"holdout={holdout} leaves no frame to fit on ({n_frames} frames)")
    keys = [hashlib.blake2b(f"{int(seed)}:{token}".encode(), digest_size=8).digest()
            + str(token).encode() for token in np.asarray(frame_ids).tolist()]
    held[sorted(range(n_frames), key=keys.__getitem__)[:n_hold]] = True
    return held



def canonical_order(dump: Dump) -> Dump:
    """`dump` with its frames sorted by token and, within a frame, its detections and
    ground-truth boxes sorted by their values: the same dump whatever order its frames and
    detections came in (a fit on it is then order-free, float sums included)."""
    frames = np.argsort(np.asarray(dump.frame_ids).astype(str), kind="stable")
    new_of_old = np.argsort(frames)
    det_frame, gt_frame = new_of_old[dump.det_frame], new_of_old[dump.gt_frame]
    det_keys = [dump.det_boxes.reshape(dump.n_detections, -1),
                dump.det_logits.reshape(dump.n_detections, -1)]
    det_keys += [a.reshape(dump.n_detections, -1) for a in
                 (dump.det_cov, dump.det_hyp_boxes, dump.det_hyp_scores, dump.det_label)
                 if a is not None]
    det = np.lexsort([*np.concatenate(det_keys, axis=1).T[::-1], det_frame])
    gt = np.lexsort([*dump.gt_boxes.T[::-1], dump.gt_labels, gt_frame])

    def take(arr: np.ndarray | None) -> np.ndarray | None:
        return None if arr is None else arr[det]

    ego = dump.ego_translation
    return replace(dump, frame_ids=dump.frame_ids[frames], det_frame=det_frame[det],
                   det_logits=dump.det_logits[det], det_boxes=dump.det_boxes[det],
                   det_cov=take(dump.det_cov), det_hyp_boxes=take(dump.det_hyp_boxes),
                   det_hyp_scores=take(dump.det_hyp_scores), det_label=take(dump.det_label),
                   gt_frame=gt_frame[gt], gt_labels=dump.gt_labels[gt],
                   gt_boxes=dump.gt_boxes[gt],
                   ego_translation=None if ego is None else ego[frames])
