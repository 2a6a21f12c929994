"""A 2-D fit's input: a COCO results file and its instances file (`POST /v1/fit`'s
`coco_results` and `coco_gt`), stored content-addressed like the nuScenes pair, checked by the
request and fit by the job runner (`calibrators.boxes2d.fit_profile_2d`).

The pair is bounded before it is parsed, as the nuScenes pair is: together at most
`DETCAL_MAX_JSON_DUMP_BYTES` (a 413 at `coco_results`), each file read under
`DETCAL_MAX_DUMP_BYTES`; then every field is checked (`read_coco_instances`,
`read_coco_results`: a 422 at the file's form field naming the record and key), the counts
held against `DETCAL_MAX_FIT_DETECTIONS` (413), and the pair against the options
(`check_fit_input_2d`: a 422 at the option or the file).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

from app.http.errors import RequestError
from app.settings import Settings
from app.store import DumpRecord, JobRecord, Store
from calibrators.core.errors import FieldError, OptionError

#: The kinds the two files are stored as (`Store.put_dump`); the runner fits a job whose
#: dump is of `COCO_RESULTS_KIND` as a 2-D fit.
COCO_RESULTS_KIND = "coco-results"
COCO_GT_KIND = "coco-instances"
#: The form fields of the pair.
RESULTS_FIELD, GT_FIELD = "coco_results", "coco_gt"


@dataclass(frozen=True)
class CocoPair:
    """A parsed, checked COCO pair: `detections` (`Detections2D`) and `instances`
    (`CocoInstances`)."""

    detections: Any
    instances: Any


def check_pair_size(results: Any, gt: Any, limit: int) -> None:
    """A 413 at `coco_results` when the two uploads weigh more than `limit` bytes together,
    before either is parsed (`results`, `gt`: FastAPI `UploadFile`s)."""
    sizes = [f.size if f.size is not None else f.file.seek(0, 2) for f in (results, gt)]
    for f in (results, gt):
        f.file.seek(0)
    if sum(sizes) > limit:
        raise RequestError(["body", RESULTS_FIELD], f"the COCO results and instances files "
                           f"weigh {sum(sizes)} bytes together, more than the limit of {limit} "
                           f"bytes per request (DETCAL_MAX_JSON_DUMP_BYTES)", status=413)


def store_pair(store: Store, settings: Settings, options: Any, results: BinaryIO,
               gt: BinaryIO) -> tuple[DumpRecord, str, CocoPair]:
    """Store the pair (after `check_pair_size`), parse and check it against the 2-D
    `options`: the results' stored record, the instances' hash and the checked pair."""
    from calibrators.boxes2d import check_fit_input_2d

    stored = store.put_dump(results, COCO_RESULTS_KIND)
    gt_sha = store.put_dump(gt, COCO_GT_KIND).sha256
    pair = read_pair(store.dump_path(stored.sha256), store.dump_path(gt_sha),
                     settings.max_dump_bytes)
    rows = max(len(pair.detections), len(pair.instances.ground_truth))
    if rows > settings.max_fit_detections:
        raise RequestError(["body", RESULTS_FIELD], f"the COCO pair holds "
                           f"{len(pair.detections)} detections and "
                           f"{len(pair.instances.ground_truth)} annotations, more than the "
                           f"limit of {settings.max_fit_detections} "
                           f"(DETCAL_MAX_FIT_DETECTIONS)", status=413)
    try:
        check_fit_input_2d(pair.detections, pair.instances, options)
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None
    except FieldError as exc:
        raise RequestError(["body", RESULTS_FIELD], f"not a valid COCO results file for "
                                                    f"these instances: {exc}") from None
    return stored, gt_sha, pair


def read_pair(results: Path, instances: Path, max_bytes: int | None) -> CocoPair:
    """The checked pair of the two stored files; a 422 at the field of the file at fault
    (the library's messages name the record and key, never the path)."""
    from calibrators.boxes2d import read_coco_instances, read_coco_results

    parsed = _loaded(lambda: read_coco_instances(instances, max_bytes=max_bytes), GT_FIELD,
                     "COCO instances")
    detections = _loaded(lambda: read_coco_results(results, max_bytes=max_bytes,
                                                   instances=parsed), RESULTS_FIELD,
                         "COCO results")
    return CocoPair(detections, parsed)


def fit_job(store: Store, job: JobRecord, pair: CocoPair | None, progress: Callable[..., None],
            max_bytes: int | None) -> Any:
    """The 2-D profile of a COCO `job`: the pair its request parsed (`pair`), or the stored
    files read again (another process claimed the job)."""
    from calibrators.boxes2d import FitOptions2D, fit_profile_2d

    if pair is None:
        if job.gt_sha256 is None:
            raise ValueError("a COCO fit job needs its instances file")
        pair = read_pair(store.dump_path(job.dump_sha256), store.dump_path(job.gt_sha256),
                         max_bytes)
    progress("fitting", 0.0)
    return fit_profile_2d(pair.detections, pair.instances, FitOptions2D.from_dict(job.options),
                          results_sha256=job.dump_sha256, instances_sha256=job.gt_sha256,
                          progress=progress)


def _loaded(read: Callable[[], Any], field: str, what: str) -> Any:
    try:
        return read()
    except ValueError as exc:   # FieldError included: its message names record and key
        raise RequestError(["body", field], f"not a valid {what} file: {exc}") from None
    except (OSError, RecursionError, MemoryError) as exc:
        raise RequestError(["body", field], f"the {what} file cannot be read "
                                            f"({type(exc).__name__})") from None
