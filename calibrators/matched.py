"""A dump matched to its ground truth, and the arrays that follow: the public dump-level API.

`match_dump` (nuScenes matching of the final layer), `tp_residuals` (matched ground truth −
box of the true positives), `raw_covariances` (Σ of every detection from a covariance
source), `resolve_cov_source` and `check_dims`; plus what a fit needs (`ts_labels`,
`ts_logits`, `select_detections`, `split_frames`). Every caller — the fit, the summary, the
CLI, the service and the detectors' report — goes through these, so a rule lives once.

All functions take a validated `Dump` (N detections, G ground-truth boxes, F frames) and use
its final decoder layer.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from calibrators.covariance import source_covariance
from calibrators.defaults import MATCH_THRESHOLD
from calibrators.detections import source_arrays
from calibrators.dump import Dump
from calibrators.matching import MatchResult, match
from calibrators.options import OptionError
from calibrators.scores import modulate_logits
from calibrators.vocab import BOX_INDEX, COV_SOURCE_CHOICES, check_dims, wrap_angle

__all__ = ["canonical_order", "check_dims", "held_out_frames", "match_dump", "raw_covariances",
           "resolve_cov_source", "select_detections", "split_frames", "tp_residuals",
           "ts_labels", "ts_logits"]


def resolve_cov_source(dump: Dump, cov_source: str, dims: tuple[str, ...]) -> str:
    """The covariance source to use: `given`, `layers`, `hypotheses` or `none`.

    `auto` is `given` when the dump carries `det_cov` over exactly `dims`, else `layers` when
    it has at least two decoder layers, else `none`. `auto` never picks `hypotheses`: it is
    asked for by name (a dump fit with `auto` keeps the source it had before the hypothesis
    arrays existed, and `other_sources` fits a `hypotheses` stage beside it anyway). An
    explicit source the dump cannot provide raises an `OptionError` naming `cov_source`.
    """
    if cov_source not in COV_SOURCE_CHOICES:
        raise OptionError("cov_source", f"cov_source must be one of {list(COV_SOURCE_CHOICES)}, "
                                        f"got {cov_source!r}")
    if cov_source == "auto":
        if dump.det_cov is not None and dump.cov_dims == dims:
            return "given"
        return "layers" if dump.n_layers >= 2 else "none"
    if cov_source == "given":
        if dump.det_cov is None:
            raise OptionError("cov_source", "cov_source='given' but the dump has no det_cov")
        if dump.cov_dims != dims:
            raise OptionError("cov_source", f"cov_source='given' needs the dump's cov_dims "
                                            f"{list(dump.cov_dims)} to equal dims {list(dims)}")
    if cov_source == "layers" and dump.n_layers < 2:
        raise OptionError("cov_source", f"cov_source='layers' needs at least 2 decoder "
                                        f"layers, the dump has {dump.n_layers}")
    if cov_source == "hypotheses" and dump.n_hypotheses == 0:
        raise OptionError("cov_source", "cov_source='hypotheses' needs the dump's box "
                                        "hypotheses (det_hyp_boxes [N, H, 9] and "
                                        "det_hyp_scores [N, H], from group regression "
                                        "heads); the dump has none")
    return cov_source


def raw_covariances(dump: Dump, source: str, dims: tuple[str, ...]) -> np.ndarray | None:
    """`[N, D, D]` uncalibrated covariance of every detection from `source`, or None (`none`):
    `source_covariance` of the dump's `source_arrays`, as a served call computes it."""
    return source_covariance(source, dims, **source_arrays(dump, source))


def match_dump(dump: Dump, threshold: float = MATCH_THRESHOLD) -> MatchResult:
    """nuScenes matching of the final-layer detections to the ground truth at `threshold` m.

    No class range filter: a profile must calibrate every detection the detector emits,
    and the far ones carry most of the depth signal (see `fit_profile`).
    """
    return match(dump.det_frame, dump.det_labels, dump.det_scores, dump.final_boxes[:, :2],
                 dump.gt_frame, dump.gt_labels, dump.gt_boxes[:, :2], threshold=threshold)


def ts_labels(dump: Dump, tp: np.ndarray) -> np.ndarray:
    """`[N]` temperature-scaling labels from the TP mask `[N]`.

    sigmoid: 1 for a TP of its predicted class, else 0. softmax: the target column, i.e. the
    class of the matched ground truth (= the predicted class, matching is per class) for a TP,
    else the no-object column C.
    """
    tp = np.asarray(tp, dtype=bool)
    if dump.score_mode == "sigmoid":
        return tp.astype(np.int64)
    return np.where(tp, dump.det_labels, len(dump.classes)).astype(np.int64)


def ts_logits(dump: Dump, modulation: bool = False) -> np.ndarray:
    """The logits temperature scaling is fit on: the final layer's `[N, C']`.

    With `modulation`, the modulated final-layer logits (`modulate_logits` over all layers).
    Modulation may move the arg-max, so in sigmoid mode only the column of the detector's
    label (raw arg-max, the class that was matched) is returned, `[N, 1]`: that is the logit
    `CalibrationProfile.calibrate` will score, and the one whose TP label `ts_labels` gives.
    Softmax labels name their target column, so all `C + 1` columns are returned.
    """
    if not modulation:
        if dump.det_label is not None and dump.score_mode == "sigmoid":
            # Given labels need not be the arg-max: the fit must see the label's logit.
            return dump.det_logits[np.arange(dump.n_detections), -1, dump.det_label][:, None]
        return dump.det_logits[:, -1]
    if dump.n_layers < 2:
        raise ValueError(f"modulation needs at least 2 decoder layers, the dump has "
                         f"{dump.n_layers}")
    z = modulate_logits(dump.det_logits)
    if dump.score_mode == "sigmoid":
        return z[np.arange(len(z)), dump.det_labels][:, None]
    return z


def tp_residuals(dump: Dump, matched: MatchResult,
                 dims: str | Sequence[str] = ("x", "y")) -> np.ndarray:
    """`[M, D]` residuals (matched ground truth − final box) over `dims` of the M TPs of
    `matched` (a `match_dump` of this dump), in detection order.

    A yaw residual is wrapped to (−π, π].
    """
    cols = [BOX_INDEX[d] for d in check_dims(dims)]
    tp = np.asarray(matched.tp, dtype=bool)
    res = dump.gt_boxes[np.asarray(matched.gt_index)[tp]][:, cols] - dump.final_boxes[tp][:, cols]
    for j, c in enumerate(cols):
        if c == BOX_INDEX["yaw"]:
            res[:, j] = wrap_angle(res[:, j])
    return res


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
