"""KITTI label text, line by line (object and tracking devkit readmes), with strict checks.

One object per line, fields separated by spaces:

    object:    type truncated occluded alpha bbox[4] dimensions[3] location[3] rotation_y [score]
    tracking:  frame track_id type truncated occluded alpha bbox[4] dimensions[3] location[3]
               rotation_y [score]

so 15 / 16 fields (object) and 17 / 18 (tracking); a file uses one count on every line.
AB3DMOT's detection files (`frame,type_id,x1,y1,x2,y2,score,h,w,l,x,y,z,rot_y,alpha`,
comma-separated, type 1 Pedestrian, 2 Car, 3 Cyclist) are read as tracking lines with score.
`bbox` is left, top, right, bottom (px); `dimensions` height, width, length (m); `location`
the bottom centre in rectified camera-0 coordinates (m); `rotation_y` in [-pi, pi].
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from calibrators.core.errors import FieldError

#: Number fields after `type`, in order (`bbox` and the vectors spread over their columns).
NUMBER_FIELDS = ("truncated", "occluded", "alpha", "bbox", "bbox", "bbox", "bbox",
                 "dimensions", "dimensions", "dimensions", "location", "location", "location",
                 "rotation_y")
#: Field counts: (object, tracking) x (without, with score).
OBJECT_COUNTS, TRACKING_COUNTS = (15, 16), (17, 18)
_WHOLE = re.compile(r"-?[0-9]{1,18}")
#: AB3DMOT's detection files (one per class and sequence, comma-separated): type ids, fields.
AB3DMOT_TYPES = {"1": "Pedestrian", "2": "Car", "3": "Cyclist"}
AB3DMOT_COUNT = 15


@dataclass(frozen=True)
class LabelTable:
    """Lines of one or more label files.

        layout  "object" | "tracking"
        keys    [M] str    file stem (object: frame; tracking: sequence)
        frames  [M] int    tracking frame (object: 0)
        types   [M] str    KITTI type
        values  [M, 14]    NUMBER_FIELDS (bbox at 3:7, h w l at 7:10, location 10:13, ry 13)
        scores  [M] | None score column (None when the lines have none)
        where   [M] str    "file line n" for messages
    """

    layout: str
    keys: np.ndarray
    frames: np.ndarray
    types: np.ndarray
    values: np.ndarray
    scores: np.ndarray | None
    where: np.ndarray

    def tokens(self) -> np.ndarray:
        """`[M]` frame token: the file stem (object), `sequence/frame:06d` (tracking)."""
        if self.layout == "object":
            return self.keys.astype(str)
        return np.array([f"{k}/{f:06d}" for k, f in zip(self.keys.tolist(),
                                                        self.frames.tolist(), strict=True)],
                        dtype=str)


def parse_label_file(text: str, name: str, key: str) -> LabelTable:
    """The lines of one label file called `name` (stem `key`); FieldError naming the file, the
    line, the field and the reason for a bad line."""
    lines = [(k, line.split()) for k, line in enumerate(text.splitlines(), start=1)
             if line.strip()]
    if lines and "," in lines[0][1][0]:
        lines = [(k, _from_ab3dmot(" ".join(f), f"{name} line {k}", k)) for k, f in lines]
    count = len(lines[0][1]) if lines else OBJECT_COUNTS[0]
    if count not in OBJECT_COUNTS + TRACKING_COUNTS:
        raise FieldError("line", f"{name} line {lines[0][0]}: {count} fields; KITTI labels "
                                 "have 15 (object), 16 (object with score), 17 (tracking) or "
                                 "18 (tracking with score)", row=lines[0][0])
    tracking = count in TRACKING_COUNTS
    frames, types, values, scores, where = [], [], [], [], []
    for number, fields in lines:
        at = f"{name} line {number}"
        if len(fields) != count:
            raise FieldError("line", f"{at}: {len(fields)} fields where the file's first line "
                                     f"has {count} (a truncated or mixed file?)", row=number)
        if tracking:
            frames.append(_whole(fields[0], "frame", at, number))
            _whole(fields[1], "track_id", at, number, minimum=-1)
            fields = fields[2:]
        types.append(fields[0])
        values.append([_number(v, NUMBER_FIELDS[i], at, number)
                       for i, v in enumerate(fields[1:15])])
        if len(fields) == 16:
            scores.append(_number(fields[15], "score", at, number))
        where.append(at)
    m = len(types)
    return LabelTable(
        layout="tracking" if tracking else "object", keys=np.array([key] * m, dtype=str),
        frames=np.array(frames if tracking else [0] * m, dtype=np.int64),
        types=np.array(types, dtype=str), values=np.array(values, dtype=float).reshape(m, 14),
        scores=np.array(scores, dtype=float) if count in (16, 18) else None,
        where=np.array(where, dtype=str))


def concat_tables(tables: list[LabelTable], what: str) -> LabelTable:
    """One table of several files' lines, in order; they must share layout and score column."""
    layouts = {t.layout for t in tables if len(t.types)}
    if len(layouts) > 1:
        raise FieldError(what, f"{what} mixes object and tracking label files")
    scored = {t.scores is not None for t in tables if len(t.types)}
    if len(scored) > 1:
        raise FieldError(what, f"{what} mixes files with and without a score column")
    has_score = scored == {True}
    return LabelTable(
        layout=layouts.pop() if layouts else "object",
        keys=np.concatenate([t.keys for t in tables] or [np.zeros(0, dtype=str)]),
        frames=np.concatenate([t.frames for t in tables] or [np.zeros(0, dtype=np.int64)]),
        types=np.concatenate([t.types for t in tables] or [np.zeros(0, dtype=str)]),
        values=np.concatenate([t.values for t in tables] or [np.zeros((0, 14))]),
        scores=np.concatenate([t.scores for t in tables if t.scores is not None] or
                              [np.zeros(0)]) if has_score else None,
        where=np.concatenate([t.where for t in tables] or [np.zeros(0, dtype=str)]))


def _from_ab3dmot(line: str, at: str, number: int) -> list[str]:
    """An AB3DMOT detection line (`frame,type_id,x1,y1,x2,y2,score,h,w,l,x,y,z,rot_y,alpha`,
    type 1 Pedestrian, 2 Car, 3 Cyclist) as the fields of a tracking line with score."""
    fields = [f.strip() for f in line.split(",")]
    if len(fields) != AB3DMOT_COUNT:
        raise FieldError("line", f"{at}: {len(fields)} comma-separated fields; AB3DMOT "
                                 f"detections have {AB3DMOT_COUNT}", row=number)
    frame, type_id, x1, y1, x2, y2, score, h, w, length, x, y, z, ry, alpha = fields
    if type_id not in AB3DMOT_TYPES:
        raise FieldError("type", f"{at}: type_id must be 1 (Pedestrian), 2 (Car) or 3 "
                                 f"(Cyclist), got {type_id[:40]!r}", row=number)
    return [frame, "-1", AB3DMOT_TYPES[type_id], "0", "0", alpha, x1, y1, x2, y2, h, w, length,
            x, y, z, ry, score]


def _number(text: str, field: str, at: str, number: int) -> float:
    try:
        value = float(text)
    except ValueError:
        raise FieldError(field, f"{at}: {field} must be a number, got {text[:40]!r}",
                         row=number) from None
    if not np.isfinite(value):
        raise FieldError(field, f"{at}: {field} is {text[:40]!r}; it must be finite",
                         row=number)
    return value


def _whole(text: str, field: str, at: str, number: int, minimum: int = 0) -> int:
    if not _WHOLE.fullmatch(text) or int(text) < minimum:
        raise FieldError(field, f"{at}: {field} must be a whole number >= {minimum}, got "
                                f"{text[:40]!r}", row=number)
    return int(text)
