"""OpenPCDet `result.pkl` (and its dataset's infos pickle as ground truth) -> `Dump`.

`result.pkl` is what OpenPCDet's `tools/test.py` saves: a list with one dict per frame, from
the dataset's `generate_prediction_dicts`:

    name         [N] str       class name (the model config's CLASS_NAMES)
    score        [N] float     detection score (a probability)
    boxes_lidar  [N, 7 | 9]    x y z dx dy dz heading [vx vy], lidar frame, z = box centre,
                               dx along the heading (length), dy across (width), dz height
    pred_labels  [N] int       optional (nuScenes, Waymo): 1-based index into CLASS_NAMES
    frame_id     str           the frame (KITTI `000123`)
    metadata     {"token"}     optional (nuScenes): the sample token, used as the frame token
    bbox         [N, 4]        optional (KITTI): 2D image box, for the DontCare rule

The ground truth, when given, is the dataset's infos pickle (`kitti_infos_val.pkl`,
`nuscenes_infos_10sweeps_val.pkl`): per frame either `annos` (KITTI, Waymo: `name`,
`gt_boxes_lidar` for the non-DontCare names, `bbox`) or `gt_boxes` / `gt_names` /
`num_lidar_pts` (nuScenes). Both pickles are read by `pickle_safe.load_restricted`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence

import numpy as np

from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io.kitti_ignore import DONTCARE_OVERLAP, NEIGHBOURS, ignored_detections
from calibrators.io.pickle_safe import load_restricted
from calibrators.io.reader_files import ByteBudget, check_file
from calibrators.io.reader_rows import Rows, class_list, rows_to_dump

#: Most detections (and ground-truth boxes) one load reads.
MAX_ROWS = 50_000_000


def load_openpcdet(path: str | os.PathLike[str],
                   ground_truth: str | os.PathLike[str] | None = None, *,
                   classes: Sequence[str], class_map: Mapping[str, str] | None = None,
                   threshold: float = MATCH_THRESHOLD, max_bytes: int | None = None) -> Dump:
    """Read an OpenPCDet `result.pkl` (and optionally its infos pickle) into a `Dump`.

    `classes` is the model config's CLASS_NAMES in order (`pred_labels` are checked against
    it); `class_map` renames them onto other classes. Ground-truth names outside the classes
    are not read; with KITTI infos, KITTI's DontCare and neighbouring-class rules apply
    (`kitti_ignore`). At most `max_bytes` (default 2 GiB) are read. Errors are FieldErrors
    naming the file, the frame entry and the key.
    """
    classes, index = class_list(classes, class_map)
    budget = ByteBudget(max_bytes)
    res = check_file(path, "result.pkl")
    entries = _entries(load_restricted(budget.read(res, res.name), res.name), res.name)
    det, det_bbox, det_names = _predictions(entries, res.name, classes, index)
    frames = np.array([_token(e, f"{res.name}[{i}]") for i, e in enumerate(entries)], dtype=str)
    if ground_truth is None:
        return rows_to_dump(classes, det, None, frames=frames, source=res.name)
    info = check_file(ground_truth, "infos")
    infos = _entries(load_restricted(budget.read(info, info.name), info.name), info.name)
    gt, neighbour, dc = _truth(infos, info.name, set(frames.tolist()), index)
    keep = np.ones(len(det.labels), dtype=bool)
    if np.any(neighbour) or (len(dc[0]) and det_bbox is not None):
        keep = ~_kitti_ignored(det, det_bbox, det_names, gt, neighbour, dc, threshold)
    real = ~neighbour
    return rows_to_dump(classes, Rows(det.frames[keep], det.labels[keep], det.boxes[keep],
                                      scores=det.scores[keep]),  # type: ignore[index]
                        Rows(gt.frames[real], gt.labels[real], gt.boxes[real]), frames=frames,
                        source=res.name)


def _entries(content: object, name: str) -> list[dict]:
    if not isinstance(content, list | tuple) or not all(isinstance(e, dict) for e in content):
        raise FieldError("pickle", f"{name}: must be a list of dicts (one per frame), got "
                                   f"{type(content).__name__}")
    return list(content)


def _token(entry: dict, where: str) -> str:
    """The frame token: metadata.token, token, frame_id or point_cloud.lidar_idx."""
    meta = entry.get("metadata")
    for value in ((meta or {}).get("token") if isinstance(meta, dict) else None,
                  entry.get("token"), entry.get("frame_id"),
                  (entry.get("point_cloud") or {}).get("lidar_idx")
                  if isinstance(entry.get("point_cloud"), dict) else None):
        if isinstance(value, str | bytes | int | np.integer | np.str_) \
                and not isinstance(value, bool):
            return value.decode() if isinstance(value, bytes) else str(value)
    raise FieldError("frame_id", f"{where}: has no frame_id (nor metadata.token) naming its "
                                 "frame")


def _array(entry: dict, key: str, where: str, shape: tuple[int | None, ...],
           kind: str = "f") -> np.ndarray:
    """entry[key] as an array of `shape` (None: any size) and kind (f float, i int, U str)."""
    if key not in entry:
        raise FieldError(key, f"{where}: missing {key!r}")
    try:
        arr = np.asarray(entry[key])
    except (ValueError, TypeError) as exc:  # ragged nested lists
        raise FieldError(key, f"{where}.{key} is not an array: {str(exc)[:120]}") from None
    if kind == "U":
        ok = arr.dtype.kind in "US" or (arr.dtype.kind == "O" and all(
            isinstance(v, str) for v in arr.reshape(-1).tolist()))
    else:
        ok = arr.dtype.kind in ("biuf" if kind == "f" else "iu")
    if not ok:
        raise FieldError(key, f"{where}.{key} must be {_KINDS[kind]}, got dtype {arr.dtype}")
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(
            shape, arr.shape, strict=True)):
        want = ", ".join("N" if s is None else str(s) for s in shape)
        raise FieldError(key, f"{where}.{key} must have shape [{want}], got {arr.shape}")
    if kind == "f" and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0].tolist()
        raise FieldError(key, f"{where}.{key} has NaN or Inf at {bad}")
    return arr.astype(str) if kind == "U" else arr.astype(np.float64 if kind == "f" else np.int64)


_KINDS = {"f": "numeric", "i": "integers", "U": "strings"}


def _boxes(raw: np.ndarray, where: str, key: str) -> np.ndarray:
    """`[N, 9]` detcal boxes of OpenPCDet boxes `[N, 7 | 9]` (x y z dx dy dz heading vx vy)."""
    if raw.shape[1] not in (7, 9):
        raise FieldError(key, f"{where}.{key} must have 7 or 9 columns, got {raw.shape[1]}")
    if len(raw) and np.any(raw[:, 3:6] <= 0):
        row = int(np.argwhere(raw[:, 3:6] <= 0)[0, 0])
        raise FieldError(key, f"{where}.{key}[{row}] has a size (dx dy dz) <= 0", row=row)
    out = np.zeros((len(raw), 9))
    out[:, :3], out[:, 3], out[:, 4], out[:, 5], out[:, 6] = \
        raw[:, :3], raw[:, 4], raw[:, 3], raw[:, 5], raw[:, 6]
    out[:, 7:] = raw[:, 7:9] if raw.shape[1] == 9 else 0.0
    return out


def _predictions(entries: list[dict], name: str, classes: tuple[str, ...],
                 index: Mapping[str, int]) -> tuple[Rows, np.ndarray | None, np.ndarray]:
    """Detection rows, `[N, 4]` 2D boxes (None unless every frame has `bbox`), `[N]` names."""
    frames, labels, boxes, scores, bbox, names = [], [], [], [], [], []
    total = 0
    for i, entry in enumerate(entries):
        where = f"{name}[{i}]"
        score = _array(entry, "score", where, (None,))
        n = len(score)
        total += n
        if total > MAX_ROWS:
            raise FieldError("score", f"{name}: more than {MAX_ROWS} detections")
        box = _boxes(_array(entry, "boxes_lidar", where, (n, None)), where, "boxes_lidar")
        label = _labels(entry, where, n, classes, index)
        bad = np.flatnonzero((score < 0) | (score > 1))
        if len(bad):
            raise FieldError("score", f"{where}.score[{bad[0]}] = {score[bad[0]]:g} is not a "
                                      "probability in [0, 1]", row=int(bad[0]))
        frames += [_token(entry, where)] * n
        labels.append(label)
        boxes.append(box)
        scores.append(score)
        names.append(_array(entry, "name", where, (n,), "U") if "name" in entry
                     else np.array(classes)[label])
        bbox.append(_array(entry, "bbox", where, (n, 4)) if "bbox" in entry else None)
    has_bbox = all(b is not None for b in bbox)
    cat = (lambda parts, empty: np.concatenate(parts) if parts else empty)  # noqa: E731
    return (Rows(np.array(frames, dtype=str), cat(labels, np.zeros(0, dtype=np.int64)),
                 cat(boxes, np.zeros((0, 9))), scores=cat(scores, np.zeros(0))),
            cat(bbox, np.zeros((0, 4))) if has_bbox else None, cat(names, np.zeros(0, str)))


def _labels(entry: dict, where: str, n: int, classes: tuple[str, ...],
            index: Mapping[str, int]) -> np.ndarray:
    """`[n]` class index from `name`, checked against the 1-based `pred_labels`."""
    from_labels = None
    if "pred_labels" in entry:
        raw = _array(entry, "pred_labels", where, (n,), "i")
        bad = np.flatnonzero((raw < 1) | (raw > len(classes)))
        if len(bad):
            raise FieldError("pred_labels", f"{where}.pred_labels[{bad[0]}] = {raw[bad[0]]} is "
                                            f"not a 1-based index into the {len(classes)} "
                                            "classes", row=int(bad[0]))
        from_labels = raw - 1
    if "name" not in entry:
        if from_labels is None:
            raise FieldError("name", f"{where}: missing 'name' (and 'pred_labels')")
        return from_labels
    names = _array(entry, "name", where, (n,), "U")
    out = np.empty(n, dtype=np.int64)
    for k, c in enumerate(names.tolist()):
        if c not in index:
            raise FieldError("name", f"{where}.name[{k}] = {c!r} is not one of the classes "
                                     f"{list(classes)} (nor class_map)", row=k)
        out[k] = index[c]
        if from_labels is not None and classes[from_labels[k]] != c:
            raise FieldError("pred_labels", f"{where}.pred_labels[{k}] = {from_labels[k] + 1} "
                                            f"names {classes[from_labels[k]]!r} but name is "
                                            f"{c!r}: classes must be the config's CLASS_NAMES "
                                            "in order", row=k)
    return out


def _truth(infos: list[dict], name: str, frames: set[str], index: Mapping[str, int]
           ) -> tuple[Rows, np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Ground-truth rows of `frames` (neighbouring-class rows flagged in the `[G]` mask) and
    the DontCare regions (frame tokens `[K]`, boxes `[K, 4]`)."""
    rows: list[tuple[str, int, np.ndarray, bool]] = []
    dc_frames, dc_boxes = [], []
    seen = set()
    for i, info in enumerate(infos):
        where = f"{name}[{i}]"
        token = _token(info, where)
        if token not in frames:
            continue
        seen.add(token)
        if "annos" in info:
            names, boxes, bbox = _kitti_annos(info["annos"], f"{where}.annos")
        else:
            names = _array(info, "gt_names", where, (None,), "U")
            boxes = _boxes(_array(_known_velocity(info), "gt_boxes", where, (len(names), None)),
                           where, "gt_boxes")
            if "num_lidar_pts" in info:
                pts = _array(info, "num_lidar_pts", where, (len(names),), "i")
                names, boxes = names[pts > 0], boxes[pts > 0]
            bbox = None
        for k, c in enumerate(names.tolist()):
            if c in index:
                rows.append((token, index[c], boxes[k], False))
            elif c in NEIGHBOURS.values():
                target = [t for t, nb in NEIGHBOURS.items() if nb == c][0]
                if target in index:
                    rows.append((token, index[target], boxes[k], True))
            elif c == "DontCare" and bbox is not None:
                dc_frames.append(token)
                dc_boxes.append(bbox[k])
    missing = sorted(frames - seen)
    if missing:
        raise FieldError("infos", f"{name}: has no entry for frame {missing[0]!r} of the results")
    gt = Rows(np.array([r[0] for r in rows], dtype=str), np.array([r[1] for r in rows],
                                                                  dtype=np.int64),
              np.array([r[2] for r in rows]).reshape(-1, 9))
    return gt, np.array([r[3] for r in rows], dtype=bool), \
        (np.array(dc_frames, dtype=str), np.array(dc_boxes).reshape(-1, 4))


def _known_velocity(info: dict) -> dict:
    """`info` with NaN velocities of `gt_boxes [M, 9]` (nuScenes: unknown) set to 0."""
    raw = info.get("gt_boxes")
    if isinstance(raw, np.ndarray) and raw.ndim == 2 and raw.shape[1] == 9 \
            and raw.dtype.kind == "f":
        raw = raw.copy()
        raw[:, 7:9] = np.nan_to_num(raw[:, 7:9], nan=0.0, posinf=np.inf, neginf=-np.inf)
        return {**info, "gt_boxes": raw}
    return info


def _kitti_annos(annos: object, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(names `[K]`, boxes `[K, 9]`, 2D boxes `[K, 4]`) of KITTI-style infos annos; the boxes
    of DontCare rows (which `gt_boxes_lidar` leaves out, last) are zeros."""
    if not isinstance(annos, dict):
        raise FieldError("annos", f"{where} must be a dict")
    names = _array(annos, "name", where, (None,), "U")
    real = int(np.sum(names != "DontCare"))
    lidar = _array(annos, "gt_boxes_lidar", where, (real, None))
    if not np.all(names[:real] != "DontCare"):
        raise FieldError("name", f"{where}.name: DontCare rows must come last (as OpenPCDet "
                                 "writes them)")
    boxes = np.zeros((len(names), 9))
    boxes[:real] = _boxes(lidar, where, "gt_boxes_lidar")
    bbox = _array(annos, "bbox", where, (len(names), 4)) if "bbox" in annos \
        else np.zeros((len(names), 4))
    return names, boxes, bbox


def _kitti_ignored(det: Rows, det_bbox: np.ndarray | None, det_names: np.ndarray, gt: Rows,
                   neighbour: np.ndarray, dc: tuple[np.ndarray, np.ndarray],
                   threshold: float) -> np.ndarray:
    """`[N]` detections KITTI's evaluation ignores (kitti_ignore) against this ground truth."""
    tokens = sorted(set(det.frames.tolist()) | set(gt.frames.tolist()) | set(dc[0].tolist()))
    frame_of = {t: i for i, t in enumerate(tokens)}

    def frames(arr: np.ndarray) -> np.ndarray:
        return np.array([frame_of[t] for t in arr.tolist()], dtype=np.int64)

    bbox = np.zeros((len(det.labels), 4)) if det_bbox is None else det_bbox
    return ignored_detections(
        frames(det.frames), det.labels, det.scores, det.boxes[:, :2], bbox,
        np.array([DONTCARE_OVERLAP.get(str(c), 0.5) for c in det_names.tolist()]),
        frames(gt.frames), gt.labels, gt.boxes[:, :2], neighbour,
        frames(dc[0]) if det_bbox is not None else np.zeros(0, dtype=np.int64),
        dc[1] if det_bbox is not None else np.zeros((0, 4)), threshold)
