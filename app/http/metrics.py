"""Prometheus metrics of one app instance and the ASGI middleware that records requests."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from typing import Any

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest, multiprocess
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.feedback.health_document import window_counts
from app.store import HealthOverview, Store
from app.store.records import JOB_STATES
from calibrators.monitoring import HealthCounts

#: Set (to a directory) when several worker processes share their counters.
MULTIPROC_ENV = "PROMETHEUS_MULTIPROC_DIR"
_BUCKETS = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


class _StoreCollector(Collector):
    """Fit jobs by state, the active version of every profile and the feedback health of every
    version that has feedback (over all of it, and over the rolling window of the last
    `window_frames` frames, as `GET /v1/profiles/{name}/health`), read at scrape time."""

    def __init__(self, store: Store, window_frames: int) -> None:
        self.store = store
        self.window_frames = window_frames

    def collect(self) -> Iterator[GaugeMetricFamily]:
        jobs = GaugeMetricFamily("detcal_fit_jobs", "Fit jobs by state.", labels=["state"])
        counts = self.store.job_counts()
        for state in JOB_STATES:
            jobs.add_metric([state], counts.get(state, 0))
        yield jobs
        active = GaugeMetricFamily("detcal_active_profile_version",
                                   "Active version of each profile name.", labels=["profile"])
        for name, version in sorted(self.store.active_versions().items()):
            active.add_metric([name], version)
        yield active
        rows = self.store.health_overview()
        totals = [HealthCounts.from_dict(json.loads(row.latest.counts)) for row in rows]
        windows = [window_counts(self.store, row.profile_id, row.latest, total,
                                 self.window_frames) for row, total in zip(rows, totals,
                                                                           strict=True)]
        yield from health_metrics(rows, totals, windows)


HEALTH_STATUSES = ("ok", "degraded", "insufficient")


def health_metrics(rows: list[HealthOverview], totals: list[HealthCounts],
                   windows: list[HealthCounts]
                   ) -> Iterator[GaugeMetricFamily | CounterMetricFamily]:
    """Feedback health of each version, one per row: status (one-hot) and the drift alarms
    raised (a counter); ECE, coverage per served level and frames over all its feedback
    (`totals`, the sums of each row) and over its rolling window (`windows`, the figures
    `GET /v1/profiles/{name}/health` shows as `window`)."""
    labels = ["profile", "version"]
    status = GaugeMetricFamily("detcal_profile_health_status", "Health status of a profile "
                               "version (1 for its status).", labels=[*labels, "status"])
    ece = GaugeMetricFamily("detcal_profile_health_ece", "ECE of the calibrated scores on "
                            "feedback.", labels=labels)
    coverage = GaugeMetricFamily("detcal_profile_health_coverage", "Fraction of true centres "
                                 "inside the served ellipses on feedback.",
                                 labels=[*labels, "level"])
    frames = GaugeMetricFamily("detcal_profile_health_frames", "Feedback frames received.",
                               labels=labels)
    alarms = CounterMetricFamily("detcal_drift_alarms", "Drift alarms raised on feedback.",
                                 labels=labels)
    w_ece = GaugeMetricFamily("detcal_profile_health_window_ece", "ECE of the calibrated "
                              "scores over the rolling feedback window.", labels=labels)
    w_coverage = GaugeMetricFamily("detcal_profile_health_window_coverage", "Fraction of true "
                                   "centres inside the served ellipses over the rolling "
                                   "feedback window.", labels=[*labels, "level"])
    w_frames = GaugeMetricFamily("detcal_profile_health_window_frames", "Feedback frames in "
                                 "the rolling window.", labels=labels)
    for row, total, window in zip(rows, totals, windows, strict=True):
        key = [row.name, str(row.version)]
        levels = json.loads(row.latest.drift)["levels"]
        for s in HEALTH_STATUSES:
            status.add_metric([*key, s], float(row.latest.status == s))
        _add_figures((ece, coverage, frames), key, levels, total)
        alarms.add_metric(key, row.latest.alarms_total)
        _add_figures((w_ece, w_coverage, w_frames), key, levels, window)
    yield from (status, ece, coverage, frames, alarms, w_ece, w_coverage, w_frames)


def _add_figures(families: tuple[GaugeMetricFamily, GaugeMetricFamily, GaugeMetricFamily],
                 key: list[str], levels: list[float], counts: HealthCounts) -> None:
    """Add one version's ECE, coverage per served level and frames of `counts` to the
    (ece, coverage, frames) gauge families; an undefined figure (no detections) is left out."""
    ece, coverage, frames = families
    value = counts.ece()
    if value is not None:
        ece.add_metric(key, value)
    for level, cov in zip(levels, counts.coverage(), strict=True):
        if cov is not None:
            coverage.add_metric([*key, f"{level:g}"], cov)
    frames.add_metric(key, counts.frames)


class ServiceMetrics:
    """The registry and instruments of one app (a fresh registry per app keeps tests apart)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        self.started = time.time()
        self.requests = Counter("detcal_http_requests", "HTTP requests by route.",
                                ["method", "route", "status"], registry=self.registry)
        self.latency = Histogram("detcal_http_request_duration_seconds",
                                 "Server time per request by route.", ["method", "route"],
                                 buckets=_BUCKETS, registry=self.registry)
        self.detections = Counter("detcal_detections_calibrated",
                                  "Detections calibrated.", ["profile"], registry=self.registry)
        self._store_collector: _StoreCollector | None = None

    def attach_store(self, store: Store, window_frames: int) -> None:
        """Report fit jobs, active versions and feedback health of `store` (once the
        lifespan opened it); `window_frames` is the health window (settings)."""
        if self._store_collector is not None:
            self.registry.unregister(self._store_collector)
        self._store_collector = _StoreCollector(store, window_frames)
        self.registry.register(self._store_collector)

    def _scrape_registry(self) -> CollectorRegistry:
        """This app's registry; under several worker processes (`PROMETHEUS_MULTIPROC_DIR`,
        set by `detcal serve --workers N`), the counters and histograms of every worker
        summed from their files, plus the store's gauges (the same in every worker)."""
        if not os.environ.get(MULTIPROC_ENV):
            return self.registry
        registry = CollectorRegistry()
        multiprocess.MultiProcessCollector(registry)
        if self._store_collector is not None:
            registry.register(self._store_collector)
        return registry

    def exposition(self) -> bytes:
        """The Prometheus text exposition of `_scrape_registry`."""
        return generate_latest(self._scrape_registry())

    def request_totals(self) -> dict[str, float]:
        """Request count per route (all methods and statuses, all workers), for the
        dashboard."""
        totals: dict[str, float] = {}
        registry = self._scrape_registry()
        metrics = (self.requests.collect() if registry is self.registry
                   else (m for m in registry.collect() if m.name == "detcal_http_requests"))
        for metric in metrics:
            for sample in metric.samples:
                if sample.name.endswith("_total"):
                    route = sample.labels["route"]
                    totals[route] = totals.get(route, 0.0) + sample.value
        return totals


#: Methods counted under their own name; any other is counted as `other`.
METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})


def request_labels(scope: Scope) -> tuple[str, str]:
    """The `method` and `route` labels of a request, from bounded sets whatever the client
    sends: a method outside `METHODS` is `other`, a path no route matched is `unmatched`."""
    method = scope.get("method", "GET")
    route: Any = scope.get("route")
    return (method if method in METHODS else "other",
            getattr(route, "path", None) or "unmatched")


class MetricsMiddleware:
    """Counts requests and observes latency per route template (labels from `request_labels`,
    so their number is bounded); adds a `Server-Timing` header."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = {"code": 500}

        async def send_wrapper(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
                dur = (time.perf_counter() - start) * 1000.0
                headers = list(message.get("headers", []))
                headers.append((b"server-timing", f"app;dur={dur:.3f}".encode()))
                message = {**message, "headers": headers}
            await send(message)

        try:
            await self.app(scope, receive, send_wrapper)
        finally:
            method, path = request_labels(scope)
            self.metrics.requests.labels(method, path, str(status["code"])).inc()
            self.metrics.latency.labels(method, path).observe(time.perf_counter() - start)
