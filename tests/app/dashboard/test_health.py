"""The dashboard's calibration-health section: a note before feedback, the status and the
time series after it."""

from __future__ import annotations

from calibrators.data import synthetic_dump
from tests.app.conftest import ADMIN
from tests.app.feedback_frames import feedback_frames


def test_the_dashboard_shows_health_as_a_time_series(client):
    page = client.get("/").text
    assert "calibration-health" in page and "No labelled feedback yet" in page
    frames = feedback_frames(synthetic_dump(n_frames=60, seed=11))
    for start in range(0, 60, 20):
        assert client.post("/v1/feedback", headers=ADMIN,
                           json={"frames": frames[start:start + 20]}).status_code == 200
    page = client.get("/").text
    assert "health-series" in page and page.count("<polyline") >= 5
    assert "lidar@1</b>: <span class='ok'>ok</span>" in page
    assert "coverage 90%" in page and "window ECE (right axis" in page
