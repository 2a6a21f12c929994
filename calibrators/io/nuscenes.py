"""nuScenes results JSON + ground-truth JSON (`DetectionBox` form) <-> `Dump`.

Both files are `{"meta": {...}, "results": {sample_token: [box, ...]}}`. A box has the devkit's
fields: sample_token, translation [3], size [3] (w, l, h), rotation [4] (quaternion w, x, y, z),
velocity [2], ego_translation [3] (the box centre minus the ego position, as the devkit's
`add_center_dist` sets it), num_pts, detection_name, detection_score, attribute_name; plus our
optional extensions `detection_logits` [C'], `covariance` [D][D], `detection_score_raw` and
`ellipses` (written by `calibrators.io.nuscenes_batch.calibrated_document`, see `ellipses_json`).
docs/formats.md has the full description and the conventions.
"""

from __future__ import annotations

import json
import os
import re
import reprlib
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from scipy.special import logit

from calibrators.core.checks import as_float_array, check_probabilities
from calibrators.core.vocab import SCORE_MODES
from calibrators.data import Dump
from calibrators.io.nuscenes_batch import quaternion_yaw
from calibrators.scores import probability_logit

if TYPE_CHECKING:
    pass

NUSCENES_CLASSES = ("car", "truck", "bus", "trailer", "construction_vehicle", "pedestrian",
                    "motorcycle", "bicycle", "traffic_cone", "barrier")
EGO_TOLERANCE = 0.01  # metres: boxes of one frame must agree on the ego position to this
OTHER_CLASS_PROB = 1e-6  # probability given to the other classes when only a score is known
_SHORT = reprlib.Repr()  # values in messages: 2 levels, 4 items, 40 characters
_SHORT.maxlevel, _SHORT.maxlist, _SHORT.maxdict, _SHORT.maxstring = 2, 4, 4, 40
#: Largest results / ground-truth file `load_nuscenes` parses (bytes); `max_bytes=` changes it.
MAX_JSON_BYTES = 512 * 2**20
#: Deepest nesting of arrays and objects accepted (a results document with ellipses has 6).
MAX_DEPTH = 32


def load_nuscenes(results_path: str | os.PathLike[str],
                  gt_path: str | os.PathLike[str] | None = None,
                  classes: Sequence[str] | None = None, *,
                  max_bytes: int | None = None) -> Dump:
    """Read a results JSON and, optionally, its ground-truth JSON into a `Dump` (L = 1 layer).

    `classes` defaults to meta["classes"] of the results file, else the 10 nuScenes classes.
    Ground-truth boxes with `num_pts == 0` are dropped (the devkit never evaluates them).
    Without `gt_path` the dump has no ground truth (G = 0) and its frames are the results
    file's sample tokens: enough to calibrate detections, not to fit or evaluate.

    A file larger than `max_bytes` (default `MAX_JSON_BYTES`, 512 MiB), or nested deeper than
    `MAX_DEPTH` arrays/objects, is refused before it is parsed. Every error is a ValueError
    naming the file and the key path (`meta.classes`, `results['tok'][3].num_pts`); messages
    never show the file's path.
    """
    results, meta = _read(results_path, "results", max_bytes)
    classes = _classes(meta) if classes is None else tuple(str(c) for c in classes)
    tokens = list(results)
    if gt_path is None:
        gt: dict = {token: [] for token in tokens}
    else:
        gt = _read(gt_path, "ground truth", max_bytes)[0]
        _check_same_tokens(results, gt)
    det = _parse(results, tokens, classes, "results", prediction=True)
    ref = _parse(gt, tokens, classes, "ground truth", prediction=False)
    keep = ref["num_pts"] != 0

    cov_dims = _class_list("meta.cov_dims", meta["cov_dims"]) if "cov_dims" in meta \
        else ("x", "y")
    logits, score_mode, det_label = _logits(det, classes, meta)
    return Dump(
        classes=classes, score_mode=score_mode, frame_ids=np.array(tokens, dtype=str),
        ego_translation=_ego(det, ref, tokens),
        det_frame=det["frame"], det_logits=logits[:, None, :], det_boxes=det["boxes"][:, None, :],
        det_cov=_covariances(det, len(cov_dims)), cov_dims=cov_dims, det_label=det_label,
        gt_frame=ref["frame"][keep], gt_labels=ref["label"][keep], gt_boxes=ref["boxes"][keep])


def _read(path: str | os.PathLike[str], what: str, max_bytes: int | None
          ) -> tuple[dict, dict]:
    """(results, meta) of a file, refused by size and nesting depth before it is parsed."""
    max_bytes = MAX_JSON_BYTES if max_bytes is None else max_bytes
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes <= 0:
        raise ValueError(f"max_bytes must be a positive integer, got {max_bytes!r}")
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            data = b"" if size > max_bytes else fh.read(max_bytes + 1)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise ValueError(f"{what} file cannot be read: {exc.strerror or exc}") from None
    if size > max_bytes or len(data) > max_bytes:
        raise ValueError(f"{what} file is larger than the limit of {max_bytes} bytes")
    depth = _depth(data)
    if depth > MAX_DEPTH:
        raise ValueError(f"{what} file nests arrays/objects {depth} deep; at most {MAX_DEPTH} "
                         "levels are accepted")
    try:
        content = json.loads(data)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{what} file is not valid JSON: {exc}") from None
    except (ValueError, RecursionError) as exc:  # bad UTF-8, an int over 4300 digits
        raise ValueError(f"{what} file is not valid JSON: {exc}") from None
    if not isinstance(content, dict) or not isinstance(content.get("results"), dict):
        raise ValueError(f"{what} file must be an object with a 'results' object mapping "
                         "sample tokens to lists of boxes")
    meta = content.get("meta", {})
    if not isinstance(meta, dict):
        raise ValueError(f"{what} 'meta' must be an object, got {_kind(meta)}")
    return content["results"], meta


_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')
_BRACKETS = bytes.maketrans(b"[{]}", b"(())")
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


def _depth(data: bytes) -> int:
    """Nesting depth of arrays and objects in JSON text, up to MAX_DEPTH + 1, without
    recursion: strings are dropped, brackets kept, and innermost pairs peeled once per level
    (all in C: a few passes over the brackets of a well-formed document)."""
    nest = _STRING.sub(b"", data).translate(_BRACKETS, _NOT_BRACKETS)
    depth = 0
    while nest and depth <= MAX_DEPTH:
        peeled = nest.replace(b"()", b"")
        if len(peeled) == len(nest):  # unbalanced: the JSON parser says where
            break
        nest, depth = peeled, depth + 1
    return depth


def _kind(value: object) -> str:
    """A short description of a JSON value for messages (never the whole value)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return f"the boolean {str(value).lower()}"
    if isinstance(value, int | float | str):
        return _SHORT.repr(value)
    return f"an {'array' if isinstance(value, list) else 'object'} {_SHORT.repr(value)}"


def _class_list(key: str, value: object) -> tuple[str, ...]:
    """A non-empty list of strings (class names or cov_dims), or a ValueError naming `key`."""
    if isinstance(value, str) or not isinstance(value, Sequence) or not value \
            or not all(isinstance(v, str) for v in value):
        raise ValueError(f"{key} must be a non-empty list of strings, got {_kind(value)}")
    return tuple(value)


def _classes(meta: dict) -> tuple[str, ...]:
    """meta.classes, or the 10 nuScenes classes when the key is absent."""
    if "classes" not in meta:
        return NUSCENES_CLASSES
    return _class_list("meta.classes", meta["classes"])


def _check_same_tokens(results: dict, gt: dict) -> None:
    for a, b, name_a, name_b in ((gt, results, "ground truth", "results"),
                                 (results, gt, "results", "ground truth")):
        extra = [t for t in a if t not in b]
        if extra:
            raise ValueError(f"{name_a} has {len(extra)} sample token(s) that {name_b} lacks, "
                             f"e.g. {extra[0]!r}; both files must cover the same samples")


def _parse(boxes: dict, tokens: list[str], classes: tuple[str, ...], what: str,
           prediction: bool) -> dict[str, np.ndarray | list]:
    """Columns of every box, frame by frame in `tokens` order, in file order within a frame."""
    index = {c: k for k, c in enumerate(classes)}
    frame, label, rows, score, ego_rel, logits, cov, num_pts = [], [], [], [], [], [], [], []
    for f, token in enumerate(tokens):
        items = boxes[token]
        if not isinstance(items, list):
            raise ValueError(f"{what}[{token!r}] must be a list of boxes")
        for i, box in enumerate(items):
            where = f"{what}[{token!r}][{i}]"
            if not isinstance(box, dict):
                raise ValueError(f"{where} must be an object")
            if box.get("sample_token", token) != token:
                raise ValueError(f"{where}.sample_token is {_kind(box['sample_token'])}, not "
                                 f"{token!r}")
            name = box.get("detection_name")
            if not isinstance(name, str) or name not in index:
                raise ValueError(f"{where}.detection_name must be one of {list(classes)}, "
                                 f"got {_kind(name)}")
            t = _vector(box, "translation", 3, where)
            size = _vector(box, "size", 3, where)
            yaw = _yaw(_vector(box, "rotation", 4, where), where)
            vel = _vector(box, "velocity", 2, where)
            rows.append([*t, *size, yaw, *vel])
            frame.append(f)
            label.append(index[name])
            rel = box.get("ego_translation")
            rel = None if rel is None else _vector(box, "ego_translation", 3, where)
            ego_rel.append(None if rel is None or not np.any(rel) else rel)
            num_pts.append(_num_pts(box, where))
            if prediction:
                score.append(_vector(box, "detection_score", 0, where))
                logits.append(box.get("detection_logits"))
                cov.append(box.get("covariance"))
    return {"frame": np.array(frame, dtype=np.int64), "label": np.array(label, dtype=np.int64),
            "boxes": np.array(rows, dtype=float).reshape(-1, 9), "score": np.array(score),
            "ego_rel": ego_rel, "logits": logits, "cov": cov,
            "num_pts": np.array(num_pts, dtype=np.int64), "what": what}


def _vector(box: dict, key: str, n: int, where: str) -> np.ndarray:
    """`n` numbers (`n = 0`: one number) at `box[key]`: JSON numbers only, finite."""
    if key not in box:
        raise ValueError(f"{where} is missing {key!r}")
    raw = box[key]
    items = raw if n and isinstance(raw, list) else [raw]
    if (len(items) != max(n, 1) or (n and not isinstance(raw, list))
            or not all(_is_number(v) for v in items)):
        want = f"{n} numbers" if n else "a number"
        raise ValueError(f"{where}.{key} must be {want}, got {_kind(raw)}")
    value = np.array(items if n else items[0], dtype=float)
    if not np.all(np.isfinite(value)):
        raise ValueError(f"{where}.{key} has NaN or Inf: {_kind(raw)}")
    return value


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _num_pts(box: dict, where: str) -> int:
    """num_pts as an int (-1 when absent): a whole, finite JSON number."""
    value = box.get("num_pts", -1)
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if not isinstance(value, int) or isinstance(value, bool) or not -2**62 < value < 2**62:
        raise ValueError(f"{where}.num_pts must be a whole number (lidar points in the box), "
                         f"got {_kind(value)}")
    return value


def _yaw(q: np.ndarray, where: str) -> float:
    """Yaw about +z of quaternion (w, x, y, z), as the devkit's quaternion_yaw."""
    try:
        return quaternion_yaw(*(float(v) for v in q))
    except ValueError as exc:
        raise ValueError(f"{where}.{exc}") from None


def _ego(det: dict, ref: dict, tokens: list[str]) -> np.ndarray | None:
    """`[F, 3]` ego position per frame from translation - ego_translation; None = ego frame."""
    n_frames = len(tokens)
    estimates: list[list[np.ndarray]] = [[] for _ in range(n_frames)]
    given = False
    for part in (det, ref):
        for k, rel in enumerate(part["ego_rel"]):
            if rel is not None:
                given = True
                estimates[part["frame"][k]].append(part["boxes"][k, :3] - rel)
    if not given:
        return None
    ego = np.zeros((n_frames, 3))
    has_box = np.zeros(n_frames, dtype=bool)
    has_box[det["frame"]] = True
    has_box[ref["frame"]] = True
    for f, est in enumerate(estimates):
        if not est:
            if has_box[f]:
                raise ValueError(f"sample {tokens[f]!r} has boxes but none with an "
                                 "ego_translation, so its ego position is unknown")
            continue
        est_arr = np.array(est)
        spread = float(np.max(np.linalg.norm(est_arr - est_arr[0], axis=1)))
        if spread > EGO_TOLERANCE:
            raise ValueError(f"boxes of sample {tokens[f]!r} disagree on the ego position "
                             f"(translation - ego_translation) by {spread:.3g} m > "
                             f"{EGO_TOLERANCE} m")
        ego[f] = est_arr.mean(axis=0)
    return None if not ego.any() else ego


def _logits(det: dict, classes: tuple[str, ...], meta: dict
            ) -> tuple[np.ndarray, str, np.ndarray | None]:
    """`[N, C']` logits, the score mode and the labels when a detection_name is not the
    arg-max of its detection_logits (a top-K (query, class) decoder: one query, several
    boxes of different classes), from detection_logits or from the scores."""
    n, c = len(det["label"]), len(classes)
    given = [v is not None for v in det["logits"]]
    if any(given) and not all(given):
        raise ValueError(f"results box {given.index(False)} lacks detection_logits while others "
                         "have them; give them for every box or for none")
    if not any(given):
        if _score_mode(meta, "sigmoid") != "sigmoid":
            raise ValueError("meta.score_mode is softmax but the boxes have no detection_logits")
        scores = det["score"].reshape(-1)
        check_probabilities("detection_score", scores)
        z = probability_logit(scores)
        out = np.minimum(logit(OTHER_CLASS_PROB), z - 1.0)[:, None] * np.ones((n, c))
        out[np.arange(n), det["label"]] = z
        return out, "sigmoid", None
    logits = as_float_array("detection_logits", det["logits"], ndim=2)
    mode = _score_mode(meta, "sigmoid" if logits.shape[1] == c else "softmax")
    want = c + (mode == "softmax")
    if logits.shape[1] != want:
        raise ValueError(f"detection_logits have {logits.shape[1]} entries but {mode} mode with "
                         f"{c} classes needs {want}")
    labels = np.asarray(det["label"], dtype=np.int64)
    given = None if np.array_equal(np.argmax(logits[:, :c], axis=1), labels) else labels
    return logits, mode, given


def _score_mode(meta: dict, default: str) -> str:
    mode = meta.get("score_mode", default)
    if mode not in SCORE_MODES:
        raise ValueError(f"meta.score_mode must be one of {list(SCORE_MODES)}, got {_kind(mode)}")
    return mode


def _covariances(det: dict, d: int) -> np.ndarray | None:
    given = [v is not None for v in det["cov"]]
    if not any(given):
        return None
    if not all(given):
        raise ValueError(f"results box {given.index(False)} lacks a covariance while others "
                         "have one; give it for every box or for none")
    cov = as_float_array("covariance", det["cov"], ndim=3)
    if cov.shape[1:] != (d, d):
        raise ValueError(f"covariance must be {d}x{d} (meta.cov_dims), got {cov.shape[1:]}")
    return cov


# -- writing ----------------------------------------------------------------------------------


