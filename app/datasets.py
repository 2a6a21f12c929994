"""Parquet datasets the server fits in place (POST /v1/fit with the form field `dataset`).

A dataset is named by its path relative to `DETCAL_DATASETS_DIR`; nothing outside that folder
can be named (no absolute paths, no `..`, no symbolic link leading out), and without the
setting datasets are refused. A fit job stores the name as a small JSON upload of kind
`parquet-dataset`, so the job, its provenance and the clean-up treat it like any stored dump;
the job resolves the name again when it runs (`calibrators.fit_stream.fit_profile_stream`).
"""

from __future__ import annotations

import json
from pathlib import Path, PurePosixPath

from app.errors import RequestError

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
    return path


def dataset_reference(name: str) -> bytes:
    """The stored form of a dataset name (the job's 'dump')."""
    return json.dumps({"dataset": name}, sort_keys=True).encode()


def referenced_dataset(root: Path | None, stored: Path) -> Path:
    """The folder a stored dataset reference names, checked again (the setting may have
    changed since the job was queued)."""
    name = json.loads(stored.read_text())["dataset"]
    try:
        return resolve_dataset(root, name)
    except RequestError as exc:
        raise ValueError(exc.msg) from None
