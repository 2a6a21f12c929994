"""Reading and writing validation dumps (docs/formats.md).

- `load_dump(path, format=...)`: any dump format (npz, parquet, nuscenes, kitti, openpcdet,
  mmdet3d, av2; `calibrators.io.formats`); `save_dump`: validation dump v1, a columnar NPZ.
- `load_nuscenes` / `save_nuscenes`: a nuScenes results JSON plus (optionally) a ground-truth
  JSON in `DetectionBox` form; `detections_from_nuscenes` / `calibrated_document`: a results
  document as the calibrate batch (`calibrators.Detections`) and calibrated detections as a
  results document, each box placed by its identity (its token and row), never by position.
- `open_parquet` / `load_parquet` / `save_parquet` / `ParquetWriter`: a dump as a Parquet
  dataset folder (parts of whole frames) for streamed and distributed fits.
- `file_sha256`: content hash for provenance; `atomic_write`: a file replaced in one rename.
"""

from calibrators.io.atomic import atomic_write
from calibrators.io.formats import FORMATS, load_dump
from calibrators.io.hashing import file_sha256
from calibrators.io.npz import save_dump
from calibrators.io.nuscenes import load_nuscenes
from calibrators.io.nuscenes_batch import calibrated_document, detections_from_nuscenes
from calibrators.io.nuscenes_write import save_nuscenes
from calibrators.io.parquet import ParquetDataset, load_parquet, open_parquet
from calibrators.io.parquet_write import ParquetWriter, save_parquet
from calibrators.profile import ellipses_json, unbounded_none

__all__ = ["FORMATS", "ParquetDataset", "ParquetWriter", "atomic_write",
           "calibrated_document", "detections_from_nuscenes",
           "ellipses_json", "file_sha256", "load_dump",
           "load_nuscenes", "load_parquet",
           "open_parquet", "save_dump", "save_nuscenes", "save_parquet", "unbounded_none"]
