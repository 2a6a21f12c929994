"""DETCAL_AUTO_REFIT: feedback that first degrades the champion queues a fit on the kept
feedback; its version lands as `challenger` and is not activated."""

from __future__ import annotations

from fastapi.testclient import TestClient

from app.main import create_app
from calibrators.data import DEFAULT_DEPTH_K, synthetic_dump
from tests.app.conftest import ADMIN
from tests.app.feedback_frames import feedback_frames


def test_a_degraded_champion_gets_a_challenger_never_activated(seeded, wait):
    settings = seeded.model_copy(update={"auto_refit": True})
    shifted = feedback_frames(synthetic_dump(
        n_frames=80, seed=12, depth_k={k: 6 * v for k, v in DEFAULT_DEPTH_K.items()}))
    with TestClient(create_app(settings)) as c:
        first = c.post("/v1/feedback", headers=ADMIN, json={"frames": shifted[:40]}).json()
        assert first["status"] == "degraded" and first["refit_job"] is not None
        job = wait(c, first["refit_job"])
        assert job["state"] == "succeeded", job
        assert job["profile"]["id"] == "lidar@2" and job["activate"] is False
        again = c.post("/v1/feedback", headers=ADMIN, json={"frames": shifted[40:]}).json()
        assert again["refit_job"] is None                 # once per degradation
        aliases = {a["alias"]: a["version"] for a in c.get(
            "/v1/profiles/lidar/aliases").json()["aliases"]}
        assert aliases == {"champion": 1, "challenger": 2}
        (fit,) = c.get("/v1/audit", headers=ADMIN, params={"action": "fit"}).json()["entries"]
        assert fit["token_id"] == "system:auto-refit" and fit["detail"]["alias"] == "challenger"
        assert fit["detail"]["feedback_frames"] == 40
        cal = c.post("/v1/calibrate", json={"profile": "lidar@challenger",
                                            "frames": [{"detections": shifted[0]["detections"]}]})
        assert cal.status_code == 200 and cal.json()["profile"]["id"] == "lidar@2"


def test_without_auto_refit_nothing_is_kept_or_queued(client):
    shifted = feedback_frames(synthetic_dump(
        n_frames=40, seed=12, depth_k={k: 6 * v for k, v in DEFAULT_DEPTH_K.items()}))
    body = client.post("/v1/feedback", headers=ADMIN, json={"frames": shifted}).json()
    assert body["status"] == "degraded" and body["refit_job"] is None
    store = client.app.state.store
    assert store.feedback_dumps(store.get("lidar", 1).id) == []
