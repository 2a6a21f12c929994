"""The health document of a profile version: status, figures over the rolling window and since
activation, the alarms and the time series, from the version's stored health rows."""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from app.calibrate.cache import LoadedProfile
from app.feedback.evidence import RULE, row_status
from app.store import HealthRecord, Store
from calibrators.monitoring import (
    HEALTH_LEVELS,
    N_SCORE_BINS,
    DriftMonitor,
    HealthCounts,
    health_figures,
    profile_edges,
    region_groups,
)

#: Points of the time series the document carries (the newest).
SERIES_POINTS = 200


def _counts(row: HealthRecord | None, zero: HealthCounts) -> HealthCounts:
    return zero if row is None else HealthCounts.from_dict(json.loads(row.counts))


def window_counts(store: Store, profile_id: int, latest: HealthRecord, total: HealthCounts,
                  window_frames: int) -> HealthCounts:
    """The sums of the rolling window of a version whose newest row is `latest` (its sums,
    already read, `total`): what came after its newest row holding at most
    `frames_total - window_frames` frames (everything when there is none). The health
    document and the Prometheus gauges both read it."""
    base = store.health_at_most(profile_id, latest.frames_total - window_frames)
    return total if base is None else total - HealthCounts.from_dict(json.loads(base.counts))


def health_document(store: Store, loaded: LoadedProfile, window_frames: int) -> dict[str, Any]:
    """The `HealthDocument` body of `loaded`'s version."""
    record, prof = loaded.record, loaded.profile
    latest = store.latest_health(record.id)
    if latest is None:
        groups = region_groups(prof)
        monitor = DriftMonitor(tuple(prof.classes), HEALTH_LEVELS,
                               tuple(profile_edges(prof).tolist()), groups.names, groups.n,
                               N_SCORE_BINS, RULE)
    else:
        monitor = DriftMonitor.from_dict(json.loads(latest.drift))
    classes, levels, edges = monitor.classes, monitor.levels, monitor.distance_edges
    zero = HealthCounts.zeros(len(classes), monitor.n_bins, len(edges) - 1, len(levels))
    total = _counts(latest, zero)
    window = zero if latest is None else window_counts(store, record.id, latest, total,
                                                       window_frames)
    activated = store.activated_at(record.name, record.version)
    since_base = None if latest is None or activated is None else store.health_before(
        record.id, activated)
    since = total - _counts(since_base, zero)

    def figures(counts: HealthCounts) -> dict[str, Any]:
        return health_figures(counts, classes, levels, edges)

    status = row_status(len(monitor.alarms), since)
    reasons = [a["reason"] for a in monitor.alarms] if status == "degraded" else [
        f"{since.frames} feedback frame(s) with {since.tp} true positive(s) since activation; "
        f"at least {RULE.min_frames} frames with a true positive are needed"
    ] if status == "insufficient" else []
    return {
        "profile": loaded.ref(), "status": status, "reasons": reasons,
        "activated_at": activated, "window_frames": window_frames,
        "window": figures(window), "since_activation": figures(since),
        "alarms": monitor.alarms,
        "alarm_rule": {**RULE.to_dict(), "n_tests": monitor.n_tests,
                       "log_threshold": monitor.log_threshold},
        "series": _series(store.health_series(record.id, SERIES_POINTS), zero, window_frames),
    }


def _series(rows: list[HealthRecord], zero: HealthCounts, window_frames: int
            ) -> list[dict[str, Any]]:
    """One point per row: the window's ECE and overall coverage per level after it."""
    counts = [_counts(r, zero) for r in rows]
    totals = [r.frames_total for r in rows]
    out = []
    for i, row in enumerate(rows):
        j = int(np.searchsorted(totals, row.frames_total - window_frames, side="right")) - 1
        if j >= 0:
            base = counts[j]
        else:   # the version's first row is fetched: the window starts at zero
            base = zero if rows[0].seq == 1 else counts[0]
        win = counts[i] - base
        out.append({"seq": row.seq, "created_at": row.created_at,
                    "frames_total": row.frames_total, "status": row.status,
                    "ece": win.ece(), "coverage": win.coverage()})
    return out
