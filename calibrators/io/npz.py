"""Validation dump v1 as a columnar NPZ (docs/formats.md lists every key).

Loading never unpickles: strings are unicode arrays, everything else numeric. The archive is
checked before anything is inflated or allocated: each member's `.npy` header (dtype, shape)
and the zip's declared sizes, against `max_bytes` (the total inflated size), the dtypes a key
may have (never object, complex or structured) and the shapes the other keys imply (N, L, G,
F, C, D, H). Every missing, unknown, unreadable or inconsistent key is refused with a
`FieldError` naming the key; values (NaN/Inf, indices) are then checked by
`calibrators.data._dump.Dump`, whose messages name the key too. Messages never show the file's path.
"""

from __future__ import annotations

import math
import os
import zipfile
from typing import BinaryIO

import numpy as np

from calibrators.core.errors import FieldError
from calibrators.data import Dump
from calibrators.io.atomic import atomic_write

REQUIRED_KEYS = ("classes", "score_mode", "frame_ids", "det_frame", "det_logits", "det_boxes",
                 "gt_frame", "gt_labels", "gt_boxes")
OPTIONAL_KEYS = ("ego_translation", "det_cov", "cov_dims", "det_label")
#: Optional too, and only together: the box hypotheses of group regression heads.
HYPOTHESIS_KEYS = ("det_hyp_boxes", "det_hyp_scores")
KNOWN_KEYS = REQUIRED_KEYS + OPTIONAL_KEYS + HYPOTHESIS_KEYS
STRING_KEYS = {"classes": 1, "score_mode": 0, "frame_ids": 1, "cov_dims": 1}  # key -> ndim
#: Shape of every key in the symbols of docs/formats.md (an int is a fixed size); a symbol
#: takes its size from the first key in this order that has it.
SHAPES: dict[str, tuple[str | int, ...]] = {
    "det_logits": ("N", "L", "C'"), "det_boxes": ("N", "L", 9), "det_frame": ("N",),
    "cov_dims": ("D",), "det_cov": ("N", "D", "D"), "det_hyp_boxes": ("N", "H", 9),
    "det_hyp_scores": ("N", "H"), "det_label": ("N",), "gt_boxes": ("G", 9), "gt_frame": ("G",),
    "gt_labels": ("G",), "frame_ids": ("F",), "ego_translation": ("F", 3), "classes": ("C",),
    "score_mode": ()}
#: Default limit on the inflated size of all arrays together (bytes); `load_dump(max_bytes=)`.
MAX_BYTES = 2 * 2**30
_MAX_HEADER = 10_000  # bytes of a .npy header (numpy's own default limit)
_CHUNK = 16 * 2**20  # bytes inflated at a time
_NUMERIC_KINDS = "biuf"
_STRING_KINDS = "US"


def load_dump(path: str | os.PathLike[str] | BinaryIO, *, max_bytes: int | None = None) -> Dump:
    """Read a validation dump v1 NPZ (a path or a binary file object) into a `Dump`.

    Refused before any array is read: a file that is not a zip archive, a member that is not
    a plain `.npy` array of a numeric (strings for the string keys) dtype, shapes that
    disagree with each other, and arrays whose inflated size (as their headers and the zip
    declare it) exceeds `max_bytes` in total (default `MAX_BYTES`, 2 GiB). Errors are
    `FieldError`s (ValueErrors) whose `field` is the key, or `"dump"` for the whole archive.
    """
    max_bytes = MAX_BYTES if max_bytes is None else max_bytes
    if isinstance(max_bytes, bool) or not isinstance(max_bytes, int) or max_bytes <= 0:
        raise ValueError(f"max_bytes must be a positive integer, got {max_bytes!r}")
    archive = _open(path)
    with archive:
        members = _members(archive)
        headers = {key: _header(archive, key, info, max_bytes) for key, info in members.items()}
        sizes = {key: max(headers[key][3], info.file_size) for key, info in members.items()}
        if sum(sizes.values()) > max_bytes:
            big = max(sizes, key=sizes.__getitem__)
            raise FieldError(big, f"the dump inflates to {sum(sizes.values())} bytes, more than "
                                  f"the limit of {max_bytes} bytes (the largest key, {big!r}, "
                                  f"to {sizes[big]})")
        _check_shapes({key: h[0] for key, h in headers.items()})
        fields = {key: _read(archive, key, members[key], headers[key]) for key in sorted(members)}
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
    if dump.det_hyp_boxes is not None and dump.det_hyp_scores is not None:
        arrays["det_hyp_boxes"] = dump.det_hyp_boxes
        arrays["det_hyp_scores"] = dump.det_hyp_scores
    if dump.det_label is not None:
        arrays["det_label"] = dump.det_label
    if hasattr(path, "write"):
        np.savez_compressed(path, **arrays)
        return
    with atomic_write(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def _open(path: str | os.PathLike[str] | BinaryIO) -> zipfile.ZipFile:
    """The archive, or a FieldError saying what the file is instead (never its path)."""
    try:
        if hasattr(path, "read"):
            head = path.read(6)  # type: ignore[union-attr]
            path.seek(-len(head), os.SEEK_CUR)  # type: ignore[union-attr]
        else:
            with open(path, "rb") as fh:
                head = fh.read(6)
    except FileNotFoundError:
        raise
    except OSError as exc:
        raise FieldError("dump", f"the dump cannot be read: {exc.strerror or exc}") from None
    if head == b"\x93NUMPY":
        raise FieldError("dump", "the dump is a single array (.npy); a validation dump is an NPZ "
                                 "archive of named arrays")
    try:
        return zipfile.ZipFile(path)  # type: ignore[arg-type]
    except (zipfile.BadZipFile, zipfile.LargeZipFile, EOFError, ValueError):
        raise FieldError("dump", "the dump is not an NPZ archive: not a zip file (an NPZ is "
                                 "a zip of .npy arrays, as numpy.savez writes)") from None
    except OSError as exc:
        raise FieldError("dump", f"the dump cannot be read: {exc.strerror or exc}") from None


def _members(archive: zipfile.ZipFile) -> dict[str, zipfile.ZipInfo]:
    """Key -> zip member; refuses missing, unknown, duplicate and non-.npy members."""
    members: dict[str, zipfile.ZipInfo] = {}
    for info in archive.infolist():
        key = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
        if key not in KNOWN_KEYS:
            raise FieldError(key, f"unknown key {key!r}; validation dump v1 has "
                                  f"{list(KNOWN_KEYS)}")
        if not info.filename.endswith(".npy") or info.is_dir():
            raise FieldError(key, f"key {key!r} must be a .npy member of the archive, got "
                                  f"{info.filename!r}")
        if key in members:
            raise FieldError(key, f"key {key!r} appears twice in the archive")
        if info.flag_bits & 0x1:
            raise FieldError(key, f"key {key!r} is encrypted")
        members[key] = info
    for key in REQUIRED_KEYS:
        if key not in members:
            raise FieldError(key, f"missing key {key!r}")
    return members


_Header = tuple[tuple[int, ...], bool, np.dtype, int, int]  # shape, fortran, dtype, nbytes, offset


def _header(archive: zipfile.ZipFile, key: str, info: zipfile.ZipInfo,
            max_bytes: int) -> _Header:
    """The key's .npy header, checked: its dtype is allowed, its data is within `max_bytes`
    and fits the member."""
    try:
        with archive.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                    fh, max_header_size=_MAX_HEADER)
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                    fh, max_header_size=_MAX_HEADER)
            else:
                raise FieldError(key, f"key {key!r} has .npy format version {version}; "
                                      "1.0 and 2.0 are read")
            offset = fh.tell()
    except FieldError:
        raise
    except (ValueError, OSError, EOFError, zipfile.BadZipFile, NotImplementedError) as exc:
        raise FieldError(key, f"key {key!r} is not a readable .npy array: "
                              f"{_reason(exc)}") from None
    kinds = _STRING_KINDS if key in STRING_KEYS else _NUMERIC_KINDS
    if dtype.hasobject:
        raise FieldError(key, f"key {key!r} cannot be read without unpickling (dtype object): "
                              "store strings as unicode arrays, numbers as numeric arrays")
    if dtype.kind == "c":
        raise FieldError(key, f"key {key!r} is complex ({dtype}); a validation dump holds "
                              "real numbers only")
    if dtype.names is not None or dtype.subdtype is not None or dtype.kind not in kinds:
        want = "a string" if key in STRING_KEYS else "a real numeric"
        raise FieldError(key, f"{key} must be {want} array, got dtype {dtype}")
    nbytes = math.prod(shape) * dtype.itemsize  # Python ints: no overflow
    if nbytes > max_bytes:
        raise FieldError(key, f"key {key!r} declares shape {shape} of {dtype}, {nbytes} bytes: "
                              f"more than the limit of {max_bytes} bytes")
    if info.file_size < offset + nbytes:
        raise FieldError(key, f"key {key!r} declares shape {shape} ({nbytes} bytes) but its "
                              f"member holds {max(info.file_size - offset, 0)} bytes of data")
    return shape, fortran, dtype, nbytes, offset


def _check_shapes(shapes: dict[str, tuple[int, ...]]) -> None:
    """Raise a FieldError naming the first key whose shape disagrees with SHAPES."""
    sizes: dict[str, tuple[int, str]] = {} if "cov_dims" in shapes else {"D": (2, "cov_dims")}
    for key, spec in SHAPES.items():
        if key not in shapes:
            continue
        shape = shapes[key]
        if len(shape) != len(spec):
            if not spec:
                raise FieldError(key, f"{key} must be a scalar, got shape {shape}")
            raise FieldError(key, f"{key} must have {len(spec)} dimensions "
                                  f"[{', '.join(map(str, spec))}], got shape {shape}")
        want = [sizes[sym][0] if isinstance(sym, str) and sym in sizes else sym
                for sym in spec]
        for axis, (size, symbol) in enumerate(zip(shape, spec, strict=True)):
            if isinstance(symbol, str) and symbol not in sizes:
                sizes[symbol] = (size, key)
                want[axis] = size
                continue
            expected = symbol if isinstance(symbol, int) else sizes[symbol][0]
            if size == expected:
                continue
            if axis == 0 and isinstance(symbol, str):
                raise FieldError(key, f"{key} has {size} rows but {sizes[symbol][1]} has "
                                      f"{expected}")
            raise FieldError(key, f"{key} must have shape [{', '.join(map(str, want))}] "
                                  f"({symbol} = {expected}), got {shape}")


def _read(archive: zipfile.ZipFile, key: str, info: zipfile.ZipInfo,
          header: _Header) -> np.ndarray:
    """The key's array, reading exactly the bytes its (checked) header declares."""
    shape, fortran, dtype, nbytes, offset = header
    arr = np.empty(math.prod(shape), dtype=dtype)
    buf = arr.view(np.uint8) if nbytes else arr
    try:
        with archive.open(info) as fh:
            fh.read(offset)
            done = 0
            while done < nbytes:
                chunk = fh.read(min(_CHUNK, nbytes - done))
                if not chunk:
                    raise FieldError(key, f"key {key!r} is truncated: {done} of {nbytes} bytes")
                buf[done:done + len(chunk)] = np.frombuffer(chunk, dtype=np.uint8)
                done += len(chunk)
    except FieldError:
        raise
    except (OSError, EOFError, zipfile.BadZipFile, ValueError, NotImplementedError) as exc:
        raise FieldError(key, f"key {key!r} is corrupt: {_reason(exc)}") from None
    return arr.reshape(shape[::-1]).T if fortran else arr.reshape(shape)


def _reason(exc: BaseException) -> str:
    """An exception's reason without a file path (OSErrors carry the file name)."""
    return str(exc.strerror) if isinstance(exc, OSError) and exc.strerror else str(exc)


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
