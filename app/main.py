"""The FastAPI application: `create_app(settings)` and the lifespan that opens the store,
loads the active profiles and starts the fit-job runner."""

from __future__ import annotations

import gc
import logging
import sys
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, asynccontextmanager

from fastapi import Depends, FastAPI

from app.bundled_detectors import DetectorService
from app.calibrate.arrow_route import ArrowCalibrateMiddleware
from app.calibrate.cache import ProfileCache
from app.calibrate.engine import CalibrateEngine
from app.calibrate.parent_watch import die_with_supervisor
from app.calibrate.runner import CalibrateRunner
from app.dashboard.page import DashboardRenderer
from app.fitting.runner import JobRunner
from app.http.api_docs import install_docs
from app.http.deps import AdminBeforeBodyMiddleware, refuse_empty_form_fields
from app.http.errors import install_handlers
from app.http.fields import FieldsMiddleware, fields_query
from app.http.head import HeadAsGetMiddleware
from app.http.json_body import install_openapi
from app.http.limits import BodySizeLimitMiddleware
from app.http.metrics import MetricsMiddleware, ServiceMetrics
from app.routers import (
    aliases,
    audit,
    calibrate,
    dashboard,
    detect,
    feedback,
    fit,
    jobs,
    liveness,
    metrics,
    profile_health,
    profiles,
)
from app.settings import Settings, get_settings
from app.store import Store
from calibrators.core.version import detcal_version

log = logging.getLogger("detcal.app")

DESCRIPTION = """Post-hoc calibration of DETR-family 3D and 2-D detectors: fit a versioned
calibration profile (score calibration, covariance scaling, coverage regions) on a validation
dump or a COCO results file, then turn raw detections into calibrated scores, covariances and
uncertainty ellipses, or calibrated 2-D boxes with conformal box regions.
Admin endpoints need `Authorization: Bearer <DETCAL_ADMIN_TOKEN>`."""


#: The interpreter's thread switch interval while serving (default 5 ms).
SWITCH_INTERVAL_S = 0.001


def _start_services(app: FastAPI, settings: Settings) -> tuple[Store, JobRunner]:
    """Open the store, load the active profiles and start the fit-job runner on `app.state`."""
    settings.data_dir.mkdir(parents=True, exist_ok=True)
    store = Store(settings.sqlalchemy_url, settings.dumps_dir)
    cache = ProfileCache(store)
    try:
        loaded = cache.load_active()
        log.info("loaded active profiles: %s", ", ".join(p.record.ref for p in loaded)
                 or "none")
    except ValueError as exc:  # a stored profile that no longer parses must not stop us
        log.error("could not load the active profiles: %s", exc)
    app.state.calibrator = CalibrateRunner(
        CalibrateEngine(cache, settings.default_profile, settings.max_detections), settings)
    runner = JobRunner(store, workers=settings.fit_workers,
                       max_dump_bytes=settings.max_dump_bytes,
                       datasets_dir=settings.datasets_dir)
    app.state.store, app.state.cache, app.state.runner = store, cache, runner
    app.state.metrics.attach_store(store, settings.health_window_frames)
    runner.start()
    return store, runner


def _lifespan(settings: Settings) -> Callable[[FastAPI], AbstractAsyncContextManager[None]]:
    """The app's lifespan: services started on entry, stopped on exit."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Worker threads calibrating a large request hold the GIL in long stretches; a
        # shorter switch interval lets the event loop answer /healthz in between.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        die_with_supervisor()   # a `--workers N` worker ends with its supervisor, even on SIGKILL
        store, runner = _start_services(app, settings)
        # The modules, the app and the loaded profiles live as long as the process: frozen
        # out of the garbage collector's full collections, which would otherwise walk them
        # all (tens of ms) whenever a large request's short-lived objects trigger one.
        gc.freeze()
        try:
            yield
        finally:
            runner.stop()
            app.state.calibrator.close()
            store.close()

    return lifespan


def _include_routers(app: FastAPI) -> None:
    # aliases and profile_health before profiles: /{name}/aliases is not /{name}/{version}
    summary = {jobs, profile_health, profiles}   # large answers: `?fields=` trims them
    for module in (liveness, metrics, calibrate, fit, jobs, aliases, profile_health, profiles,
                   feedback, audit, detect, dashboard):
        app.include_router(module.router, dependencies=[Depends(fields_query)]
                           if module in summary else None)


def _add_middleware(app: FastAPI, settings: Settings) -> None:
    app.add_middleware(FieldsMiddleware)
    app.add_middleware(ArrowCalibrateMiddleware)   # innermost: inside the limits and metrics
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_request_bytes,
                       upload_bytes=settings.max_upload_bytes)
    app.add_middleware(AdminBeforeBodyMiddleware)
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics)
    app.add_middleware(HeadAsGetMiddleware)   # outermost: HEAD wherever GET is allowed


def create_app(settings: Settings | None = None) -> FastAPI:
    """A new app bound to `settings` (default: read from the environment)."""
    settings = settings or get_settings()
    app = FastAPI(title="detcal", version=detcal_version(), description=DESCRIPTION,
                  lifespan=_lifespan(settings), dependencies=[Depends(refuse_empty_form_fields)],
                  docs_url=None, redoc_url=None)
    install_docs(app)   # /docs and /redoc from the installed package, never a CDN
    app.state.settings = settings
    app.state.metrics = ServiceMetrics()
    app.state.detectors = DetectorService()
    app.state.dashboard = DashboardRenderer()
    install_handlers(app)
    install_openapi(app)
    _include_routers(app)
    _add_middleware(app, settings)
    return app
