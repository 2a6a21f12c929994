"""GET /: the dashboard (server-rendered HTML with inline SVG plots; works offline)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse

from app.calibrate.cache import LoadedProfile
from app.dashboard.health_series import health_section
from app.dashboard.page import (
    DashboardRenderer,
    before_after_table,
    per_class_table,
    region_table,
    render_page,
    uptime,
    versions_table,
)
from app.feedback.health_document import health_document
from app.http.deps import CacheDep, MetricsDep, SettingsDep, StoreDep
from app.store import NotFoundError
from calibrators import ProfileReport
from calibrators.core.vocab import PROFILE_KINDS

router = APIRouter(tags=["dashboard"])


async def _renderer(request: Request) -> DashboardRenderer:
    return request.app.state.dashboard


RendererDep = Annotated[DashboardRenderer, Depends(_renderer)]


@router.get("/", response_class=HTMLResponse)
def dashboard(request: Request, store: StoreDep, cache: CacheDep, settings: SettingsDep,
              metrics: MetricsDep, renderer: RendererDep) -> HTMLResponse:
    """The dashboard: health, request rates, profiles, calibration health from feedback,
    before/after report and plots."""
    ok = store.ping()
    status = {"store": "ok" if ok else "unreachable"}
    loaded = note = None
    try:
        loaded = cache.resolve(settings.default_profile, settings.default_profile,
                               kinds=PROFILE_KINDS)
        status["active profile"] = "ok"
    except (NotFoundError, ValueError) as exc:
        status["active profile"] = str(exc)
    status["readiness"] = "ready" if ok and loaded is not None else "not ready"
    report_html = bev_html = versions_html = health_html = ""
    if loaded is not None and loaded.kind != "3d":   # a 2-D profile: its own panels
        from app.dashboard.panels2d import profile_summary

        note = profile_summary(loaded, versions_table(store.versions(loaded.record.name)))
        report_html = renderer.panels_2d(loaded)
        bev_html = ("<p class='note'>A 2-D profile has no bird's-eye view: one of its held-out "
                    "images is drawn above.</p>")
        health_html = ("<p class='note'>Labelled feedback is measured for 3-D profiles only."
                       "</p>")
        loaded = None
    if loaded is not None:
        versions_html = versions_table(store.versions(loaded.record.name))
        health_html = health_section(health_document(store, loaded,
                                                     settings.health_window_frames))
        report_html = _report_html(loaded, renderer)
        bev_html = renderer.bev(loaded, request.app.state.detectors, settings.dashboard_sensor,
                                settings.dashboard_seed)
    page = render_page(
        version=request.app.version, status=status, uptime_s=uptime(metrics.started),
        requests=metrics.request_totals(), names=store.names(),
        default_name=settings.default_profile, loaded=loaded, versions_html=versions_html,
        report_html=report_html, bev_html=bev_html, jobs=store.recent_jobs(8),
        health_html=health_html, profile_note=note)
    return HTMLResponse(page)


def _report_html(loaded: LoadedProfile, renderer: DashboardRenderer) -> str:
    """Before/after tables (fit and held-out part), served-region coverage per class × range
    (held-out part when there is one) and the plots of the active profile's report."""
    report = ProfileReport.from_dict(loaded.profile.report)
    if report is None:
        return "<p class='note'>This profile has no report (it was not fit by detcal).</p>"
    held = report.holdout
    tables = ("<div class='plots'><div><h3>fit part</h3>" + before_after_table(report.fit)
              + "</div>" + (("<div><h3>held-out part</h3>" + before_after_table(held)
                             + "</div>") if held is not None else "") + "</div>")
    part = "held-out part" if held is not None else "fit part (no held-out part)"
    return (tables + "<h3>Per class</h3>" + per_class_table(report.fit)
            + "<h3 id='coverage'>Served ellipses: coverage per class × range</h3>"
            + region_table(held if held is not None else report.fit, part)
            + renderer.report_plots(loaded))
