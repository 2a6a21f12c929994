"""A physically plausible synthetic validation dump with known miscalibration (numpy only).

Used by the tests, the benchmarks and the service's demos. The generator knows the truth the
calibrators should recover:

- **temperature**: every detection has a *calibrated* logit `u` of its predicted class; whether
  it is a true positive is drawn with probability `p(u)` (sigmoid, or the softmax column of the
  class), and the detector emits `T · u`, i.e. it is overconfident by `T`. Fitting a
  temperature on the emitted logits against the TP labels recovers `T`.
- **depth k**: a true positive's centre is its ground-truth centre plus Gaussian noise of
  covariance `Σ_i + k_c · d_i · I` (over x, y; `d_i` its BEV distance from the ego), where
  `Σ_i` is the small covariance the detector reports (`det_cov`, overconfident). Fitting depth
  scaling with `cov_source="given"` recovers `k_c`.
- **layers**: earlier decoder layers deviate more from the final box (and their spread grows
  with distance), so the spread across layers is a usable covariance source.
- **hypotheses** (`n_hypotheses = H > 0`): every detection gets H box hypotheses with group
  scores; the top-scoring one is the final box, the others lie around it with the detection's
  true position noise `Σ_i + k_c · d_i · I`, so their group-score-weighted spread is a usable
  covariance source. They are drawn after everything else: a dump's other arrays do not
  depend on `n_hypotheses`.

True positives are copies of ground-truth boxes; false positives are placed at least
`_FP_CLEARANCE` m from every ground-truth box of their frame, so the nuScenes matching at 2 m
labels them as intended (up to the rare TP whose noise exceeds the threshold).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from calibrators.core.vocab import SCORE_MODES, wrap_angle
from calibrators.data._dump import Dump
from calibrators.scores import class_probabilities

CLASSES10 = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
             "motorcycle", "bicycle", "traffic_cone", "barrier")

# Ground-truth k per class (m² of position variance per metre of distance): larger for big,
# hard-to-localise vehicles, small for cones and pedestrians. Kept small enough that almost
# every TP lands within the 2 m matching threshold even at 60 m.
DEFAULT_DEPTH_K: dict[str, float] = {
    "car": 0.004, "truck": 0.008, "bus": 0.010, "trailer": 0.010,
    "construction_vehicle": 0.008, "pedestrian": 0.002, "motorcycle": 0.004,
    "bicycle": 0.003, "traffic_cone": 0.001, "barrier": 0.002,
}

# (w, l, h, z-centre, relative frequency, moving) per known class; unknown names get a car.
_SHAPES: dict[str, tuple[float, float, float, float, float, bool]] = {
    "car": (1.9, 4.6, 1.7, 0.9, 0.35, True),
    "truck": (2.5, 7.0, 3.0, 1.5, 0.08, True),
    "bus": (2.9, 11.0, 3.5, 1.8, 0.03, True),
    "trailer": (2.4, 10.0, 3.8, 1.9, 0.03, True),
    "construction_vehicle": (2.8, 6.5, 3.2, 1.6, 0.03, False),
    "pedestrian": (0.7, 0.7, 1.8, 0.9, 0.18, True),
    "motorcycle": (0.8, 2.1, 1.5, 0.75, 0.04, True),
    "bicycle": (0.6, 1.8, 1.3, 0.65, 0.04, True),
    "traffic_cone": (0.4, 0.4, 1.0, 0.5, 0.1, False),
    "barrier": (2.5, 0.5, 1.0, 0.5, 0.12, False),
}
_RANGE = (2.0, 60.0)        # BEV distance of ground truth from the ego, m
_FP_CLEARANCE = 4.0         # false positives keep at least this far from any ground truth, m
_DETECT_PROB = 0.9          # chance that a ground-truth object is detected at all
_LOGIT_MEAN, _LOGIT_STD = -0.5, 2.0   # calibrated logit distribution of candidates


def synthetic_dump(n_frames: int = 50, n_gt_per_frame: int = 20,
                   classes: Sequence[str] = CLASSES10, score_mode: str = "sigmoid",
                   n_layers: int = 3, temperature: float = 2.0,
                   depth_k: Mapping[str, float] | None = None, seed: int = 0,
                   with_cov: bool = True, n_hypotheses: int = 0) -> Dump:
    """A `Dump` of `n_frames` ego-frame frames with known temperature and per-class k.

    `depth_k` maps class name -> true k (classes absent from it take 0.004); default
    `DEFAULT_DEPTH_K`. Expect about `0.9 · n_frames · n_gt_per_frame` true positives and
    about 1.4 times as many false positives. `det_cov` (`[N, 2, 2]` over x, y) is the small,
    overconfident covariance the detector reports, present when `with_cov`.
    `n_hypotheses`: H box hypotheses per detection (`det_hyp_boxes [N, H, 9]`,
    `det_hyp_scores [N, H]`; module docstring), none when 0.
    """
    classes = tuple(str(c) for c in classes)
    _check_args(n_frames, n_gt_per_frame, classes, score_mode, n_layers, temperature)
    n_hypotheses = _checked_n_hypotheses(n_hypotheses)
    k_true = _checked_depth_k(depth_k)
    rng = np.random.default_rng(seed)
    shapes, freq, moving, ks = _class_table(classes, k_true)

    gt_frame, gt_labels, gt_boxes = _ground_truth(rng, n_frames, n_gt_per_frame, shapes,
                                                  freq / freq.sum(), moving)
    det_frame, det_labels, final, cov, rows = _detections(
        rng, n_frames, score_mode, shapes, freq, moving, ks, (gt_frame, gt_labels, gt_boxes))
    logits = _emitted_logits(rng, rows, n_layers, temperature)
    layer_boxes = _layer_boxes(rng, final, ks[det_labels], n_layers)
    hyp_boxes = hyp_scores = None
    if n_hypotheses:
        noise = _position_noise(final, cov, ks[det_labels])
        hyp_boxes, hyp_scores = _hypotheses(rng, final, noise, n_hypotheses)
    return Dump(
        classes=classes, score_mode=score_mode,
        frame_ids=np.array([f"synth-{seed}-{i:05d}" for i in range(n_frames)]),
        det_frame=det_frame, det_logits=logits, det_boxes=layer_boxes,
        gt_frame=gt_frame, gt_labels=gt_labels, gt_boxes=gt_boxes,
        det_cov=cov if with_cov else None, cov_dims=("x", "y"),
        det_hyp_boxes=hyp_boxes, det_hyp_scores=hyp_scores,
    )


def _checked_n_hypotheses(n_hypotheses: int) -> int:
    if isinstance(n_hypotheses, bool) or int(n_hypotheses) != n_hypotheses or n_hypotheses < 0:
        raise ValueError(f"n_hypotheses must be an integer >= 0, got {n_hypotheses!r}")
    return int(n_hypotheses)


def _checked_depth_k(depth_k: Mapping[str, float] | None) -> dict[str, float]:
    """The true k per class name (default `DEFAULT_DEPTH_K`), each finite and >= 0."""
    k_true = dict(DEFAULT_DEPTH_K if depth_k is None else depth_k)
    for name, k in k_true.items():
        if not np.isfinite(k) or k < 0:
            raise ValueError(f"depth_k[{name!r}] must be a finite number >= 0, got {k}")
    return k_true


def _class_table(classes: tuple[str, ...], k_true: Mapping[str, float]
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per class: shape `[C, 4]` (w, l, h, z-centre), relative frequency, moving, true k."""
    shapes = np.array([_SHAPES.get(c, _SHAPES["car"])[:4] for c in classes])   # [C, 4]
    freq = np.array([_SHAPES.get(c, _SHAPES["car"])[4] for c in classes])
    moving = np.array([_SHAPES.get(c, _SHAPES["car"])[5] for c in classes])
    ks = np.array([float(k_true.get(c, 0.004)) for c in classes])
    return shapes, freq, moving, ks


def _detections(rng: np.random.Generator, n_frames: int, score_mode: str, shapes: np.ndarray,
                freq: np.ndarray, moving: np.ndarray, ks: np.ndarray,
                gt: tuple[np.ndarray, np.ndarray, np.ndarray]) -> tuple[np.ndarray, ...]:
    """`det_frame [N]`, labels `[N]`, final boxes `[N, 9]`, reported covariances
    `[N, 2, 2]` and calibrated logit rows `[N, C']` of the TPs (detected ground truth) and
    FPs, shuffled within frames."""
    gt_frame, gt_labels, gt_boxes = gt
    detected = np.flatnonzero(rng.random(len(gt_labels)) < _DETECT_PROB)
    u_tp, u_fp = _calibrated_logits(rng, len(detected), score_mode, len(freq))
    n_fp = len(u_fp)
    fp_frame = rng.integers(0, n_frames, n_fp)
    fp_labels = rng.choice(len(freq), n_fp, p=freq / freq.sum())

    tp_boxes, tp_cov = _true_positive_boxes(rng, gt_boxes[detected], ks[gt_labels[detected]])
    fp_boxes, fp_cov = _false_positive_boxes(rng, fp_frame, fp_labels, shapes, moving,
                                             gt_frame, gt_boxes)
    det_frame = np.concatenate([gt_frame[detected], fp_frame])
    det_labels = np.concatenate([gt_labels[detected], fp_labels])
    final = np.concatenate([tp_boxes, fp_boxes])
    cov = np.concatenate([tp_cov, fp_cov])
    rows = _place_label(np.concatenate([u_tp, u_fp]), det_labels)
    order = np.lexsort((rng.random(len(det_frame)), det_frame))   # shuffle within frames
    return tuple(a[order] for a in (det_frame, det_labels, final, cov, rows))


def _position_noise(final: np.ndarray, cov: np.ndarray, k: np.ndarray) -> np.ndarray:
    """`[N, 2, 2]` a detection's true position noise `Σ_i + k_c · d_i · I`."""
    d = np.hypot(final[:, 0], final[:, 1])
    return cov + (k * d)[:, None, None] * np.eye(2)


def _check_args(n_frames: int, n_gt: int, classes: tuple[str, ...], score_mode: str,
                n_layers: int, temperature: float) -> None:
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if int(n_gt) < 1:
        raise ValueError(f"n_gt_per_frame must be >= 1, got {n_gt}")
    if not classes:
        raise ValueError("classes must name at least one class")
    if score_mode not in SCORE_MODES:
        raise ValueError(f"score_mode must be one of {list(SCORE_MODES)}, got {score_mode!r}")
    if int(n_layers) < 1:
        raise ValueError(f"n_layers must be >= 1, got {n_layers}")
    if not np.isfinite(temperature) or temperature <= 0:
        raise ValueError(f"temperature must be a finite number > 0, got {temperature}")


def _ground_truth(rng: np.random.Generator, n_frames: int, n_gt: int, shapes: np.ndarray,
                  freq: np.ndarray, moving: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`gt_frame [G]`, `gt_labels [G]`, `gt_boxes [G, 9]` with G = n_frames · n_gt."""
    g = n_frames * n_gt
    frame = np.repeat(np.arange(n_frames), n_gt)
    labels = rng.choice(len(freq), g, p=freq)
    # Uniform over the annulus area, so far objects are as common as on a real road.
    lo, hi = _RANGE
    r = np.sqrt(rng.uniform(lo * lo, hi * hi, g))
    phi = rng.uniform(-np.pi, np.pi, g)
    size = shapes[labels, :3] * rng.normal(1.0, 0.05, (g, 3))
    z = shapes[labels, 3] + rng.normal(0.0, 0.1, g)
    yaw = rng.uniform(-np.pi, np.pi, g)
    speed = np.where(moving[labels], np.abs(rng.normal(0.0, 4.0, g)), 0.0)
    boxes = np.column_stack([r * np.cos(phi), r * np.sin(phi), z, size, yaw,
                             speed * np.cos(yaw), speed * np.sin(yaw)])
    return frame, labels.astype(np.int64), boxes


def _calibrated_logits(rng: np.random.Generator, n_tp: int, score_mode: str, n_cls: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Calibrated logit rows `[n_tp, C']` of the TPs and `[n_fp, C']` of the FPs.

    The predicted class sits in column 0 (moved to the real label by `_place_label`), with
    logit `u ~ N(mean, std)`; the other object classes are `gap` below it (softmax: no-object
    at 0 and gaps >= 10, so a detection is almost surely its label or no-object). Candidates are
    labelled TP with the calibrated probability of column 0 until `n_tp` TPs are drawn; the
    failures on the way are the FPs, so P(TP | row) = p(row) holds exactly.
    """
    tp_parts: list[np.ndarray] = []
    fp_parts: list[np.ndarray] = []
    need = n_tp
    while need > 0:
        m = max(4 * need, 64)
        u = rng.normal(_LOGIT_MEAN, _LOGIT_STD, m)
        if score_mode == "softmax":
            gap = 10.0 + rng.exponential(2.0, (m, n_cls + 1))
        else:
            gap = 0.5 + rng.exponential(2.0, (m, n_cls))
        rows = u[:, None] - gap
        rows[:, 0] = u
        if score_mode == "softmax":
            rows[:, -1] = 0.0
        is_tp = rng.random(m) < class_probabilities(rows, score_mode)[:, 0]
        if int(is_tp.sum()) >= need:   # stop exactly at the need-th success
            cut = int(np.flatnonzero(is_tp)[need - 1]) + 1
            rows, is_tp = rows[:cut], is_tp[:cut]
        tp_parts.append(rows[is_tp])
        fp_parts.append(rows[~is_tp])
        need -= int(is_tp.sum())
    width = n_cls + (1 if score_mode == "softmax" else 0)
    empty = np.zeros((0, width))
    return np.concatenate(tp_parts or [empty]), np.concatenate(fp_parts or [empty])


def _place_label(rows: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Swap column 0 of each row `[N, C']` with the row's label column."""
    out = rows.copy()
    i = np.arange(len(rows))
    out[i, 0], out[i, labels] = rows[i, labels], rows[i, 0]
    return out


def _emitted_logits(rng: np.random.Generator, rows: np.ndarray, n_layers: int,
                    temperature: float) -> np.ndarray:
    """`[N, L, C']` logits the detector emits: `T ·` calibrated, noisier in earlier layers."""
    final = temperature * rows
    layers = np.empty((len(rows), n_layers, rows.shape[1]))
    for layer in range(n_layers):
        scale = 0.5 * (n_layers - 1 - layer) / max(n_layers - 1, 1)
        layers[:, layer] = final + rng.normal(0.0, 1.0, final.shape) * scale
    layers[:, -1] = final
    return layers


def _true_positive_boxes(rng: np.random.Generator, gt: np.ndarray, k: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Final boxes `[M, 9]` and reported covariances `[M, 2, 2]` of true positives."""
    d = np.hypot(gt[:, 0], gt[:, 1])
    cov = _reported_cov(rng, d)
    full = cov + (k * d)[:, None, None] * np.eye(2)
    noise = np.einsum("nij,nj->ni", np.linalg.cholesky(full), rng.standard_normal((len(gt), 2)))
    boxes = gt.copy()
    boxes[:, :2] += noise
    boxes[:, 2] += rng.normal(0.0, 0.1, len(gt))
    boxes[:, 3:6] *= rng.normal(1.0, 0.05, (len(gt), 3))
    boxes[:, 6] = wrap_angle(boxes[:, 6] + rng.normal(0.0, 0.1, len(gt)))
    boxes[:, 7:9] += rng.normal(0.0, 0.3, (len(gt), 2))
    return boxes, cov


def _false_positive_boxes(rng: np.random.Generator, frame: np.ndarray, labels: np.ndarray,
                          shapes: np.ndarray, moving: np.ndarray, gt_frame: np.ndarray,
                          gt_boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Boxes `[M, 9]` and covariances `[M, 2, 2]` of false positives clear of all GT."""
    m = len(frame)
    xy = np.zeros((m, 2))
    todo = np.arange(m)
    lo, hi = _RANGE
    while len(todo):
        r = np.sqrt(rng.uniform(lo * lo, hi * hi, len(todo)))
        phi = rng.uniform(-np.pi, np.pi, len(todo))
        xy[todo] = np.column_stack([r * np.cos(phi), r * np.sin(phi)])
        clear = np.array([_clear(xy[i], gt_boxes[gt_frame == frame[i], :2]) for i in todo],
                         dtype=bool)
        todo = todo[~clear]
    size = shapes[labels, :3] * rng.normal(1.0, 0.1, (m, 3))
    yaw = rng.uniform(-np.pi, np.pi, m)
    speed = np.where(moving[labels], np.abs(rng.normal(0.0, 4.0, m)), 0.0)
    boxes = np.column_stack([xy, shapes[labels, 3] + rng.normal(0.0, 0.2, m), size, yaw,
                             speed * np.cos(yaw), speed * np.sin(yaw)])
    return boxes, _reported_cov(rng, np.hypot(xy[:, 0], xy[:, 1]))


def _clear(xy: np.ndarray, others: np.ndarray) -> bool:
    return bool(len(others) == 0 or np.min(np.hypot(*(others - xy).T)) >= _FP_CLEARANCE)


def _reported_cov(rng: np.random.Generator, d: np.ndarray) -> np.ndarray:
    """`[M, 2, 2]` small rotated covariances growing mildly with distance (overconfident)."""
    m = len(d)
    var = rng.uniform(0.002, 0.02, (m, 2)) * (1.0 + d / 30.0)[:, None]
    angle = rng.uniform(-np.pi, np.pi, m)
    c, s = np.cos(angle), np.sin(angle)
    rot = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)     # [M, 2, 2]
    cov = np.einsum("nij,nj,nkj->nik", rot, var, rot)
    return 0.5 * (cov + np.swapaxes(cov, 1, 2))


def _layer_boxes(rng: np.random.Generator, final: np.ndarray, k: np.ndarray, n_layers: int
                 ) -> np.ndarray:
    """`[N, L, 9]` per-layer boxes converging to `final` (layer L-1 is `final` itself)."""
    n = len(final)
    d = np.hypot(final[:, 0], final[:, 1])
    xy_std = 0.05 + 0.7 * np.sqrt(np.maximum(k, 1e-4) * d)              # [N]
    field_std = np.array([1.0, 1.0, 0.1, 0.05, 0.1, 0.05, 0.05, 0.2, 0.2])
    out = np.empty((n, n_layers, 9))
    for layer in range(n_layers):
        scale = (n_layers - 1 - layer) / max(n_layers - 1, 1)
        noise = rng.standard_normal((n, 9)) * field_std
        noise[:, :2] *= xy_std[:, None]
        noise[:, 3:6] *= final[:, 3:6]
        out[:, layer] = final + scale * noise
    out[:, :, 6] = wrap_angle(out[:, :, 6])
    out[:, -1] = final
    return out


def _hypotheses(rng: np.random.Generator, final: np.ndarray, noise: np.ndarray, n_hyp: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """`[N, H, 9]` box hypotheses and `[N, H]` group scores: the detection's own group (a
    random one) scores highest and its hypothesis is `final [N, 9]`; the others lie around it
    in x, y with covariance `noise [N, 2, 2]`."""
    n = len(final)
    rows = np.arange(n)
    scores = rng.uniform(0.05, 1.0, (n, n_hyp))
    own = rng.integers(0, n_hyp, n)
    scores[rows, own] += 1.0
    boxes = np.repeat(final[:, None], n_hyp, axis=1)
    step = np.einsum("nij,nhj->nhi", np.linalg.cholesky(noise),
                     rng.standard_normal((n, n_hyp, 2)))
    boxes[:, :, :2] += step
    boxes[rows, own] = final
    return boxes, scores
