"""Issue 25, item 8: jobs need a token, versions are plain positive integers (activate
included), deleting `champion` is the documented 409, HEAD is answered wherever GET is."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.main import create_app
from tests.app.conftest import ADMIN

ROOT = Path(__file__).resolve().parents[3]


@pytest.mark.parametrize("path", ["/v1/jobs", "/v1/jobs/" + "0" * 32])
def test_jobs_need_the_admin_or_the_feedback_token(client, path):
    assert client.get(path).status_code == 401
    assert client.get(path, headers={"Authorization": "Bearer nope"}).status_code == 403
    assert client.get(path, headers=ADMIN).status_code in (200, 404)


@pytest.mark.parametrize("text", ["1.0", "%201", "1%20", "+1", "01", "1e0", "0x1", "%EF%BC%91"])
def test_a_version_is_plain_digits_in_every_path(client, text):
    for method, path in (("GET", f"/v1/profiles/lidar/{text}"),
                         ("POST", f"/v1/profiles/lidar/{text}/activate")):
        r = client.request(method, path, headers=ADMIN)
        assert r.status_code == 422, (method, path, r.text)
        assert r.json()["detail"][0]["loc"] == ["path", "version"]
    r = client.get("/v1/profiles/lidar/health", params={"version": text.replace("%20", " ")})
    assert r.status_code == 422, r.text
    assert client.get("/v1/profiles/lidar/1").status_code == 200
    assert client.get("/v1/audit", headers=ADMIN).json()["entries"] == []   # nothing activated


def test_a_reference_with_a_non_plain_version_is_refused(client):
    r = client.get("/v1/profiles/lidar/health", params={"version": "1"})
    assert r.status_code == 200
    for ref in ("lidar@1.0", "lidar@01", "lidar@+1"):
        r = client.post("/v1/calibrate", json={"profile": ref, "frames": [{"detections": []}]})
        assert r.status_code == 422, r.text
        assert r.json()["detail"][0]["loc"] == ["body", "profile"]


def test_deleting_champion_is_409_as_documented(client):
    r = client.delete("/v1/profiles/lidar/aliases/champion", headers=ADMIN)
    assert r.status_code == 409, r.text
    doc = (ROOT / "docs" / "production.md").read_text()
    assert "409 for `champion`" in doc


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/v1/profiles", "/v1/profiles/lidar",
                                  "/metrics", "/"])
def test_head_is_answered_wherever_get_is(client, path):
    get, head = client.get(path), client.head(path)
    assert head.status_code == get.status_code == 200, (path, head.status_code)
    assert head.content == b""
    assert head.headers["content-type"] == get.headers["content-type"]


def test_head_where_get_is_not_allowed_is_405(client):
    assert client.head("/v1/fit").status_code == 405


def test_the_feedback_token_may_read_jobs_but_not_the_audit(seeded):
    from pydantic import SecretStr

    settings = seeded.model_copy(update={"feedback_token": SecretStr("feedback-token-abc")})
    with TestClient(create_app(settings)) as c:
        fb = {"Authorization": "Bearer feedback-token-abc"}
        assert c.get("/v1/jobs", headers=fb).status_code == 200
        assert c.get("/v1/jobs/" + "0" * 32, headers=fb).status_code == 404
        assert c.get("/v1/audit", headers=fb).status_code == 403
