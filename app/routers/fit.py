"""POST /v1/fit: upload a validation dump (NPZ v1 or nuScenes results + GT JSON) and queue a fit."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated, Literal

from fastapi import APIRouter, File, Form, UploadFile, status
from fastapi.responses import JSONResponse

from app.deps import AdminDep, RunnerDep, SettingsDep, StoreDep
from app.errors import RequestError
from app.schemas.common import ErrorResponse, ProfileName
from app.schemas.profiles import FitAccepted

if TYPE_CHECKING:
    from calibrators import Dump

router = APIRouter(prefix="/v1", tags=["fit"])

_DIMS = ("x", "y", "z", "w", "l", "h", "yaw", "vx", "vy")


def _dims(text: str) -> list[str]:
    dims = [d.strip() for d in text.split(",") if d.strip()]
    bad = [d for d in dims if d not in _DIMS]
    if not dims or bad or len(set(dims)) != len(dims):
        raise RequestError(["body", "dims"], f"dims must be distinct box fields from "
                                             f"{list(_DIMS)} separated by commas, got {text!r}")
    return dims


@router.post("/fit", status_code=status.HTTP_202_ACCEPTED,
             responses={202: {"model": FitAccepted}, 401: {"model": ErrorResponse},
                        403: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                        422: {"model": ErrorResponse}})
def fit(
    _: AdminDep, store: StoreDep, runner: RunnerDep, settings: SettingsDep,
    dump: Annotated[UploadFile | None, File(description="Validation dump v1 (NPZ).")] = None,
    results: Annotated[UploadFile | None, File(description="nuScenes results JSON.")] = None,
    gt: Annotated[UploadFile | None, File(description="Ground truth JSON for `results`.")] = None,
    name: Annotated[ProfileName | None, Form(description="Profile name (default: the "
                                                         "configured default).")] = None,
    threshold: Annotated[float, Form(gt=0.0, allow_inf_nan=False)] = 2.0,
    dims: Annotated[str, Form(description="Regression dims, comma separated.")] = "x,y",
    cov_source: Annotated[Literal["auto", "given", "layers", "none"], Form()] = "auto",
    holdout: Annotated[float, Form(ge=0.0, lt=1.0)] = 0.0,
    min_score: Annotated[float | None, Form(ge=0.0, le=1.0)] = None,
    min_samples: Annotated[int, Form(ge=1)] = 50,
    seed: Annotated[int, Form(ge=0)] = 0,
    modulation: Annotated[bool, Form(description="Logits modulation before temperature "
                                                 "scaling (needs every decoder layer's "
                                                 "logits: an NPZ dump with L >= 2).")] = False,
    activate: Annotated[bool, Form(description="Activate the new version when it lands (the "
                                               "first version of a name always is).")] = False,
) -> JSONResponse:
    """Store the uploaded dump (content-addressed) and queue a fit job; 202 with its id."""
    if (dump is None) == (results is None) or (results is None) != (gt is None):
        raise RequestError(["body"], "upload either `dump` (NPZ) or both `results` and `gt` "
                                     "(nuScenes JSON)")
    from calibrators.io import load_dump, load_nuscenes

    profile_name = name or settings.default_profile
    options = {"threshold": threshold, "dims": _dims(dims), "cov_source": cov_source,
               "holdout": holdout, "min_score": min_score, "min_samples": min_samples,
               "seed": seed, "modulation": modulation}
    if dump is not None:
        stored = store.put_dump(dump.file, "npz")
        gt_sha = None
        loaded = _check(lambda: load_dump(store.dump_path(stored.sha256)), "dump")
    else:
        stored = store.put_dump(results.file, "nuscenes-results")  # type: ignore[union-attr]
        gt_sha = store.put_dump(gt.file, "nuscenes-gt").sha256  # type: ignore[union-attr]
        loaded = _check(lambda: load_nuscenes(store.dump_path(stored.sha256),
                                              store.dump_path(gt_sha)), "results")
    if modulation and loaded.n_layers < 2:
        raise RequestError(["body", "modulation"], "logits modulation needs every decoder "
                                                   f"layer's logits; the upload has "
                                                   f"{loaded.n_layers} layer")
    job = store.create_job(profile_name, options, stored.sha256, gt_sha, activate)
    runner.notify()
    body = FitAccepted(job_id=job.id, status_url=f"/v1/jobs/{job.id}",
                       dump_sha256=stored.sha256, name=profile_name)
    return JSONResponse(body.model_dump(), status_code=status.HTTP_202_ACCEPTED,
                        headers={"Location": body.status_url})


def _check(load: Callable[[], Dump], field: str) -> Dump:
    """Load the stored upload once so a malformed dump is a 422 now, not a failed job later."""
    try:
        return load()
    except (ValueError, KeyError, OSError, EOFError) as exc:
        raise RequestError(["body", field], f"not a valid validation dump: {exc}") from None
