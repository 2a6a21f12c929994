"""POST /v1/fit: upload a validation dump (NPZ v1 or nuScenes results + GT JSON) and queue a fit."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Annotated

from fastapi import APIRouter, File, Form, UploadFile, status
from fastapi.responses import JSONResponse

from app.deps import AdminDep, RunnerDep, SettingsDep, StoreDep
from app.errors import RequestError
from app.schemas.common import ErrorResponse, ProfileName
from app.schemas.fit import FitForm
from app.schemas.profiles import FitAccepted
from calibrators.fit import check_fit_input
from calibrators.options import FitOptions, OptionError

if TYPE_CHECKING:
    from calibrators import Dump

router = APIRouter(prefix="/v1", tags=["fit"])

@router.post("/fit", status_code=status.HTTP_202_ACCEPTED,
             responses={202: {"model": FitAccepted}, 401: {"model": ErrorResponse},
                        403: {"model": ErrorResponse}, 413: {"model": ErrorResponse},
                        422: {"model": ErrorResponse}})
def fit(
    _: AdminDep, store: StoreDep, runner: RunnerDep, settings: SettingsDep,
    options: Annotated[FitForm, Form()],
    dump: Annotated[UploadFile, File(description="Validation dump v1 (NPZ).")] = None,
    results: Annotated[UploadFile, File(description="nuScenes results JSON.")] = None,
    gt: Annotated[UploadFile, File(description="Ground truth JSON for `results`.")] = None,
    name: Annotated[ProfileName | None, Form(description="Profile name (default: the "
                                                         "configured default).")] = None,
    activate: Annotated[bool, Form(description="Activate the new version when it lands (the "
                                               "first version of a name always is).")] = False,
) -> JSONResponse:
    """Store the uploaded dump (content-addressed) and queue a fit job; 202 with its id."""
    if (dump is None) == (results is None) or (results is None) != (gt is None):
        raise RequestError(["body"], "upload either `dump` (NPZ) or both `results` and `gt` "
                                     "(nuScenes JSON)")
    from calibrators.io import load_dump, load_nuscenes

    profile_name = name or settings.default_profile
    try:
        fit_options = FitOptions.from_dict(options.model_dump())
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None
    if dump is not None:
        stored = store.put_dump(dump.file, "npz")
        gt_sha = None
        loaded = _check(lambda: load_dump(store.dump_path(stored.sha256),
                                          max_bytes=settings.max_dump_bytes), "dump")
    else:
        stored = store.put_dump(results.file, "nuscenes-results")  # type: ignore[union-attr]
        gt_sha = store.put_dump(gt.file, "nuscenes-gt").sha256  # type: ignore[union-attr]
        loaded = _check(lambda: load_nuscenes(store.dump_path(stored.sha256),
                                              store.dump_path(gt_sha),
                                              max_bytes=settings.max_dump_bytes), "results")
    try:
        check_fit_input(loaded, fit_options)
    except OptionError as exc:
        raise RequestError(["body", exc.field], str(exc)) from None
    job = store.create_job(profile_name, fit_options.to_dict(), stored.sha256, gt_sha, activate)
    runner.notify()
    body = FitAccepted(job_id=job.id, status_url=f"/v1/jobs/{job.id}",
                       dump_sha256=stored.sha256, name=profile_name)
    return JSONResponse(body.model_dump(), status_code=status.HTTP_202_ACCEPTED,
                        headers={"Location": body.status_url})


def _check(load: Callable[[], Dump], field: str) -> Dump:
    """Load the stored upload once so a malformed dump is a 422 now, not a failed job later.

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
