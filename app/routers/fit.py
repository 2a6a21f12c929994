"""POST /v1/fit: upload a validation dump (NPZ v1 or nuScenes results + GT JSON), or a COCO
results + instances pair for a 2-D profile, and queue a fit."""

from __future__ import annotations

import io
import json
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, File, Form, UploadFile, status
from fastapi.responses import JSONResponse

from app.fitting.coco import check_pair_size, store_pair
from app.fitting.datasets import DATASET_KIND, dataset_reference, open_dataset
from app.fitting.options import options_of
from app.fitting.uploads import check_declared, declared_npz, load_upload
from app.http.deps import AdminIdDep, RunnerDep, SettingsDep, StoreDep
from app.http.errors import RequestError
from app.schemas.fit import FitForm
from app.schemas.profiles import FitAccepted
from app.schemas.types import ErrorResponse, ProfileName
from app.settings import Settings
from app.store import AuditEntry, DumpRecord, Store
from calibrators.core.errors import OptionError
from calibrators.fit import FitOptions, check_fit_input

router = APIRouter(prefix="/v1", tags=["fit"])

_BOX = {"sample_token": "sample-0", "translation": [10.0, 5.0, 0.8], "size": [1.9, 4.5, 1.6],
        "rotation": [1.0, 0.0, 0.0, 0.0], "velocity": [0.0, 0.0],
        "ego_translation": [10.0, 5.0, 0.8], "num_pts": 12, "detection_name": "car",
        "detection_score": 0.8, "attribute_name": ""}
#: A request the route accepts (202) with nothing but text: a one-box nuScenes results file
#: and its ground truth, as the file parts' contents (a real fit needs thousands of boxes;
#: this job fails with the reason, visible at its status URL).
_EXAMPLE = {"name": "example",
            "results": json.dumps({"meta": {"use_lidar": True}, "results": {"sample-0": [_BOX]}}),
            "gt": json.dumps({"meta": {}, "results": {"sample-0": [_BOX]}})}

@router.post("/fit", status_code=status.HTTP_202_ACCEPTED,
             openapi_extra={"requestBody": {"content": {"multipart/form-data": {
                 "examples": {"nuscenes": {"summary": "one-box nuScenes results + GT",
                                           "value": _EXAMPLE}}}}}},
             responses={202: {"model": FitAccepted}, 401: {"model": ErrorResponse},
                        403: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                        422: {"model": ErrorResponse}})
def fit(
    token: AdminIdDep, store: StoreDep, runner: RunnerDep, settings: SettingsDep,
    options: Annotated[FitForm, Form()],
    dump: Annotated[UploadFile, File(description="Validation dump v1 (NPZ).")] = None,
    results: Annotated[UploadFile, File(description="nuScenes results JSON.")] = None,
    gt: Annotated[UploadFile, File(description="Ground truth JSON for `results`.")] = None,
    coco_results: Annotated[UploadFile, File(description="COCO results JSON of a 2-D "
                                                         "detector (with `coco_gt`): fits a "
                                                         "2-D profile.")] = None,
    coco_gt: Annotated[UploadFile, File(description="COCO instances JSON for "
                                                    "`coco_results`.")] = None,
    dataset: Annotated[str | None, Form(
        max_length=1024, description="A Parquet dataset (`detcal convert`) to fit in place "
                                     "and part by part: its path relative to "
                                     "`DETCAL_DATASETS_DIR`.")] = None,
    name: Annotated[ProfileName | None, Form(description="Profile name (default: the "
                                                         "configured default).")] = None,
    activate: Annotated[bool, Form(description="Activate the new version when it lands (the "
                                               "first version of a name always is).")] = False,
) -> JSONResponse:
    """Store the uploaded dump (content-addressed) and queue a fit job; 202 with its id."""
    coco = _check_forms(dump, results, gt, dataset, coco_results, coco_gt)
    profile_name = name or settings.default_profile
    fit_options = _fit_options(options, coco)
    if coco:
        check_pair_size(coco_results, coco_gt, settings.max_json_dump_bytes)
        stored, gt_sha, parsed = store_pair(store, settings, fit_options,
                                            coco_results.file,  # type: ignore[union-attr]
                                            coco_gt.file)  # type: ignore[union-attr]
    else:
        stored, gt_sha, parsed = _store_checked(store, settings, fit_options, dump, results,
                                                gt, dataset)
    if parsed is not None:   # the job fits this very parse (app.fitting.handoff)
        runner.parsed.put((stored.sha256, gt_sha), parsed)
    audit = AuditEntry("fit", profile_name, token, {"dump_sha256": stored.sha256,
                                                    "activate": activate})
    job = store.create_job(profile_name, fit_options.to_dict(), stored.sha256, gt_sha, activate,
                           audit)
    runner.notify()
    body = FitAccepted(job_id=job.id, status_url=f"/v1/jobs/{job.id}",
                       dump_sha256=stored.sha256, name=profile_name)
    return JSONResponse(body.model_dump(), status_code=status.HTTP_202_ACCEPTED,
                        headers={"Location": body.status_url})


def _check_forms(dump: UploadFile | None, results: UploadFile | None, gt: UploadFile | None,
                 dataset: str | None, coco_results: UploadFile | None,
                 coco_gt: UploadFile | None) -> bool:
    """A 422 unless the request gives exactly one form of fit input; whether it is the COCO
    pair."""
    coco = coco_results is not None or coco_gt is not None
    forms = (dump is not None) + (results is not None or gt is not None) + \
        (dataset is not None) + coco
    if forms != 1 or (results is None) != (gt is None) \
            or (coco_results is None) != (coco_gt is None):
        raise RequestError(["body"], "upload either `dump` (NPZ) or both `results` and `gt` "
                                     "(nuScenes JSON), or name a `dataset`, or upload both "
                                     "`coco_results` and `coco_gt` (COCO JSON, a 2-D fit)")
    return coco


def _fit_options(options: FitForm, coco: bool) -> Any:
    """The form's options of a 3-D fit, or of a 2-D one for a COCO pair; a 422 at the option
    the library refuses or that the other kind of fit takes."""
    try:
        return options_of(options.model_dump(), set(options.model_fields_set), coco)
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None


def _store_checked(store: Store, settings: Settings, fit_options: FitOptions,
                   dump: UploadFile | None, results: UploadFile | None, gt: UploadFile | None,
                   dataset: str | None) -> tuple[DumpRecord, str | None, Any]:
    """Store the fit input and check it loads and fits `fit_options`: its stored record, the
    ground truth's hash (None but for nuScenes JSON) and the checked dump the job is to fit
    (None for a dataset, which the job reads part by part)."""
    stored, gt_sha, loaded = _store_input(store, settings, fit_options, dump, results, gt,
                                          dataset)
    if max(loaded.n_detections, len(loaded.gt_labels)) > settings.max_fit_detections:
        raise RequestError(["body", "dump" if gt_sha is None else "results"],
                           f"the fit dump holds {loaded.n_detections} detections and "
                           f"{len(loaded.gt_labels)} ground-truth boxes, more than the limit of "
                           f"{settings.max_fit_detections} (DETCAL_MAX_FIT_DETECTIONS)", status=413)
    try:
        check_fit_input(loaded, fit_options)
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None
    return stored, gt_sha, None if dataset is not None else loaded


def _store_input(store: Store, settings: Settings, fit_options: FitOptions,
                 dump: UploadFile | None, results: UploadFile | None, gt: UploadFile | None,
                 dataset: str | None) -> tuple[DumpRecord, str | None, Any]:
    """Store the one form of fit input given and load it: the stored record, the ground
    truth's hash and the loaded dump."""
    from calibrators.io import load_dump, load_nuscenes

    if dataset is not None:
        stored, loaded = _dataset(store, settings.datasets_dir, dataset, fit_options,
                                  settings.max_fit_detections)
        return stored, None, loaded
    if dump is not None:
        check_declared(declared_npz(dump.file), max_bytes=settings.max_dump_bytes,
                       max_detections=settings.max_fit_detections, field="dump", what="fit")
        stored = store.put_dump(dump.file, "npz")
        loaded = load_upload(lambda: load_dump(store.dump_path(stored.sha256),
                                               max_bytes=settings.max_dump_bytes), "dump")
        return stored, None, loaded
    _check_json_pair(results, gt, settings.max_json_dump_bytes)  # type: ignore[arg-type]
    stored = store.put_dump(results.file, "nuscenes-results")  # type: ignore[union-attr]
    gt_sha = store.put_dump(gt.file, "nuscenes-gt").sha256  # type: ignore[union-attr]
    loaded = load_upload(lambda: load_nuscenes(store.dump_path(stored.sha256),
                                               store.dump_path(gt_sha),
                                               max_bytes=settings.max_dump_bytes), "results")
    return stored, gt_sha, loaded


def _check_json_pair(results: UploadFile, gt: UploadFile, limit: int) -> None:
    """A 413 at `results` when the nuScenes pair is larger than `DETCAL_MAX_JSON_DUMP_BYTES`
    together (what parsing it would take in memory), before either is parsed."""
    sizes = [f.size if f.size is not None else f.file.seek(0, 2) for f in (results, gt)]
    for f in (results, gt):
        f.file.seek(0)
    if sum(sizes) > limit:
        raise RequestError(["body", "results"], f"the nuScenes results and ground truth weigh "
                           f"{sum(sizes)} bytes together, more than the limit of {limit} bytes "
                           f"per request (DETCAL_MAX_JSON_DUMP_BYTES)", status=413)


def _dataset(store: Store, root: Path | None, name: str, options: FitOptions,
             max_part_detections: int) -> tuple[DumpRecord, Any]:
    """The stored reference of a dataset fit in place and its empty dump (for the option
    checks): a 422 at `dataset` for a name outside `root` (links included) or a bad dataset,
    a 413 for a part too large, a 422 at the option for one a streamed fit cannot
    reproduce."""
    from calibrators.fit import check_stream_options

    ds = open_dataset(root, name, max_part_detections)
    empty = load_upload(ds.empty_dump, "dataset")
    try:
        check_stream_options(options, score_mode=ds.score_mode)
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None
    return store.put_dump(io.BytesIO(dataset_reference(name)), DATASET_KIND), empty
