"""Loading an uploaded dump so that a malformed file is a 422 at its form field, not a 500,
and refusing one too large for a request's memory (413) before anything is inflated.

`declared_npz` reads what an NPZ declares (each member's `.npy` header: shape and dtype, and
the zip's uncompressed sizes) without inflating any data; `check_declared` holds that against
the per-request limits (`DETCAL_MAX_DUMP_BYTES`, `DETCAL_MAX_FIT_DETECTIONS`,
`DETCAL_MAX_FEEDBACK_DETECTIONS`).
"""

from __future__ import annotations

import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from app.http.errors import RequestError

if TYPE_CHECKING:
    from calibrators import Dump


def load_upload(load: Callable[[], Dump], field: str) -> Dump:
    """Load an upload once so a malformed dump is a 422 now, not a failed job later.

    Every loader error is a 422 at `body.<field>`: the library's ValueErrors (FieldError
    included: its key is in the message) and, as a last resort, any other error a malformed
    file could still raise (MemoryError, RecursionError: the loaders refuse oversized and too
    deeply nested files before they get there).
    """
    try:
        return load()
    except ValueError as exc:
        reason = f"not a valid validation dump: {exc}"
    except (KeyError, TypeError, OverflowError, IndexError) as exc:
        reason = f"not a valid validation dump ({type(exc).__name__}): {exc}"
    except MemoryError:
        reason = "the dump is too large to load"
    except RecursionError:
        reason = "the dump is nested too deeply to load"
    except (OSError, EOFError) as exc:  # the stored copy is unreadable: no server path shown
        reason = f"the dump cannot be read: {getattr(exc, 'strerror', None) or type(exc).__name__}"
    raise RequestError(["body", field], reason)


_MAX_HEADER = 10_000   # bytes of a .npy header (numpy's default limit)
_MAX_MEMBERS = 16      # a validation dump v1 has 15 keys at most
_ROW_KEYS = {"detections": ("det_logits", "det_boxes", "det_frame"),
             "gt": ("gt_boxes", "gt_labels", "gt_frame")}


@dataclass(frozen=True)
class DeclaredDump:
    """What an uploaded NPZ dump declares: row counts from its arrays' headers, and the bytes
    its arrays inflate to (the larger of the headers' and the zip's sizes)."""

    detections: int
    ground_truth: int
    frames: int
    inflated_bytes: int
    shapes: dict[str, tuple[int, ...]]
    sizes: dict[str, int]
    members: int = 0


def declared_npz(file: BinaryIO) -> DeclaredDump | None:
    """The sizes an NPZ upload declares, read from the zip directory and each member's
    `.npy` header (a few hundred bytes inflated per member, never the data); the file's
    position is restored. None when it is not a readable NPZ: the loader then says why."""
    start = file.tell()
    try:
        members = _zip_entries(file)
        if members is not None and members > _MAX_MEMBERS:   # never parse such a directory
            return DeclaredDump(0, 0, 0, 0, {}, {}, members)
        with zipfile.ZipFile(file) as archive:
            shapes: dict[str, tuple[int, ...]] = {}
            sizes: dict[str, int] = {}
            for info in archive.infolist():
                with archive.open(info) as fh:
                    version = np.lib.format.read_magic(fh)
                    read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                            else np.lib.format.read_array_header_2_0)
                    shape, _, dtype = read(fh, max_header_size=_MAX_HEADER)
                key = info.filename.removesuffix(".npy")
                shapes[key] = shape
                sizes[key] = max(math.prod(shape) * dtype.itemsize, info.file_size)
    except Exception:  # noqa: BLE001 - a pre-check: the loader then says what is wrong
        return None
    finally:
        file.seek(start, os.SEEK_SET)

    def rows(keys: tuple[str, ...]) -> int:
        return max((shapes[k][0] for k in keys if shapes.get(k)), default=0)

    return DeclaredDump(detections=rows(_ROW_KEYS["detections"]),
                        ground_truth=rows(_ROW_KEYS["gt"]),
                        frames=rows(("frame_ids",)), inflated_bytes=sum(sizes.values()),
                        shapes=shapes, sizes=sizes, members=len(shapes))


def check_declared(declared: DeclaredDump | None, *, max_bytes: int, max_detections: int,
                   field: str, what: str) -> None:
    """A 413 at `body.<field>` when the dump would inflate beyond `max_bytes` or carries more
    than `max_detections` detections (or ground-truth boxes): refused before it is built."""
    if declared is None:
        return
    if declared.members > _MAX_MEMBERS:
        raise RequestError(["body", field], f"the {what} dump's zip directory declares "
                           f"{declared.members} members; a validation dump has at most "
                           f"{_MAX_MEMBERS}")
    rows = max(declared.detections, declared.ground_truth)
    if rows > max_detections:
        keys = _ROW_KEYS["detections" if declared.detections >= declared.ground_truth else "gt"]
        key = next(k for k in keys if declared.shapes.get(k) and declared.shapes[k][0] == rows)
        kind = "detections" if key.startswith("det_") else "ground-truth boxes"
        setting = "FEEDBACK" if what == "feedback" else "FIT"
        raise RequestError(["body", field], f"{key} declares shape {declared.shapes[key]}: "
                           f"{rows} {kind}, more than the limit of {max_detections} per {what} "
                           f"request (DETCAL_MAX_{setting}_DETECTIONS)", status=413)
    if declared.inflated_bytes > max_bytes:
        big = max(declared.sizes, key=declared.sizes.__getitem__)
        raise RequestError(["body", field], f"the {what} dump inflates to "
                           f"{declared.inflated_bytes} bytes (the largest key, {big!r}, shape "
                           f"{declared.shapes[big]}, to {declared.sizes[big]}), more than the "
                           f"limit of {max_bytes} bytes per request (DETCAL_MAX_DUMP_BYTES)",
                           status=413)


def _zip_entries(file: BinaryIO) -> int | None:
    """The member count a zip's end-of-central-directory record declares (zip64 included),
    read from the file's last 64 KiB; None if there is no such record."""
    file.seek(0, os.SEEK_END)
    size = file.tell()
    tail_len = min(size, 65_557)   # the record (22 bytes) and a comment of up to 64 KiB
    file.seek(size - tail_len)
    tail = file.read(tail_len)
    at = tail.rfind(b"PK\x05\x06")
    if at < 0 or len(tail) - at < 22:
        return None
    total = int.from_bytes(tail[at + 10:at + 12], "little")
    loc = at - 20   # zip64: the locator just before names the zip64 record
    if total == 0xFFFF and loc >= 0 and tail[loc:loc + 4] == b"PK\x06\x07":
        file.seek(int.from_bytes(tail[loc + 8:loc + 16], "little"))
        record = file.read(56)
        if record[:4] == b"PK\x06\x06":
            total = int.from_bytes(record[32:40], "little")
    return total
