"""Profiles: listing, versions, detail, activation and roll-back, readiness, admin token rules."""

from __future__ import annotations

from fastapi.testclient import TestClient

from app.main import create_app
from app.settings import Settings
from app.store import Store

ADMIN = {"Authorization": "Bearer test-admin-token-0123456789"}


def test_list_and_detail(client):
    names = {p["name"]: p for p in client.get("/v1/profiles").json()}
    assert names["lidar"]["active_version"] == 1 and names["layers"]["n_versions"] == 1
    detail = client.get("/v1/profiles/lidar/1").json()
    for key in ("temperature", "depth_k", "pooled_k", "classes", "score_mode", "cov_dims",
                "report", "provenance"):
        assert key in detail["profile"]
    assert detail["id"] == "lidar@1" and detail["active"]


def test_activate_then_roll_back_changes_what_calibrate_uses(seeded, profile_json_layers):
    store = Store(seeded.sqlalchemy_url, seeded.dumps_dir)
    store.add_profile("lidar", profile_json_layers)               # lidar@2, not active
    store.close()
    det = {"score": 0.6, "label": "car", "box": [30, 0, 1, 2, 4, 1.5, 0, 0, 0],
           "covariance": [[0.1, 0], [0, 0.1]]}
    with TestClient(create_app(seeded)) as c:
        body = {"frames": [{"detections": [det]}]}
        assert c.post("/v1/calibrate", json=body).json()["profile"]["id"] == "lidar@1"
        r = c.post("/v1/profiles/lidar/2/activate", headers=ADMIN)
        assert r.status_code == 200 and r.json()["active"]
        assert c.get("/readyz").json()["checks"]["profile"] == "lidar@2"
        # lidar@2 takes covariance from layer boxes: the same request is now a 422 saying so
        r = c.post("/v1/calibrate", json=body)
        assert r.status_code == 422 and "cov_source" in r.json()["detail"][0]["msg"]
        assert c.post("/v1/profiles/lidar/1/activate", headers=ADMIN).status_code == 200
        assert c.post("/v1/calibrate", json=body).json()["profile"]["id"] == "lidar@1"
        assert 'detcal_active_profile_version{profile="lidar"} 1.0' in c.get("/metrics").text


def test_readyz_and_healthz(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200 and ready.json()["checks"] == {"store": "ok",
                                                                   "profile": "lidar@1"}


def test_not_ready_without_a_profile(empty_client):
    assert empty_client.get("/healthz").status_code == 200
    not_ready = empty_client.get("/readyz")
    assert not_ready.status_code == 503 and "does not exist" in not_ready.json()["checks"][
        "profile"]


def test_admin_is_refused_without_a_configured_token(tmp_path):
    settings = Settings(data_dir=tmp_path / "d")
    assert settings.admin_token is None
    with TestClient(create_app(settings)) as c:
        r = c.post("/v1/profiles/lidar/1/activate", headers={"Authorization": "Bearer x"})
        assert r.status_code == 403 and r.json()["detail"] == "admin token not configured"


def test_token_file_configures_admin(tmp_path):
    data = tmp_path / "d"
    data.mkdir()
    (data / "admin_token").write_text("from-file-token\n")
    settings = Settings(data_dir=data)
    assert settings.admin_token is not None
    assert settings.admin_token.get_secret_value() == "from-file-token"
    assert "from-file-token" not in repr(settings)


def test_openapi_documents_every_endpoint_with_examples(client):
    spec = client.get("/openapi.json").json()
    paths = spec["paths"]
    for path in ("/v1/calibrate", "/v1/calibrate/nuscenes", "/v1/fit", "/v1/jobs/{job_id}",
                 "/v1/profiles", "/v1/profiles/{name}", "/v1/profiles/{name}/{version}",
                 "/v1/profiles/{name}/{version}/activate", "/v1/detect", "/healthz",
                 "/readyz", "/metrics"):
        assert path in paths, path
    assert spec["components"]["schemas"]["CalibrateRequest"]["examples"]
    assert paths["/v1/calibrate"]["post"]["summary"]
