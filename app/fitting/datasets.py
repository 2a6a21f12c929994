"""Parquet datasets the server fits in place (POST /v1/fit with the form field `dataset`).

A dataset is named by its path relative to `DETCAL_DATASETS_DIR`; nothing outside that folder
can be named (no absolute paths, no `..`, no symbolic link leading out: not the folder, nor
anything inside it, its parts and sub-folders included), and without the setting datasets are
refused. No message shows a server path: the folder is named by its relative name. A fit job
stores the name as a small JSON upload of kind `parquet-dataset`, so the job, its provenance and
the clean-up treat it like any stored dump; the job resolves the name again when it runs
(`calibrators.fit._stream.fit_profile_stream`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING

from app.http.errors import RequestError

if TYPE_CHECKING:
    from calibrators.io.parquet import ParquetDataset

DATASET_KIND = "parquet-dataset"
LOC = ["body", "dataset"]


def resolve_dataset(root: Path | None, name: str) -> Path:
    """The folder of dataset `name` under `root`; a 422 at `dataset` if datasets are off or
    `name` leads anywhere else."""
    if root is None:
        raise RequestError(LOC, "this server fits no datasets in place: set DETCAL_DATASETS_DIR "
                                "to the folder that holds them, or upload a dump")
    rel = PurePosixPath(name)
    if not name or rel.is_absolute() or ".." in rel.parts or "\\" in name or "\x00" in name:
        raise RequestError(LOC, f"dataset must be a path relative to DETCAL_DATASETS_DIR "
                                f"without '..', got {name!r}")
    base = root.resolve()
    path = (base / rel).resolve()
    if not path.is_relative_to(base):
        raise RequestError(LOC, f"dataset {name!r} leads outside DETCAL_DATASETS_DIR")
    if not path.is_dir():
        raise RequestError(LOC, f"dataset {name!r} is not a folder under DETCAL_DATASETS_DIR "
                                f"(detcal convert writes one)")
    outside = _link_leading_out(base, path)
    if outside is not None:
        raise RequestError(LOC, f"dataset {name!r}: {outside} is a link leading outside "
                                f"DETCAL_DATASETS_DIR")
    return path


def _link_leading_out(base: Path, path: Path) -> str | None:
    """The first entry of the folder `path` (at any depth, links not followed) that resolves
    outside `base`, as a path relative to `path`; None if there is none."""
    for folder, dirs, files in os.walk(path, followlinks=False):
        dirs.sort()
        for entry in sorted((*dirs, *files)):
            full = Path(folder) / entry
            if not full.resolve().is_relative_to(base):
                return full.relative_to(path).as_posix()
    return None


def open_dataset(root: Path | None, name: str, max_part_detections: int) -> ParquetDataset:
    """Dataset `name` opened (metadata and schemas checked, `resolve_dataset`'s rules): a 422
    at `dataset` naming what is wrong without a server path, a 413 when a part holds more
    rows than `max_part_detections` (what a streamed fit holds in memory at once)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from calibrators.io.parquet import open_parquet

    path = resolve_dataset(root, name)
    try:
        ds = open_parquet(path)
    except (ValueError, OSError) as exc:
        raise RequestError(LOC, f"dataset {name!r}: {redact_paths(str(exc), root)}") from None
    for part in ds.parts:
        for sub, claimed in (("detections", part.n_detections),
                             ("ground_truth", part.n_ground_truth)):
            try:
                rows = pq.read_metadata(path / sub / f"{part.name}.parquet").num_rows
            except (OSError, pa.ArrowException) as exc:
                raise RequestError(LOC, f"dataset {name!r}: {sub}/{part.name}.parquet: "
                                        f"{redact_paths(str(exc), root)}") from None
            if max(rows, claimed) > max_part_detections:
                raise RequestError(LOC, f"dataset {name!r}: part {sub}/{part.name}.parquet "
                                        f"holds {max(rows, claimed)} rows, more than the limit "
                                        f"of {max_part_detections} per part "
                                        f"(DETCAL_MAX_FIT_DETECTIONS)", status=413)
    return ds


def redact_paths(text: str, root: Path | None, label: str = "<DETCAL_DATASETS_DIR>") -> str:
    """`text` with every occurrence of the folder `root` (as given, absolute and resolved)
    replaced by `label`: messages that reach a client never carry a server path."""
    if root is None:
        return text
    for form in sorted({str(root.resolve()), str(root), os.path.abspath(root)}, key=len,
                       reverse=True):
        if form not in (".", "/", ""):
            text = text.replace(form, label)
    return text


def dataset_reference(name: str) -> bytes:
    """The stored form of a dataset name (the job's 'dump')."""
    return json.dumps({"dataset": name}, sort_keys=True).encode()


def referenced_dataset(root: Path | None, stored: Path) -> Path:
    """The folder a stored dataset reference names, checked again (the setting may have
    changed since the job was queued)."""
    name = json.loads(stored.read_text())["dataset"]
    try:
        return resolve_dataset(root, name)   # links are checked again: they may have moved
    except RequestError as exc:
        raise ValueError(exc.msg) from None
