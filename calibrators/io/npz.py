"""Validation dump v1 as a columnar NPZ (docs/formats.md lists every key).

Loading never unpickles (`allow_pickle=False`): strings are unicode arrays, everything else
numeric. Every missing, unknown or unreadable key is refused naming the key; shapes, NaN/Inf
and indices are then checked by `calibrators.dump.Dump`, whose messages name the key too.
"""

from __future__ import annotations

import os
import zipfile
from typing import BinaryIO

import numpy as np

from calibrators.dump import Dump
from calibrators.io.atomic import atomic_write

REQUIRED_KEYS = ("classes", "score_mode", "frame_ids", "det_frame", "det_logits", "det_boxes",
                 "gt_frame", "gt_labels", "gt_boxes")
OPTIONAL_KEYS = ("ego_translation", "det_cov", "cov_dims")
STRING_KEYS = {"classes": 1, "score_mode": 0, "frame_ids": 1, "cov_dims": 1}  # key -> ndim


def load_dump(path: str | os.PathLike[str] | BinaryIO) -> Dump:
    """Read a validation dump v1 NPZ (a path or a binary file object) into a `Dump`."""
    try:
        archive = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"{_name(path)} is not a readable NPZ archive: {exc}") from None
    if not isinstance(archive, np.lib.npyio.NpzFile):
        raise ValueError(f"{_name(path)} holds a single array; a validation dump is an "
                         "NPZ archive of named arrays")
    with archive:
        keys = set(archive.files)
        for key in REQUIRED_KEYS:
            if key not in keys:
                raise ValueError(f"missing key {key!r}")
        unknown = sorted(keys - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
        if unknown:
            raise ValueError(f"unknown key {unknown[0]!r}; validation dump v1 has "
                             f"{list(REQUIRED_KEYS + OPTIONAL_KEYS)}")
        fields = {key: _read(archive, key) for key in sorted(keys)}
    for key, ndim in STRING_KEYS.items():
        if key in fields:
            fields[key] = _strings(key, fields[key], ndim)
    fields["score_mode"] = str(fields["score_mode"])
    return Dump(**fields)


def save_dump(path: str | os.PathLike[str] | BinaryIO, dump: Dump) -> None:
    """Write `dump` as a compressed validation dump v1 NPZ.

    A path is written exactly (no `.npz` appended) and atomically; a binary file object is
    written in place.
    """
    if not isinstance(dump, Dump):
        raise ValueError(f"dump must be a calibrators.Dump, got {type(dump).__name__}")
    arrays = {
        "classes": np.array(dump.classes, dtype=str),
        "score_mode": np.array(dump.score_mode, dtype=str),
        "frame_ids": np.asarray(dump.frame_ids, dtype=str),
        "det_frame": dump.det_frame,
        "det_logits": dump.det_logits,
        "det_boxes": dump.det_boxes,
        "gt_frame": dump.gt_frame,
        "gt_labels": dump.gt_labels,
        "gt_boxes": dump.gt_boxes,
        "cov_dims": np.array(dump.cov_dims, dtype=str),
    }
    if dump.ego_translation is not None:
        arrays["ego_translation"] = dump.ego_translation
    if dump.det_cov is not None:
        arrays["det_cov"] = dump.det_cov
    if hasattr(path, "write"):
        np.savez_compressed(path, **arrays)
        return
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def _name(path: object) -> str:
    return repr(os.fspath(path)) if isinstance(path, str | os.PathLike) else "the file object"


def _read(archive: np.lib.npyio.NpzFile, key: str) -> np.ndarray:
    try:
        return archive[key]
    except ValueError as exc:  # object arrays need pickle, which is refused
        raise ValueError(f"key {key!r} cannot be read without unpickling (store strings as "
                         f"unicode arrays, numbers as numeric arrays): {exc}") from None
    except (OSError, EOFError, zipfile.BadZipFile) as exc:
        raise ValueError(f"key {key!r} is corrupt: {exc}") from None


def _strings(key: str, arr: np.ndarray, ndim: int) -> np.ndarray | str:
    if arr.dtype.kind == "S":
        try:
            arr = np.char.decode(arr, "utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(f"{key} is not valid UTF-8: {exc}") from None
    if arr.dtype.kind != "U":
        raise ValueError(f"{key} must be a string array, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        want = "a scalar" if ndim == 0 else f"{ndim}-dimensional"
        raise ValueError(f"{key} must be {want}, got shape {arr.shape}")
    return str(arr[()]) if ndim == 0 else arr
