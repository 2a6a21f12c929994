"""KITTI object and tracking label text with a score column -> `Dump` (docs/formats.md).

Detections are KITTI label lines with a 16th (object) or 18th (tracking) `score` field, as
PointRCNN, PV-RCNN / OpenPCDet (`--save_to_file`) and AB3DMOT write them; the ground truth is
KITTI's own labels (`label_2/`, `label_02/`). Either may be one file, a folder of files (one
per frame, or per sequence for tracking), or a folder of such folders (one per class, as many
pipelines write them): every `.txt` below it, read in sorted order and concatenated, so one
frame's detections may come from several files.

Frames: object files are frames (token = file stem, `000123`); tracking files are sequences
and the frame column numbers frames (token `0004/000012`). With a ground-truth folder, the
ground truth read is that of the detections' files (`<folder>/<stem>.txt`), not the whole
folder (a val split's detections against every training label would count misses).

Boxes go to the lidar frame through a calib file (`kitti_calib`), else to the camera frame
with its axes renamed (x forward, y left, z up; origin at camera 0). Classes and the ignore
rules (`DontCare`, neighbouring classes) are described in `kitti_ignore` and docs/formats.md.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from calibrators.core.defaults import MATCH_THRESHOLD
from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io.kitti_calib import CAMERA_AXES, camera_boxes, parse_calib
from calibrators.io.kitti_ignore import (
    DIFFICULTY,
    DONTCARE_OVERLAP,
    NEIGHBOURS,
    ignored_detections,
    too_hard,
    too_small,
)
from calibrators.io.kitti_text import LabelTable, concat_tables, parse_label_file
from calibrators.io.reader_files import ByteBudget, check_file
from calibrators.io.reader_rows import Rows, class_list, rows_to_dump

#: The object types of the KITTI devkit readme.
KITTI_TYPES = ("Car", "Van", "Truck", "Pedestrian", "Person_sitting", "Cyclist", "Tram", "Misc",
               "DontCare")
#: The classes KITTI's benchmark evaluates: the default class list.
KITTI_CLASSES = ("Car", "Pedestrian", "Cyclist")
#: Most label files one load reads.
MAX_FILES = 100_000
#: How a score column is read: a probability in [0, 1], or a logit (any real number).
SCORE_KINDS = ("probability", "logit")

PathArg = str | os.PathLike[str]


def load_kitti(detections: PathArg | Sequence[PathArg], ground_truth: PathArg | None = None,
               *, calib: PathArg | None = None, classes: Sequence[str] = KITTI_CLASSES,
               class_map: Mapping[str, str] | None = None, score: str = "probability",
               threshold: float = MATCH_THRESHOLD, difficulty: str | None = None,
               max_bytes: int | None = None) -> Dump:
    """Read KITTI label files with scores (and, optionally, KITTI ground truth) into a `Dump`.

    `classes` is the dump's class list (default Car, Pedestrian, Cyclist); `class_map` maps
    KITTI type names onto it (`{"Car": "car", "Van": "car"}`). Lines of other KITTI types are
    not read (as KITTI's evaluation); a type that is neither a KITTI type nor mapped is
    refused. `score`: `"probability"` (checked in [0, 1]) or `"logit"`. `calib`: a calib file
    for every frame, or a folder with one per file stem (`calib/000123.txt`, tracking
    `calib/0004.txt`); without it boxes stay in the camera frame (axes renamed). `threshold`
    (m) is the matching distance of the ignore rules; `difficulty` (`easy`, `moderate`, `hard`,
    default none) adds KITTI's difficulty rules to them (`kitti_ignore`). At most `max_bytes`
    (default 2 GiB) are read in all. Errors are `FieldError`s naming the file, the line and
    the field.
    """
    classes, index = class_list(classes, class_map)
    if score not in SCORE_KINDS:
        raise FieldError("score", f"score must be one of {list(SCORE_KINDS)}, got {score!r}")
    if difficulty is not None and difficulty not in DIFFICULTY:
        raise FieldError("difficulty", f"difficulty must be one of {list(DIFFICULTY)} or None, "
                                       f"got {difficulty!r}")
    budget = ByteBudget(max_bytes)
    det_files = _label_files(detections, "detections")
    det = concat_tables([_read(p, name, budget) for p, name in det_files], "detections")
    if det.scores is None and len(det.types):
        raise FieldError("score", f"{det.where[0]}: detections need a score column (16 fields "
                                  "for object labels, 18 for tracking)")
    gt_files = [] if ground_truth is None else \
        _truth_files(ground_truth, [p for p, _ in det_files])
    to_frame = _calib_maps(calib, sorted({p.stem for p, _ in det_files + gt_files}), budget)
    labels = _labels(det, index)
    rows = _detection_rows(det, labels, to_frame, score)
    frames = det.tokens() if det.layout == "tracking" else \
        np.array([p.stem for p, _ in det_files], dtype=str)
    if ground_truth is None:
        return rows_to_dump(classes, rows, None, score_is_logit=score == "logit",
                            frames=frames, source=_source_name(detections))
    gt = concat_tables([_read(p, name, budget) for p, name in gt_files], "ground truth")
    if len(gt.types) and len(det.types) and gt.layout != det.layout:
        raise FieldError("ground_truth", f"ground truth is {gt.layout} labels but the "
                                         f"detections are {det.layout} labels")
    gt_labels = _labels(gt, index)
    hard = too_hard(gt.values[:, 3:7], gt.values[:, 1], gt.values[:, 0], difficulty)
    keep = _ignore(det, labels, gt, gt_labels, hard, index, to_frame, rows, threshold)
    keep &= ~too_small(det.values[labels >= 0, 3:7], difficulty)
    truth = np.flatnonzero((gt_labels >= 0) & ~hard)
    return rows_to_dump(classes, _select(rows, keep),
                        Rows(gt.tokens()[truth], gt_labels[truth], _boxes(gt, truth, to_frame)),
                        score_is_logit=score == "logit",
                        frames=np.concatenate([frames, gt.tokens()]),
                        source=_source_name(detections))


def _source_name(source: PathArg | Sequence[PathArg]) -> str:
    """The detections' name for messages: the (first) file or folder given."""
    first = source if isinstance(source, str | os.PathLike) else next(iter(source), "")
    return Path(first).name or "detections"


def _label_files(source: PathArg | Sequence[PathArg], what: str) -> list[tuple[Path, str]]:
    """(path, name for messages) of every `.txt` file of `source`, sorted per source."""
    sources = [source] if isinstance(source, str | os.PathLike) else list(source)
    files: list[tuple[Path, str]] = []
    for item in sources:
        root = check_file(item, f"{what} {Path(item).name}")
        found = sorted(root.rglob("*.txt")) if root.is_dir() else [root]
        if len(files) + len(found) > MAX_FILES:
            raise FieldError(what, f"{what}: more than {MAX_FILES} label files")
        files += [(p, str(Path(root.name) / p.relative_to(root)) if root.is_dir() else p.name)
                  for p in found if p.is_file()]
    return files


def _truth_files(source: PathArg, det_paths: list[Path]) -> list[tuple[Path, str]]:
    """Ground-truth files: a folder's `<stem>.txt` for each detection file's stem, or as
    `_label_files` for a file."""
    root = check_file(source, f"ground truth {Path(source).name}")
    if not root.is_dir():
        return _label_files(root, "ground truth")
    out = []
    for stem in sorted({p.stem for p in det_paths}):
        path = root / f"{stem}.txt"
        if not path.is_file():
            raise FieldError("ground_truth", f"ground truth {root.name}/{stem}.txt is missing "
                                             f"(the detections have {stem}.txt)")
        out.append((path, f"{root.name}/{stem}.txt"))
    return out


def _read(path: Path, name: str, budget: ByteBudget) -> LabelTable:
    data = budget.read(path, name)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise FieldError("line", f"{name}: not UTF-8 text ({exc.reason} at byte "
                                 f"{exc.start})") from None
    return parse_label_file(text, name, path.stem)


def _calib_maps(calib: PathArg | None, stems: list[str], budget: ByteBudget
                ) -> dict[str, np.ndarray]:
    """File stem -> `[4, 4]` rectified camera -> box frame (the camera axes without calib)."""
    if calib is None:
        return {stem: CAMERA_AXES for stem in stems}
    root = check_file(calib, f"calib {Path(calib).name}")
    if not root.is_dir():
        one = parse_calib(_text(budget.read(root, root.name), root.name), root.name)
        return {stem: one for stem in stems}
    maps = {}
    for stem in stems:
        path = root / f"{stem}.txt"
        if not path.is_file():
            raise FieldError("calib", f"calib {root.name}/{stem}.txt is missing")
        name = f"{root.name}/{stem}.txt"
        maps[stem] = parse_calib(_text(budget.read(path, name), name), name)
    return maps


def _text(data: bytes, name: str) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise FieldError("calib", f"{name}: not UTF-8 text") from None


def _labels(table: LabelTable, index: Mapping[str, int]) -> np.ndarray:
    """`[M]` class index of each line, -1 for a KITTI type outside the classes; refuses a type
    that is neither (naming the line)."""
    out = np.full(len(table.types), -1, dtype=np.int64)
    for i, name in enumerate(table.types.tolist()):
        if name in index:
            out[i] = index[name]
        elif name not in KITTI_TYPES:
            raise FieldError("type", f"{table.where[i]}: type {name!r} is neither a KITTI type "
                                     f"({', '.join(KITTI_TYPES)}) nor one of the classes or "
                                     "class_map")
    return out


def _boxes(table: LabelTable, rows: np.ndarray, to_frame: Mapping[str, np.ndarray]
           ) -> np.ndarray:
    """`[len(rows), 9]` boxes of the given lines (dimensions checked > 0)."""
    values = table.values[rows]
    bad = np.flatnonzero(np.any(values[:, 7:10] <= 0, axis=1))
    if len(bad):
        raise FieldError("dimensions", f"{table.where[rows[bad[0]]]}: dimensions (height, "
                                       f"width, length) must be > 0, got "
                                       f"{values[bad[0], 7:10].tolist()}", row=int(rows[bad[0]]))
    out = np.zeros((len(rows), 9))
    keys = table.keys[rows]
    for key in sorted(set(keys.tolist())):
        mine = keys == key
        out[mine] = camera_boxes(values[mine][:, [7, 8, 9, 10, 11, 12, 13]], to_frame[key])
    return out


def _detection_rows(det: LabelTable, labels: np.ndarray, to_frame: Mapping[str, np.ndarray],
                    score: str) -> Rows:
    """Rows of the detections whose type is one of the classes (`labels >= 0`)."""
    rows = np.flatnonzero(labels >= 0)
    scores = np.zeros(len(det.types)) if det.scores is None else det.scores
    bad = np.flatnonzero((labels >= 0) & ((scores < 0) | (scores > 1)))
    if score == "probability" and len(bad):
        raise FieldError("score", f"{det.where[bad[0]]}: score {scores[bad[0]]:g} is not a "
                                  "probability in [0, 1] (a logit? pass score='logit')")
    return Rows(det.tokens()[rows], labels[rows], _boxes(det, rows, to_frame),
                scores=scores[rows])


def _ignore(det: LabelTable, labels: np.ndarray, gt: LabelTable, gt_labels: np.ndarray,
            hard: np.ndarray, index: Mapping[str, int], to_frame: Mapping[str, np.ndarray],
            rows: Rows, threshold: float) -> np.ndarray:
    """`[N]` mask of the detection `rows` KITTI's evaluation counts (kitti_ignore); `hard`
    `[M]` marks ground truth of the classes ignored at the difficulty level."""
    kept = np.flatnonzero(labels >= 0)
    neighbour = np.full(len(gt_labels), -1, dtype=np.int64)
    for target, name in NEIGHBOURS.items():
        if target in index and name not in index:
            neighbour[(gt.types == name) & (gt_labels < 0)] = index[target]
    use = np.flatnonzero((gt_labels >= 0) | (neighbour >= 0))
    gt_tokens = gt.tokens()
    frame_of = {t: i for i, t in enumerate(sorted(set(rows.frames.tolist())
                                                  | set(gt_tokens.tolist())))}
    dc = np.flatnonzero(gt.types == "DontCare")
    ignored = ignored_detections(
        det_frame=np.array([frame_of[t] for t in rows.frames.tolist()], dtype=np.int64),
        det_labels=rows.labels, det_scores=rows.scores, det_xy=rows.boxes[:, :2],
        det_bbox=det.values[kept, 3:7],
        det_min_overlap=np.array([DONTCARE_OVERLAP.get(t, 0.5) for t in det.types[kept]]),
        gt_frame=np.array([frame_of[t] for t in gt_tokens[use].tolist()], dtype=np.int64),
        gt_labels=np.where(gt_labels[use] >= 0, gt_labels[use], neighbour[use]),
        gt_xy=_boxes(gt, use, to_frame)[:, :2], gt_ignored=(neighbour[use] >= 0) | hard[use],
        dc_frame=np.array([frame_of[t] for t in gt_tokens[dc].tolist()], dtype=np.int64),
        dc_bbox=gt.values[dc, 3:7], threshold=threshold)
    return ~ignored


def _select(rows: Rows, keep: np.ndarray) -> Rows:
    return Rows(rows.frames[keep], rows.labels[keep], rows.boxes[keep],
                scores=None if rows.scores is None else rows.scores[keep])
