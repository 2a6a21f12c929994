"""Bounded file reads of the format readers (KITTI, OpenPCDet, MMDetection3D, Argoverse 2).

One `ByteBudget` per reader call caps the bytes read from disk, all files together, and
refuses a file before reading past it; errors are FieldErrors naming the file.
"""

from __future__ import annotations

import os
from pathlib import Path

from calibrators.core.errors import FieldError

#: Default cap on the bytes one reader call reads from disk, all files together.
MAX_READ_BYTES = 2 * 2**30


class ByteBudget:
    """Bytes still allowed for one reader call; `read(path, what)` charges each file."""

    def __init__(self, max_bytes: int | None) -> None:
        limit = MAX_READ_BYTES if max_bytes is None else max_bytes
        if isinstance(limit, bool) or not isinstance(limit, int) or limit <= 0:
            raise ValueError(f"max_bytes must be a positive integer, got {max_bytes!r}")
        self.limit = limit
        self.left = limit

    def read(self, path: str | os.PathLike[str], what: str) -> bytes:
        """The file's bytes, refused (FieldError on `what`) before reading past the budget."""
        try:
            with open(path, "rb") as fh:
                size = os.fstat(fh.fileno()).st_size
                if size > self.left:
                    raise FieldError(what, f"{what}: reading it would pass the limit of "
                                           f"{self.limit} bytes for one load (max_bytes)")
                data = fh.read(self.left + 1)
        except FieldError:
            raise
        except FileNotFoundError:
            raise FieldError(what, f"{what}: no such file") from None
        except OSError as exc:
            raise FieldError(what, f"{what}: cannot be read: {exc.strerror or exc}") from None
        if len(data) > self.left:
            raise FieldError(what, f"{what}: reading it would pass the limit of {self.limit} "
                                   "bytes for one load (max_bytes)")
        self.left -= len(data)
        return data


def check_file(path: str | os.PathLike[str], what: str) -> Path:
    """`path` as a Path that exists (FieldError naming `what` otherwise)."""
    p = Path(path)
    if not p.exists():
        raise FieldError(what, f"{what}: no such file or folder")
    return p
