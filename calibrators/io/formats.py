"""`load_dump(path, format=...)`: one entry point for every dump format (docs/formats.md).

| format      | reader                      | input                                              |
|-------------|-----------------------------|----------------------------------------------------|
| `npz`       | `npz.load_dump`             | validation dump v1 (`.npz`)                        |
| `parquet`   | `parquet.load_parquet`      | Parquet dataset folder (`detcal.json` inside)      |
| `nuscenes`  | `nuscenes.load_nuscenes`    | nuScenes (or MMDetection3D) results JSON (`.json`) |
| `kitti`     | `kitti.load_kitti`          | KITTI object / tracking label text with scores     |
| `openpcdet` | `openpcdet.load_openpcdet`  | OpenPCDet `result.pkl` (restricted unpickler)      |
| `mmdet3d`   | `mmdet3d.load_mmdet3d`      | `pred_instances_3d` saved as NPZ arrays            |
| `av2`       | `argoverse2.load_av2`       | Argoverse 2 detections feather                     |

Without `format` it reads validation dump v1 (`npz`), as it always has: other formats are
named (`detcal convert --from FORMAT`), never guessed from a suffix. Keyword options go to
the reader; `ground_truth=` names the ground truth where the format keeps it in another file.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

from calibrators.core.errors import FieldError
from calibrators.data import Dump

FORMATS = ("npz", "parquet", "nuscenes", "kitti", "openpcdet", "mmdet3d", "av2")


def load_dump(path: str | os.PathLike[str] | BinaryIO, format: str | None = None,
              **options: Any) -> Dump:
    """Read a dump of any of `FORMATS` into a validated `Dump` (see the module docstring).

    Raises FieldError (a ValueError) on `format` for an unknown format, and the
    reader's errors (naming the file, line or field) otherwise.
    """
    name = "npz" if format is None else format
    if name not in FORMATS:
        raise FieldError("format", f"format must be one of {list(FORMATS)}, got {name!r}")
    return _reader(name)(path, **options)


def inputs_sha256(*paths: str | os.PathLike[str] | None) -> str:
    """One hex digest of a reader's input files, for a profile's provenance: a file's
    `file_sha256`, a folder's every file below it (sorted by relative path, names included),
    the parts joined by newlines (None parts skipped); one plain file gives its own hash."""
    from calibrators.io.hashing import file_sha256

    parts = []
    for path in (p for p in paths if p is not None):
        root = Path(path)
        if root.is_dir():
            files = sorted(p for p in root.rglob("*") if p.is_file())
            parts += [f"{f.relative_to(root).as_posix()} {file_sha256(f)}" for f in files]
        else:
            parts.append(file_sha256(root))
    if len(parts) == 1 and not Path(next(p for p in paths if p is not None)).is_dir():
        return parts[0]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _reader(name: str) -> Callable[..., Dump]:
    """The reader function of a format (imported on use: pyarrow only when needed)."""
    if name == "npz":
        from calibrators.io.npz import load_dump as reader
    elif name == "parquet":
        from calibrators.io.parquet import load_parquet as reader
    elif name == "nuscenes":
        from calibrators.io.nuscenes import load_nuscenes

        def reader(path: Any, ground_truth: Any = None, **kw: Any) -> Dump:
            return load_nuscenes(path, ground_truth, **kw)
    elif name == "kitti":
        from calibrators.io.kitti import load_kitti as reader
    elif name == "openpcdet":
        from calibrators.io.openpcdet import load_openpcdet as reader
    elif name == "mmdet3d":
        from calibrators.io.mmdet3d import load_mmdet3d as reader
    else:
        from calibrators.io.argoverse2 import load_av2 as reader
    return reader
