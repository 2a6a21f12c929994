"""Reading and writing validation dumps (docs/formats.md).

- `load_dump` / `save_dump`: validation dump v1, a columnar NPZ.
- `load_nuscenes` / `save_nuscenes`: a nuScenes results JSON plus a ground-truth JSON in
  `DetectionBox` form.
- `file_sha256`: content hash for provenance.
"""

from calibrators.io.hashing import file_sha256
from calibrators.io.npz import load_dump, save_dump
from calibrators.io.nuscenes import load_nuscenes, save_nuscenes

__all__ = ["file_sha256", "load_dump", "load_nuscenes", "save_dump", "save_nuscenes"]
