"""GET /: the dashboard (server-rendered HTML with inline SVG plots; works offline)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi.responses import HTMLResponse

from app.dashboard.page import (
    DashboardRenderer,
    before_after_table,
    per_class_table,
    render_page,
    uptime,
    versions_table,
)
from app.deps import CacheDep, MetricsDep, SettingsDep, StoreDep
from app.store import NotFoundError

router = APIRouter(tags=["dashboard"])


def _renderer(request: Request) -> DashboardRenderer:
    return request.app.state.dashboard


RendererDep = Annotated[DashboardRenderer, Depends(_renderer)]


@router.get("/", response_class=HTMLResponse)
def dashboard(request: Request, store: StoreDep, cache: CacheDep, settings: SettingsDep,
              metrics: MetricsDep, renderer: RendererDep) -> HTMLResponse:
    """The dashboard: health, request rates, profiles, before/after report and plots."""
    ok = store.ping()
    status = {"store": "ok" if ok else "unreachable"}
    loaded = None
    try:
        loaded = cache.resolve(settings.default_profile, settings.default_profile)
        status["active profile"] = "ok"
    except (NotFoundError, ValueError) as exc:
        status["active profile"] = str(exc)
    status["readiness"] = "ready" if ok and loaded is not None else "not ready"
    report_html = bev_html = versions_html = ""
    if loaded is not None:
        versions_html = versions_table(store.versions(loaded.record.name))
        fit = loaded.profile.report.get("fit") or {}
        holdout = loaded.profile.report.get("holdout")
        report_html = ("<div class='plots'><div><h3>fit part</h3>" + before_after_table(fit)
                       + "</div>" + (("<div><h3>held-out part</h3>" + before_after_table(holdout)
                                      + "</div>") if holdout else "") + "</div>"
                       + "<h3>Per class</h3>" + per_class_table(fit)
                       + renderer.report_plots(loaded))
        bev_html = renderer.bev(loaded, request.app.state.detectors, settings.dashboard_sensor,
                                settings.dashboard_seed)
    page = render_page(
        version=request.app.version, status=status, uptime_s=uptime(metrics.started),
        requests=metrics.request_totals(), names=store.names(),
        default_name=settings.default_profile, loaded=loaded, versions_html=versions_html,
        report_html=report_html, bev_html=bev_html, jobs=store.recent_jobs(8))
    return HTMLResponse(page)
